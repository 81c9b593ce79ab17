"""Managed (lifecycle) nodes over real DDS: nothing acts before it is active, and on again.

* nmpc_node started with ``autostart:=false`` stays unconfigured and publishes no
  command, and refuses a transition it has none for (activate) without dying;
  configured it is inactive and still publishes none; active, it answers every state;
  deactivated it stops (inputs dropped); activated again it answers again; cleaned up
  and configured again it is a new controller.  Its report names its state.
* `erva run` configures its nodes, activates them in the documented order, and a
  deactivate of the controller mid-run (as `ros2 lifecycle set` does) sends the plant to
  the plan, then to passive damping; re-activated, commands act again.
"""

import json
import math

import numpy as np
import pytest
from lifecycle_msgs.srv import GetState

from erva_ros.ros.lifecycle import LifecycleDriver
import ros_msgs as msgs
from live_harness import cleaned_up, Harness, start_node, stop_node, TS_NS
from run_helpers import SampleWatch, start_run, wait_connected

pytestmark = pytest.mark.ros   # every test here starts DDS


def _state(k):
    x = np.zeros(6)
    x[0], x[1] = 1e-3 * math.sin(0.3 * k), 1e-2 * math.cos(0.3 * k)
    return x


def _transition(h, driver, name, transition):
    driver.request(name, transition)
    result = []
    assert h.spin_until(lambda: result.append(driver.result(name)) or result[-1] is not None,
                        60.0), f'{name}: no answer to {transition}'
    return result[-1]


def _get_state(h, client):
    future = client.call_async(GetState.Request())
    assert h.spin_until(future.done, 30.0)
    return future.result().current_state.label


def test_nmpc_node_acts_only_while_active(tmp_path):
    ns = '/erva_t_lifecycle'
    proc = start_node('nmpc_node', ns, str(tmp_path / 'nmpc.log'), 'controller:=skyhook',
                      'duration_s:=100.0', 'autostart:=false')
    h = Harness(ns)
    with cleaned_up(proc, h):
        driver = LifecycleDriver(h.node, ['nmpc_node'], ns)
        get_state = h.node.create_client(GetState, f'{ns}/nmpc_node/get_state')
        assert h.spin_until(lambda: driver.ready() and get_state.service_is_ready(), 60.0)
        assert _get_state(h, get_state) == 'unconfigured'
        # A transition its state has none for is refused, and the node lives on (rclpy's
        # own service raised, which ended the node: two sessions at once crashed so).
        assert _transition(h, driver, 'nmpc_node', 'activate') is False
        assert proc.poll() is None and _get_state(h, get_state) == 'unconfigured'
        stamps = []

        def tick(k, stamp):
            h.pub_preview.publish(msgs.preview_msg(stamp, np.zeros(11), TS_NS))
            h.pub_state.publish(msgs.state_msg(stamp, _state(k), 'erva'))
            stamps.append(stamp)

        def play(k0, n):
            start = (h.node.get_clock().now().nanoseconds // TS_NS + 2) * TS_NS
            h.run_ticks(start - k0 * TS_NS, k0, k0 + n, tick)
            h.spin_for(0.3)          # what is in flight arrives
            return start - k0 * TS_NS

        play(0, 10)
        assert h.commands == []                                    # unconfigured
        assert _transition(h, driver, 'nmpc_node', 'configure')
        assert _get_state(h, get_state) == 'inactive'
        h.wait_matched([h.pub_state, h.pub_preview], [h.sub_cmd])
        play(10, 10)
        assert h.commands == []                                    # inactive
        assert h.last_diag('nmpc_node').lifecycle == 'inactive'

        assert _transition(h, driver, 'nmpc_node', 'activate')
        assert _get_state(h, get_state) == 'active'
        first = len(stamps)
        play(20, 20)
        # Active: it answers the states (and, once they stop, sends the safe command).
        assert len({c[0] for c in h.commands} & set(stamps[first:])) >= 15

        assert _transition(h, driver, 'nmpc_node', 'deactivate')
        h.spin_for(0.3)
        n = len(h.commands)
        play(40, 20)
        assert len(h.commands) == n                 # inactive: nothing, safe command neither
        assert _transition(h, driver, 'nmpc_node', 'activate')
        again = len(stamps)
        play(60, 20)
        assert len({c[0] for c in h.commands[n:]} & set(stamps[again:])) >= 15

        # Back to unconfigured and up again: a new controller on the same process.
        assert _transition(h, driver, 'nmpc_node', 'deactivate')
        assert _transition(h, driver, 'nmpc_node', 'cleanup')
        assert _get_state(h, get_state) == 'unconfigured'
        assert _transition(h, driver, 'nmpc_node', 'configure')
        assert _transition(h, driver, 'nmpc_node', 'activate')
        m = len(h.commands)
        h.wait_matched([h.pub_state, h.pub_preview], [h.sub_cmd])
        again = len(stamps)
        play(80, 20)
        assert len({c[0] for c in h.commands[m:]} & set(stamps[again:])) >= 15
        # Its report counts what its new publisher published, safe commands too.
        assert _transition(h, driver, 'nmpc_node', 'deactivate')
        h.spin_for(0.3)
        report = h.wait_for_diag('nmpc_node', lambda r: r.lifecycle == 'inactive')
        assert report.published[f'{ns}/damping_cmd'] == len(h.commands) - m
        assert stop_node(proc) == 0


def _run_deactivating(args, nodes):
    """Run ``erva run ARGS``, deactivating ``nodes`` in turn; return (summary, bring-up line).

    Each node is deactivated mid-run for 25 samples, then active again for 50.
    """
    watch = SampleWatch()
    proc = start_run(*args, '--no-record', '--json')
    try:
        lines = []
        wait_connected(proc, lines=lines)
        driver = LifecycleDriver(watch.node, list(nodes), '/erva')
        watch.spin_until(driver.ready, lambda: 'no lifecycle service', proc=proc)

        def transition(node, name):
            driver.request(node, name)
            got = []
            watch.spin_until(lambda: got.append(driver.result(node)) or got[-1],
                             lambda: f'{node} did not {name}', proc=proc)

        watch.wait(50, proc=proc)
        for node in nodes:
            transition(node, 'deactivate')
            watch.wait(watch.samples + 25, proc=proc)        # 0.5 s without a command
            transition(node, 'activate')
            watch.wait(watch.samples + 50, proc=proc)        # 1 s of control
        out, err = proc.communicate(timeout=240)
    finally:
        watch.close()
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err[-2000:]
    bring_up = [line for line in lines if 'activating them in this order' in line]
    assert len(bring_up) == 1
    return json.loads(out), bring_up[0]


def test_erva_run_brings_nodes_up_in_order_and_a_deactivated_controller_is_replaced():
    s, bring_up = _run_deactivating(('--duration', 6, '--controller', 'skyhook'),
                                    ['nmpc_node'])
    assert 'nmpc_node, plant_sim_node, road_preview_node' in bring_up
    plant = s['plant']
    # The plan of the last command served its horizon, then passive damping; then the
    # commands acted again.
    assert plant['u_from_plan'] >= 1 and plant['u_from_passive'] >= 10
    assert plant['u_from_command'] >= 100
    assert s['nmpc']['commands'] < s['plant']['steps']


def _episodes(mode_changes):
    """Return the ECU's passive episodes: the modes from each leaving CONTROLLED to the next."""
    modes = [item.split(':')[1] for item in mode_changes.split(',') if item]
    episodes, current = [], None
    for mode in modes:
        if mode == 'CONTROLLED':
            if current:
                episodes.append(current)
            current = []
        elif current is not None:
            current.append(mode)
    return episodes, current


def test_erva_run_ecu_brings_the_bridge_up_and_the_ecu_goes_passive_without_commands():
    # HIL with d = 10 ms (the ECU applies each cycle's frame at t_k + d; the bridge sends
    # the plan ahead).  The controller deactivated: the ECU lives on the plan, then goes
    # passive (SAFE_TIMEOUT: the plan ran out, or SAFE_REQUESTED: the bridge's safe
    # command); the bridge deactivated: it sends nothing at all, and the ECU's own rule
    # (the plan ran out) makes it passive.  Each time, re-activated, CONTROLLED again.
    s, bring_up = _run_deactivating(('--ecu', 'virtual', '--duration', 10, '--controller',
                                     'skyhook', '--command-delay', 0.01),
                                    ['nmpc_node', 'ecu_bridge_node'])
    assert ('nmpc_node, state_estimator_node, ecu_bridge_node, road_preview_node'
            in bring_up)
    ecu = s['hil']['ecu']
    episodes, last = _episodes(ecu['mode_changes'])
    assert len(episodes) >= 2 and last == [], ecu['mode_changes']   # controlled at the end
    assert all(e and set(e) <= {'SAFE_TIMEOUT', 'SAFE_REQUESTED'} for e in episodes), episodes
    # The bridge's episode (the last one): nothing came, the plan ran out first.
    assert episodes[-1][0] == 'SAFE_TIMEOUT', episodes
    assert ecu['command_timeouts'] >= 1 and ecu['mode_changes_unlogged'] == 0
    assert ecu['command_timeouts'] == sum(e.count('SAFE_TIMEOUT') for e in episodes)
    # Each cycle's damping: its command, an earlier command's plan, or passive c_e0.
    plant = s['plant']
    assert plant['u_from_plan'] >= 2 and plant['u_from_passive'] >= 20
    assert plant['u_from_command'] >= 100
