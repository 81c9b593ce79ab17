"""The session monitor's figures from synthetic inputs: its store fed directly, no DDS.

Messages are built with rclpy's message classes and serialized by rclpy, as they
arrive at the monitor's raw subscriptions; statuses are the nodes' typed reports in
DiagnosticArrays.  Every expected figure is computed here from the inputs.
"""

import math

import numpy as np
import pytest
from rclpy.serialization import serialize_message

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from erva_ros.core import topics
from erva_ros.core.levels import OK, WARN
from erva_ros.core.reports import NMPCReport, PlantReport, RoadReport, Timing
import ros_msgs as msgs
from erva_ros.session.run import monitor_figures
from erva_ros.session.run.observations import Observations

TS = 0.02
TS_NS = 20_000_000
T0 = 1_000_000_000_000          # stamp of sample 0 (ns)
N = 40                          # samples
LAT_NS = 3_000_000              # state published -> command received (ns)
RNG = np.random.default_rng(7)
X = RNG.normal(scale=0.01, size=(N + 1, 6))
ACC = RNG.normal(size=N)
U = 1000.0 + 100.0 * np.arange(N)


def _stamp(k):
    return T0 + k * TS_NS


def _feed_loop(obs, skip_state=None):
    """Feed N samples of the live loop; state k arrives 1 ms after its stamp."""
    for k in range(N + 1):
        if k != skip_state:
            obs.add(topics.STATE, _stamp(k) + 1_000_000,
                    serialize_message(msgs.state_msg(_stamp(k), X[k], 'erva')))
        obs.add(topics.ROAD_HEIGHT, _stamp(k),
                serialize_message(msgs.road_height_msg(_stamp(k), 0.1 * k, 1e-3 * k)))
        obs.add(topics.ROAD_PREVIEW, _stamp(k), serialize_message(
            msgs.preview_msg(_stamp(k), [1e-3 * k] * 11, TS_NS)))
        if k == N:
            break
        obs.add(topics.DAMPING_CMD, _stamp(k) + 1_000_000 + LAT_NS,
                serialize_message(msgs.damping_msg(_stamp(k), [U[k]] * 10, TS_NS)))
        obs.add(topics.SPRUNG_ACCEL, _stamp(k) + 2_000_000,
                serialize_message(msgs.accel_msg(_stamp(k), ACC[k])))
        obs.add(topics.GENERATOR, _stamp(k) + 2_000_000,
                serialize_message(msgs.generator_msg(_stamp(k), 0.0, 0.01 * k, U[k])))


def _status(obs, report, rx_ns, namespace='/erva'):
    """Feed ``report`` (its node a name in ``namespace``) as rclpy serializes the array."""
    report.node = f'{namespace}/{report.node}'
    arr = DiagnosticArray(status=[DiagnosticStatus(
        level=bytes([report.level]), name=report.node, message=report.message,
        hardware_id=report.hardware_id,
        values=[KeyValue(key=k, value=v) for k, v in report.values().items()])])
    obs.add_diagnostics(serialize_message(arr), rx_ns)


def _final_statuses(obs, states=N + 1, harvested=0.5):
    rx = _stamp(N) + 10_000_000
    _status(obs, PlantReport(
        node='plant_sim_node', message='finished', states=states, steps=N,
        harvested_j=harvested, u_from_command=N, rejected_road_height=2,
        out_of_order_commands=1, cmd_jitter_ms=Timing(0.1, 0.4, 0.5, N - 1),
        loop_latency_ms=Timing(3.0, 3.5, 4.0, N), final=True), rx)
    _status(obs, NMPCReport(node='nmpc_node', message='finished', controller='preview',
                            commands=N, solves=N, rejected_state=3,
                            solve_ms=Timing(1.5, math.nan, math.nan, N), final=True), rx)
    _status(obs, RoadReport(node='road_preview_node', message='finished',
                            samples_published=N + 1, finished=True, final=True), rx)


def _observations():
    return Observations(window_ns=(T0, T0 + 10 * N * TS_NS))


def test_summary_figures_are_those_of_the_inputs():
    obs = _observations()
    _status(obs, PlantReport(node='plant_sim_node', level=WARN, message='no command yet'),
            T0 - 1)
    _feed_loop(obs)
    _final_statuses(obs)
    s = obs.summary(TS, N, realtime=True)

    m = s['metrics']
    assert m['samples'] == N
    assert m['acc_2norm'] == pytest.approx(math.sqrt(np.sum(ACC ** 2)), rel=1e-12)
    assert m['acc_rms'] == pytest.approx(math.sqrt(np.mean(ACC ** 2)), rel=1e-12)
    assert m['power_w'] == pytest.approx(0.5 / (N * TS), rel=1e-12)
    # N state periods over the N arrivals' wall span (states arrive on the grid).
    assert m['realtime_factor'] == pytest.approx(1.0, rel=1e-9)

    c = s['commands']
    assert c['received'] == c['for_samples'] == N
    assert c['rate_hz'] == pytest.approx(1 / TS, rel=1e-9)
    assert c['sample_to_command_ms']['p50'] == pytest.approx(4.0, rel=1e-9)
    assert c['sample_to_command_ms']['samples'] == N
    assert c['monitor']['state_to_command_ms']['max'] == pytest.approx(LAT_NS * 1e-6, rel=1e-9)
    assert c['monitor']['period_jitter_ms']['max'] == pytest.approx(0.0, abs=1e-6)
    assert c['state_to_command_ms'] == {'p50': 3.0, 'p99': 3.5, 'max': 4.0, 'samples': N}
    assert c['period_jitter_ms']['samples'] == N - 1

    assert s['nmpc']['controller'] == 'preview' and s['nmpc']['commands'] == N
    assert s['nmpc']['solve_ms']['p50'] == 1.5 and math.isnan(s['nmpc']['solve_ms']['p99'])
    assert s['nmpc']['late'] == 0
    assert s['plant']['u_from_command'] == N and s['plant']['steps'] == N

    msg = s['messages']
    assert msg['published'][topics.STATE] == N + 1
    assert msg['received'][topics.STATE] == N + 1 and msg['dropped_total'] == 0
    assert msg['rejected'] == {'state': 3, 'road/preview': 0, 'road/height': 2,
                               'damping_cmd': 0, '/clock': 0, 'out_of_order': 1}
    assert msg['rejected_total'] == 6
    # The plant's status changed once (WARN -> OK); the others reported once each.
    assert [(e['node'], e['level']) for e in s['events']] == [
        ('plant_sim_node', 'WARN'), ('plant_sim_node', 'OK'), ('nmpc_node', 'OK'),
        ('road_preview_node', 'OK')]
    assert s['events'][0]['t_s'] < 0 and obs.finished_rx == {
        'road_preview_node': _stamp(N) + 10_000_000}
    assert obs.all_received()


def test_a_lost_and_a_foreign_message_are_told_apart():
    obs = _observations()
    _feed_loop(obs, skip_state=7)               # published, never received
    _final_statuses(obs)
    # From another process on the domain: stamped long before the session.
    obs.add(topics.STATE, T0, serialize_message(msgs.state_msg(5, X[0], 'erva')))
    # A repeated stamp on a data topic is not the loop's either.
    obs.add(topics.SPRUNG_ACCEL, T0, serialize_message(msgs.accel_msg(_stamp(3), 9.0)))
    s = obs.summary(TS, N, realtime=True)
    m = s['messages']
    assert m['received'][topics.STATE] == N + 1 and m['received'][topics.SPRUNG_ACCEL] == N + 1
    assert m['foreign'][topics.STATE] == 1 and m['foreign'][topics.SPRUNG_ACCEL] == 1
    assert m['foreign_total'] == 2
    assert m['dropped'][topics.STATE] == 1 and m['dropped'][topics.SPRUNG_ACCEL] == 0
    assert m['dropped_total'] == 1 and not obs.all_received()
    # The command of the lost state is received but not for a sample the monitor saw.
    assert s['commands']['received'] == N and s['commands']['for_samples'] == N - 1
    assert s['metrics']['acc_2norm'] == pytest.approx(math.sqrt(np.sum(ACC ** 2)), rel=1e-12)


def test_unknown_counts_and_lockstep_leave_figures_out():
    obs = _observations()
    _feed_loop(obs)
    s = obs.summary(TS, N, realtime=False)       # lock-step: no wall-clock figures
    assert set(s['commands']) == {'received', 'for_samples'}
    assert all(v is None for v in s['messages']['dropped'].values())
    assert not obs.all_received()                # no node said what it published
    assert math.isnan(s['metrics']['harvested_j']) and math.isnan(s['metrics']['power_w'])


def test_trajectory_is_by_sample_and_cut_at_n_steps():
    obs = _observations()
    _feed_loop(obs)
    tr = obs.trajectory(N - 5)
    assert tr['x'].shape == (N - 5, 6)
    np.testing.assert_array_equal(tr['x'], X[:N - 5])
    np.testing.assert_array_equal(tr['u'], U[:N - 5])
    np.testing.assert_array_equal(tr['sprung_accel'], ACC[:N - 5])
    np.testing.assert_allclose(tr['t'], np.arange(N - 5) * TS, rtol=0, atol=1e-12)
    np.testing.assert_allclose(tr['power'], U[:N - 5] * (0.01 * np.arange(N - 5)) ** 2,
                               rtol=1e-12, atol=0)


def test_events_are_capped():
    obs = _observations()
    for i in range(monitor_figures.MAX_EVENTS + 5):
        _status(obs, NMPCReport(node='nmpc_node', level=WARN if i % 2 else OK,
                                message=f'flap {i}'), T0 + i)
    assert len(obs.events) == monitor_figures.MAX_EVENTS      # the store keeps no more
    assert len(monitor_figures.events(obs)) == monitor_figures.MAX_EVENTS


def test_only_the_sessions_own_reports_count():
    """Another namespace, another session id, or no id: counted foreign, figures untouched."""
    obs = Observations(window_ns=(T0, T0 + 10 * N * TS_NS), session='a1')
    _feed_loop(obs)
    _final_statuses(obs)            # reports without the session's id
    assert obs.reports == {} and obs.foreign_statuses == 3
    for ns, session, commands in (('/other', 'a1', 7), ('/erva', 'b2', 8),
                                  ('/erva/sub', 'a1', 9), ('/erva', 'a1', N)):
        _status(obs, NMPCReport(node='nmpc_node', session=session, commands=commands,
                                final=True), T0, namespace=ns)
    assert list(obs.reports) == ['nmpc_node'] and obs.foreign_statuses == 6
    assert obs.report('nmpc_node').commands == N
    assert obs.summary(TS, N, realtime=True)['messages']['foreign_statuses'] == 6


def test_a_node_without_its_final_report_published_an_unknown_number():
    obs = _observations()
    _feed_loop(obs)
    _final_statuses(obs)
    assert obs.published(final_only=True)[topics.STATE] == N + 1
    _status(obs, PlantReport(node='plant_sim_node', states=N - 3, steps=N - 3), T0)
    assert obs.published()[topics.STATE] == N - 3       # its newest count, for the drain
    assert obs.published(final_only=True)[topics.STATE] is None
