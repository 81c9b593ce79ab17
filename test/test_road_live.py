"""The vehicle's own road in the live loop, over real DDS (docs/road.md "How to run it").

* state_estimator_node with ``road_at_tyre:=estimated`` is a managed node: unconfigured
  and inactive it publishes nothing; active it answers each ECU cycle with a state and a
  ``road/estimate`` of the same stamp (odometry distance + Ts·speed per cycle), reading no
  road topic; deactivated it stops.
* `erva run --ecu virtual --preview map:MAP` on a map built here from a simulated drive:
  on the live graph no loop node reads the true road or state; the previews come from the
  map (one per road estimate, same stamps), road/estimate and
  road/alignment are recorded (read back with the ``mcap`` reader), the summary has the
  map preview's counts.
* A missing, corrupt, other-route or too-short map: exit 2, one line, nothing started.
"""

import json
import os
import subprocess
import sys

from geometry_msgs.msg import PoseWithCovarianceStamped
from mcap.reader import make_reader
from sensor_msgs.msg import JointState
import pytest

from erva_ros.core import contract, topics
from erva_ros.core.hil import topics as hil_topics
from erva_ros.ros.lifecycle import LifecycleDriver
from erva_ros.ros.qos import control_qos
from live_harness import cleaned_up, Harness, REPO, ros_env, start_node, stop_node, TS_NS
import road_helpers as rh
from run_helpers import start_run, wait_connected
from test_lifecycle import _transition

pytestmark = pytest.mark.ros   # every test here starts DDS

SPEED = 20.0


def test_estimator_estimates_the_road_only_while_active(tmp_path):
    ns = '/erva_t_road_est'
    proc = start_node('state_estimator_node', ns, str(tmp_path / 'est.log'),
                      'autostart:=false', 'road_at_tyre:=estimated', f'speed_mps:={SPEED}')
    h = Harness(ns)
    with cleaned_up(proc, h):
        pub = h.node.create_publisher(JointState, hil_topics.ECU_MEASUREMENTS, control_qos(100))
        estimates = []
        h.node.create_subscription(
            PoseWithCovarianceStamped, topics.ROAD_ESTIMATE,
            lambda data: estimates.append(contract.decode_road_estimate(data, strict=True)),
            control_qos(100), raw=True)
        driver = LifecycleDriver(h.node, ['state_estimator_node'], ns)
        assert h.spin_until(driver.ready, 60.0)

        def play(n):
            def tick(k, stamp):
                pub.publish(contract.MEASUREMENTS_ENCODER.encode(
                    stamp + 500_000, [10000.0, 10000.0, 0.0, 0.0, 0.0, 0.0]))
            start = (h.node.get_clock().now().nanoseconds // TS_NS + 2) * TS_NS
            h.run_ticks(start, 0, n, tick)
            h.spin_for(0.3)

        play(10)
        assert h.states == [] and estimates == []                 # unconfigured
        assert _transition(h, driver, 'state_estimator_node', 'configure')
        assert h.wait_for_diag('state_estimator_node',
                               lambda r: r.lifecycle == 'inactive').road_at_tyre == 'estimated'
        play(10)
        assert h.states == [] and estimates == []                 # inactive
        assert _transition(h, driver, 'state_estimator_node', 'activate')
        h.spin_until(lambda: pub.get_subscription_count() >= 1, 30.0)
        play(40)
        assert len(estimates) >= 30
        assert [e.stamp_ns for e in estimates] == [s for s, _ in h.states]
        # Each cycle, received 0.5 ms after its k·Ts, is stamped with it (docs/hil.md §8).
        assert {e.stamp_ns % TS_NS for e in estimates} == {0}
        steps = {round(b.distance_m - a.distance_m, 9) for a, b in zip(estimates, estimates[1:])
                 if b.stamp_ns - a.stamp_ns == TS_NS}
        assert steps == {round(SPEED * TS_NS * 1e-9, 9)}       # odometry: Ts·speed a cycle
        assert all(e.var_w > 0 for e in estimates)
        assert _transition(h, driver, 'state_estimator_node', 'deactivate')
        h.spin_for(0.3)
        n = len(estimates)
        play(10)
        assert len(estimates) == n                                # inactive again
        report = h.wait_for_diag('state_estimator_node', lambda r: r.lifecycle == 'inactive')
        assert report.published[f'{ns}/{topics.ROAD_ESTIMATE}'] == n
        assert report.road_estimates == report.updates == n
        # It reads no road: its subscriptions are the ECU's only (and no road/height).
        assert h.node.count_subscribers(f'{ns}/{topics.ROAD_HEIGHT}') == 0
        assert stop_node(proc) == 0


@pytest.fixture(scope='module')
def road_map(tmp_path_factory):
    """Return a map of the paper road, seed 0, at 20 m/s: 12 s of a simulated drive."""
    d = tmp_path_factory.mktemp('map')
    run = rh.drive(rh.route(0, seconds=14.0), 1, seconds=12.0)
    rh.map_build([rh.write_bag(str(d / 'drive.mcap'), run)], str(d / 'paper.map'))
    return str(d / 'paper.map')


def _run(*args):
    return subprocess.run([sys.executable, '-m', 'erva_ros.cli', 'run', *map(str, args)],
                          capture_output=True, text=True, env=ros_env(), cwd=REPO,
                          timeout=600)


#: The loop's nodes: with the map preview none of them may read the true road or state.
LOOP_NODES = {'nmpc_node', 'state_estimator_node', 'ecu_bridge_node', 'road_preview_node',
              'plant_sim_node'}


def _readers(ns, names):
    """Return {topic: names of the nodes subscribed to it} as the live graph shows them.

    A node of its own (no publisher, no subscription) asks the graph until the simulated
    ECU's reader of the true road is seen, then once more a second later.
    """
    import time
    import rclpy
    ctx = rclpy.Context()
    rclpy.init(args=[], context=ctx)
    node = rclpy.create_node('test_graph_watch', context=ctx)
    try:
        def readers():
            return {t: {i.node_name for i in node.get_subscriptions_info_by_topic(f'{ns}/{t}')}
                    for t in names}
        end = time.monotonic() + 30.0
        while 'ecu_sim' not in readers()[names[0]] and time.monotonic() < end:
            time.sleep(0.1)
        time.sleep(1.0)
        return readers()
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def test_erva_run_previews_from_the_map_and_records_the_road(road_map, tmp_path):
    ns = '/erva_t_road_run'
    proc = start_run('--ecu', 'virtual', '--preview', f'map:{road_map}', '--duration', 6,
                     '--namespace', ns, '--record', tmp_path, '--json')
    try:
        wait_connected(proc)
        graph = _readers(ns, (topics.ROAD_HEIGHT, hil_topics.TRUE_STATE))
        out, err = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err[-3000:]
    # The true road and state reach the simulated ECU and the session's observers only.
    assert 'ecu_sim' in graph[topics.ROAD_HEIGHT], graph
    assert not any(names & LOOP_NODES for names in graph.values()), graph
    s = json.loads(out)
    m = s['road']['map']
    est = s['hil']['estimator']
    assert m['samples'] == est['updates'] > 250            # one preview per road estimate
    assert est['error']['matched'] > 250       # estimates on their own grid, paired by cycle
    assert m['points'] == m['samples'] * 11
    assert m['alignments'] >= 1 and m['fallback_points'] < m['points']
    assert s['messages']['dropped_total'] == 0
    counts, stamps = {}, {}
    mcap, = [f for f in os.listdir(s['bag']) if f.endswith('.mcap')]
    with open(os.path.join(s['bag'], mcap), 'rb') as fh:
        for _, channel, message in make_reader(fh).iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if channel.topic in (f'{ns}/{topics.ROAD_ESTIMATE}', f'{ns}/{topics.ROAD_PREVIEW}',
                                 f'{ns}/{topics.ROAD_ALIGNMENT}'):
                stamps.setdefault(channel.topic, []).append(
                    contract.DECODERS[channel.topic[len(ns) + 1:]](message.data).stamp_ns)
    assert counts[f'{ns}/{topics.ROAD_ESTIMATE}'] == est['updates']
    assert counts[f'{ns}/{topics.ROAD_ALIGNMENT}'] == m['samples']
    assert stamps[f'{ns}/{topics.ROAD_PREVIEW}'] == stamps[f'{ns}/{topics.ROAD_ESTIMATE}'] \
        == stamps[f'{ns}/{topics.ROAD_ALIGNMENT}']
    assert 'map' in _run_text(s)
    # Reported, replayed and a map drive like any other session.
    bag = s['bag']
    rep = subprocess.run([sys.executable, '-m', 'erva_ros.cli', 'report', bag, '--json'],
                         capture_output=True, text=True, env=ros_env(), cwd=REPO, timeout=300)
    assert rep.returncode == 0, rep.stderr[-2000:]
    assert json.loads(rep.stdout)['samples']['damping_cmd'] == counts[f'{ns}/damping_cmd']
    play = subprocess.run([sys.executable, '-m', 'erva_ros.cli', 'replay', bag, '--rate', '4',
                           '--json'], capture_output=True, text=True, env=ros_env(),
                          cwd=REPO, timeout=300)
    assert play.returncode == 0, play.stderr[-2000:]
    assert json.loads(play.stdout)['total'] == sum(counts.values())
    rh.map_build([bag], str(tmp_path / 'next.map'))


def _run_text(summary):
    from erva_ros.session.run.report import format_summary
    return format_summary(summary)


def test_a_bad_map_stops_erva_run_before_anything_starts(road_map, tmp_path):
    corrupt = tmp_path / 'corrupt.map'
    corrupt.write_bytes(b'not a database' * 100)
    other = tmp_path / 'other.map'
    run = rh.drive(rh.route(1, seconds=14.0), 1, seconds=12.0)
    rh.map_build([rh.write_bag(str(tmp_path / 'seed1.mcap'), run, road_seed=1)], str(other))
    cases = {'no such map file': (tmp_path / 'missing.map', ()),
             'not a readable road map': (corrupt, ()),
             'the map is of route': (other, ()),
             'the map covers': (road_map, ('--duration', 20))}
    for why, (path, extra) in cases.items():
        bags = tmp_path / f'bags_{len(why)}'
        r = _run('--ecu', 'virtual', '--preview', f'map:{path}', '--record', bags, *extra)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1, r.stderr
        assert lines[0].startswith('erva run: error: --preview map: ') and why in lines[0]
        assert not bags.exists()                               # nothing started
    r = _run('--preview', f'map:{road_map}', '--no-record')
    assert r.returncode == 2 and 'needs --ecu virtual' in r.stderr


def test_a_server_map_is_fetched_first_and_the_loop_never_needs_the_server(road_map, tmp_path):
    """Fetch a server map's section first; the loop never needs the server.

    `--preview map:postgresql://...`: the section is fetched into the local cache before
    anything starts; the server is stopped right after and the run goes on; a second run
    with the server gone from the start uses the cache (one WARN line).  The URI's password
    is in no output, bag or summary.
    """
    import map_server
    if map_server.bindir() is None:
        if os.environ.get(map_server.ENV):
            pytest.fail('PostgreSQL binaries missing under .ci/run')
        pytest.skip('no PostgreSQL server binaries (apt-get install postgresql-15)')
    secret = 'S3cr3tPw'
    base = map_server.new_base()
    try:
        server = map_server.new_database(map_server.start(base))
        uri = server.replace('postgres@', f'postgres:{secret}@', 1)   # trust: unused
        r = subprocess.run([sys.executable, '-m', 'erva_ros.cli', 'map', 'migrate', road_map,
                            uri], capture_output=True, text=True, env=ros_env(), cwd=REPO)
        assert r.returncode == 0, r.stderr
        env = {'ERVA_MAP_CACHE_DIR': str(tmp_path / 'cache')}
        outputs = []
        for n, up in enumerate((True, False)):
            proc = subprocess.Popen(
                [sys.executable, '-m', 'erva_ros.cli', 'run', '--ecu', 'virtual', '--preview',
                 f'map:{uri}', '--duration', '4', '--namespace', f'/erva_t_road_pg{n}',
                 '--record', str(tmp_path / f'bags{n}'), '--json'], stdout=subprocess.PIPE,
                stderr=subprocess.PIPE, text=True, env=ros_env(env), cwd=REPO,
                start_new_session=True)
            try:
                first = proc.stderr.readline()
                if up:
                    assert first.startswith('map: fetched '), first
                    map_server.stop(base, remove=False)          # the loop has not started
                else:
                    assert first.startswith('WARN map server unreachable ('), first
                lines = [first]
                wait_connected(proc, lines=lines)
                out, err = proc.communicate(timeout=600)
            finally:
                if proc.poll() is None:
                    proc.kill()
            assert proc.returncode == 0, err[-3000:]
            err = ''.join(lines) + err
            warns = sum('map server unreachable' in x for x in err.splitlines())
            assert warns == (0 if up else 1)
            s = json.loads(out)
            assert s['road']['map']['samples'] > 150 and s['road']['map']['alignments'] >= 1
            outputs += [out, err]
            for folder, _, files in os.walk(tmp_path / f'bags{n}'):
                for f in files:
                    with open(os.path.join(folder, f), 'rb') as fh:
                        assert secret.encode() not in fh.read(), f
        assert not any(secret in o for o in outputs)
        assert all('postgres@' in o or 'postgresql' not in o for o in outputs)
    finally:
        map_server.stop(base)
