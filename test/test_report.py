"""``erva report``: the figures computed from a bag alone agree with what produced the bag."""

import json
import os

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import AccelStamped
import pytest
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from erva_ros.core.model.quarter_car import make_model
from erva_ros.session.bag.offline_bag import run_and_record

from erva_ros.ros.bag_messages import write_message
from erva_ros.core.bag.writer import BagWriter
from erva_ros.core.controllers import make_controller
from erva_ros.core.model.params import load_erva_params
from erva_ros.core.road.profiles import make_road

T0 = 1_800_000_000 * 10 ** 9
MS = 1_000_000


@pytest.fixture(scope='module')
def offline_session(tmp_path_factory):
    """Return a 2 s passive session on the paper road, from the offline closed loop."""
    params = load_erva_params(None)
    bag = str(tmp_path_factory.mktemp('report') / 'passive')
    model = make_model(params)
    result, _ = run_and_record(bag, model, make_controller('passive', model),
                               make_road('paper', 2.0, seed=3), 2.0,
                               session={'scenario': 'paper', 'controller': 'passive',
                                        'seed': '3'})
    return bag, result


def test_comfort_and_power_equal_the_closed_loops(erva, offline_session, tmp_path):
    bag, result = offline_session
    out = tmp_path / 'plots'
    report = json.loads(erva('report', bag, '--json', '--out', out, check=True).stdout)
    assert report['samples']['sprung_accel'] == report['samples']['damping_cmd'] == 100
    assert report['duration_s'] == pytest.approx(2.0, abs=1e-9)
    assert report['comfort']['acc_2norm'] == pytest.approx(result.metrics['acc_2norm'],
                                                           rel=1e-12)
    assert report['comfort']['acc_rms'] == pytest.approx(result.metrics['acc_rms'], rel=1e-12)
    assert report['power']['power_w'] == pytest.approx(result.metrics['power_w'], rel=1e-12)
    assert report['power']['source'].startswith('plant diagnostics')
    # P = effort·velocity at the samples is the instantaneous power the plant reported.
    assert report['power']['power_mean_samples_w'] == pytest.approx(
        float(result.power.mean()), rel=1e-9)
    assert report['timing']['offline'] and report['fallbacks']['total'] == 0
    assert report['session']['controller'] == 'passive'
    names = sorted(os.path.basename(f) for f in report['files'])
    assert names == ['acceleration.png', 'damping_cmd.png', 'power.png', 'prediction.png',
                     'road_preview.png']           # no timing.png: offline, not measured
    for f in report['files']:
        assert open(f, 'rb').read(8) == b'\x89PNG\r\n\x1a\n' and os.path.getsize(f) > 5000
    text = erva('report', bag, check=True).stdout
    assert f'acc 2-norm {result.metrics["acc_2norm"]:.4f}' in text
    assert 'offline session' in text


def test_road_preview_plot_compares_each_preview_with_the_road_that_came(offline_session):
    """The offline preview is the road itself: 0 error 1 and N steps ahead.

    At every t_k whose point the 2 s road still covers; a preview matched one sample off
    would be ~0.1 mm out.
    """
    from erva_ros.core.bag.reader import open_bag
    from erva_ros.core.plots.bag_report import preview_errors
    from erva_ros.session.bag.bag_report import load_session
    data = load_session(open_bag(offline_session[0]))
    n = len(data.previews[0]) - 1
    errors = preview_errors(data)
    assert sorted(errors) == [1, n] and data.road.n == len(data.previews) == 100
    for h, (t_k, e) in errors.items():
        assert len(t_k) == 100 - h and t_k[0] == 0.0
        assert max(abs(e)) < 1e-9, (h, max(abs(e)))


def _stamp(ns):
    return Time(sec=ns // 10 ** 9, nanosec=ns % 10 ** 9)


def test_timing_deadlines_and_fallbacks_from_message_times(erva, tmp_path):
    """A hand-made session whose latencies, jitter and counters are known exactly."""
    bag = str(tmp_path / 'timed')
    with BagWriter(bag, session={'scenario': 'timing'}) as w:
        w.add_topic('/erva/state', 'sensor_msgs/msg/JointState')
        w.add_topic('/erva/damping_cmd', 'trajectory_msgs/msg/JointTrajectory')
        w.add_topic('/erva/sprung_accel', 'geometry_msgs/msg/AccelStamped')
        w.add_topic('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray')
        for k in range(100):
            stamp = T0 + k * 20 * MS
            state = JointState(position=[0.0] * 3, velocity=[0.0] * 3)
            state.header.stamp = _stamp(stamp)
            write_message(w, '/erva/state', state, stamp + MS // 2, stamp + MS // 4)
            accel = AccelStamped()
            accel.header.stamp = _stamp(stamp)
            accel.accel.linear.z = 2.0 if k % 2 else -2.0
            write_message(w, '/erva/sprung_accel', accel, stamp + MS, stamp + MS)
            if k == 50:
                continue          # this state never gets a command
            delay = 2 * MS if k != 70 else 15 * MS   # one late command
            cmd = JointTrajectory(points=[JointTrajectoryPoint(positions=[1e4])])
            cmd.header.stamp = _stamp(stamp)
            write_message(w, '/erva/damping_cmd', cmd, stamp + delay + MS, stamp + delay)
        diag = DiagnosticArray(status=[
            DiagnosticStatus(name='/erva/nmpc_node', values=[
                KeyValue(key='deadline_misses', value='2'),
                KeyValue(key='controller_fallback_plan', value='3'),
                KeyValue(key='controller_fallback_passive', value='1'),
                KeyValue(key='solve_ms_p99', value='4.5')]),
            DiagnosticStatus(level=DiagnosticStatus.ERROR, name='/erva/plant_sim_node',
                             message='no command', values=[
                                 KeyValue(key='harvested_j', value='8.0')])])
        write_message(w, '/diagnostics', diag, T0 + 2000 * MS)
        # Before the loop's first sample and after its last (Ts on): the start-up's and
        # the shut-down's states, reported apart.
        for t, text in ((T0 - 100 * MS, 'ECU silent: no valid frame received yet'),
                        (T0 + 2001 * MS, 'no fresh damping command for 0.062 s')):
            write_message(w, '/diagnostics', DiagnosticArray(status=[DiagnosticStatus(
                level=DiagnosticStatus.ERROR, name='/erva/ecu_bridge_node: command',
                message=text)]), t)
    r = json.loads(erva('report', bag, '--json', '--out', tmp_path / 'o', check=True).stdout)
    assert os.path.join(tmp_path, 'o', 'timing.png') in r['files']   # measured: it has one
    t = r['timing']
    assert r['ts_s'] == pytest.approx(0.02) and not t['offline'] and t['clock'] == 'wall'
    assert t['latency_publish_ms']['p50'] == pytest.approx(2.0)
    assert t['latency_publish_ms']['max'] == pytest.approx(15.0)
    assert t['latency_log_ms']['p50'] == pytest.approx(3.0)
    assert t['latency_publish_ms']['samples'] == 99 and t['unanswered_states'] == 1
    # Periods: 40 ms over the missing k = 50, 33 ms to the late k = 70, 7 ms after it.
    assert t['publish']['period_ms']['max'] == pytest.approx(40.0)
    assert t['publish']['jitter_ms']['max'] == pytest.approx(20.0)
    assert t['late_commands'] == 2           # the two periods over 1.5 Ts
    assert r['deadline_misses']['total'] == 2 and r['fallbacks']['total'] == 4
    assert r['solve_ms'] == {'/erva/nmpc_node/solve_ms_p99': 4.5,
                             '/erva/nmpc_node/solve_ms_samples': 0.0}
    assert r['comfort']['acc_rms'] == pytest.approx(2.0)
    assert r['power']['harvested_j'] == 8.0 and r['power']['power_w'] == pytest.approx(4.0)
    assert r['diagnostics_errors'] == ['/erva/plant_sim_node: no command']
    assert r['diagnostics_errors_outside'] == {'/erva/ecu_bridge_node: command': [
        'ECU silent: no valid frame received yet', 'no fresh damping command for 0.062 s']}
    text = erva('report', bag, check=True).stdout
    assert text.count('ERROR diagnostic') == 1
    assert 'outside the loop (before its first sample, after its last): 2 ERROR statuses of ' \
        '/erva/ecu_bridge_node: command' in text


def test_a_bag_without_session_topics_still_reports(erva, tmp_path):
    bag = str(tmp_path / 'bare')
    with BagWriter(bag) as w:
        w.add_topic('/clock', 'rosgraph_msgs/msg/Clock')
    r = json.loads(erva('report', bag, '--json', '--out', tmp_path / 'o', check=True).stdout)
    assert r['samples']['state'] == 0 and r['comfort']['acc_rms'] is None
    assert len(r['files']) == 5   # empty figures say what is missing
