"""The shipped SROS2 policy (config/sros2_policy.xml) allows exactly what the live nodes do.

The PyPI Fast DDS has no DDS-Security plugins, so secured nodes cannot run here; what
can be checked is the policy itself: well formed in the sros2 0.2.0 format, and every
endpoint the real nodes create in a recorded `erva run` (read from the live ROS graph)
is allowed by the profile of that node -- and the loop topics by no other writer.
"""

import fnmatch
import os
import time
import xml.etree.ElementTree as ET

import pytest

from conftest import REPO
from run_helpers import start_run, wait_connected

POLICY = os.path.join(REPO, 'config', 'sros2_policy.xml')
NS = '/erva'


def _resolve(name, node):
    if name.startswith('~/'):
        return f'{NS}/{node}/{name[2:]}'
    return name if name.startswith('/') else f'{NS}/{name}'


def load_policy():
    """Return {node: {'publish': [patterns], 'subscribe': [...], 'reply': [...]}}."""
    root = ET.parse(POLICY).getroot()
    assert root.tag == 'policy' and root.get('version') == '0.2.0'
    out = {}
    for enclave in root.find('enclaves'):
        assert enclave.tag == 'enclave' and enclave.get('path').startswith(NS + '/')
        for profile in enclave.find('profiles'):
            assert profile.get('ns') == NS
            node = profile.get('node')
            rules = out.setdefault(node, {'publish': [], 'subscribe': [], 'reply': []})
            for group in profile:
                names = [_resolve(e.text.strip(), node) for e in group]
                for kind in ('publish', 'subscribe', 'reply'):
                    if group.get(kind) == 'ALLOW':
                        rules[kind] += names
    return out


def allowed(patterns, name):
    return any(fnmatch.fnmatchcase(name, p) for p in patterns)


def test_policy_gives_each_loop_topic_exactly_its_writers():
    from erva_ros.core import topics
    from erva_ros.core.hil import topics as hil
    policy = load_policy()
    writers = {
        topics.STATE: {'plant_sim_node', 'state_estimator_node'},
        topics.SPRUNG_ACCEL: {'plant_sim_node', 'ecu_sim'},
        topics.GENERATOR: {'plant_sim_node', 'ecu_sim'},
        topics.ROAD_HEIGHT: {'road_preview_node'},
        topics.ROAD_PREVIEW: {'road_preview_node'},
        topics.DAMPING_CMD: {'nmpc_node'},
        hil.ECU_MEASUREMENTS: {'ecu_bridge_node'},
        hil.TRUE_STATE: {'ecu_sim'},
    }
    for topic, nodes in writers.items():
        name = f'{NS}/{topic}'
        got = {n for n, r in policy.items() if allowed(r['publish'], name)}
        assert got == nodes, (topic, got)
    assert allowed(policy['nmpc_node']['subscribe'], f'{NS}/state')
    assert not allowed(policy['nmpc_node']['publish'], f'{NS}/state')
    assert not allowed(policy['erva_run_monitor']['publish'], f'{NS}/damping_cmd')


@pytest.mark.ros
def test_policy_allows_every_endpoint_of_a_live_session(tmp_path):
    import rclpy
    policy = load_policy()
    # The probe exists before the session's nodes: it learns of them while they start,
    # not in the few seconds the run lasts after it connected.
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('policy_probe', context=context)
    proc = start_run('--duration', 3, '--record', tmp_path, '--json')
    seen = {}
    try:
        wait_connected(proc)
        names = ('plant_sim_node', 'road_preview_node', 'nmpc_node', 'recorder',
                 'erva_run_monitor')
        end = time.monotonic() + 20
        while time.monotonic() < end and len(seen) < len(names):
            for n in names:
                try:
                    pubs = node.get_publisher_names_and_types_by_node(n, NS)
                    subs = node.get_subscriber_names_and_types_by_node(n, NS)
                    srvs = node.get_service_names_and_types_by_node(n, NS)
                except Exception:     # not discovered yet
                    continue
                if pubs or subs:
                    seen[n] = ([t for t, _ in pubs], [t for t, _ in subs],
                               [s for s, _ in srvs])
            time.sleep(0.2)
        node.destroy_node()
        proc.communicate(timeout=120)
    finally:
        rclpy.try_shutdown(context=context)
        if proc.poll() is None:
            proc.kill()
    assert set(seen) == {'plant_sim_node', 'road_preview_node', 'nmpc_node', 'recorder',
                         'erva_run_monitor'}, seen
    for n, (pubs, subs, srvs) in seen.items():
        for t in pubs:
            assert allowed(policy[n]['publish'], t), (n, 'publishes', t)
        for t in subs:
            assert allowed(policy[n]['subscribe'], t), (n, 'subscribes', t)
        for s in srvs:
            assert allowed(policy[n]['reply'], s), (n, 'serves', s)
