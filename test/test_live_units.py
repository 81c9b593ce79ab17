"""Live-system helpers without processes: messages, validation, command hold, parameters."""

import math
import os

import numpy as np
import pytest
import rclpy
from rclpy.serialization import serialize_message
import yaml

from erva_ros.core import topics
import ros_msgs as msgs
from erva_ros.core.loop.command_hold import CommandHold
from erva_ros.core.contract import decode_command, decode_diagnostics
from erva_ros.core.levels import ERROR
from erva_ros.core.loop.status import StatusReporter
from erva_ros.core.settings.schemas import LIVE, NodeSchema
from erva_ros.core.reports import NodeReport, report_from_status
from erva_ros.session.run.run_config import RunConfig
from erva_ros.session.run.session_file import prepare_session, read_live_file, validate_live
from erva_ros.ros.parameters import declare_node_parameters, declare_schema
from erva_ros.session.run.report import format_summary, jsonable
from erva_ros.core.loop.scenario import build_road, load_road_file
from erva_ros.core.timing import next_grid_delay_ns, PeriodStats, SampleGrid
from erva_ros.core.loop.validation import MessageRejected, Rejections
from erva_ros.core.model.params import ParamError, PAPER_VALUES

from conftest import REPO

TS_NS = 20_000_000
X = np.array([0.01, -0.2, 0.002, 0.3, 0.004, -0.5])


# -- messages ----------------------------------------------------------------------------
def test_state_round_trip_keeps_every_bit_and_the_stamp():
    stamp = 1_700_000_000_123_456_789
    msg = msgs.state_msg(stamp, X, 'erva')
    assert list(msg.name) == list(topics.STATE_JOINTS)
    got_stamp, x = msgs.parse_state(msg, 'erva')
    assert got_stamp == stamp and np.array_equal(x, X)
    bench = msgs.state_msg(stamp, X[:4], 'benchmark')
    assert list(bench.name) == ['z_s', 'z_us']
    assert np.array_equal(msgs.parse_state(bench, 'benchmark')[1], X[:4])


@pytest.mark.parametrize('delay_ns', [0, 15_000_000])
def test_trajectories_round_trip_on_the_ts_grid(delay_ns):
    # plan[k] acts at d + k·Ts after its sample (d = 0: the paper's loop; 15 ms: shipped).
    plan = np.array([1e4, 2e4, 0.0, 5e3])
    msg = msgs.damping_msg(5 * TS_NS, plan, TS_NS, delay_ns)
    assert msg.joint_names == [topics.DAMPING_JOINT]
    assert msgs.time_to_ns(msg.points[3].time_from_start) == delay_ns + 3 * TS_NS
    stamp, got = msgs.parse_damping(msg, TS_NS)
    assert stamp == 5 * TS_NS and np.array_equal(got, plan)
    assert decode_command(serialize_message(msg), TS_NS).delay_ns == delay_ns
    heights = np.linspace(-1e-3, 1e-3, 11)
    stamp, got = msgs.parse_preview(msgs.preview_msg(0, heights, TS_NS), TS_NS, 11)
    assert stamp == 0 and np.array_equal(got, heights)


@pytest.mark.parametrize('bad', [math.nan, math.inf, -math.inf, 5.0])
def test_non_finite_or_absurd_state_is_rejected(bad):
    x = X.copy()
    x[3] = bad if bad != 5.0 else 50.0    # 50 m/s suspension velocity is absurd
    with pytest.raises(MessageRejected):
        msgs.parse_state(msgs.state_msg(0, x, 'erva'), 'erva')


def test_malformed_messages_are_rejected_with_a_reason():
    msg = msgs.state_msg(0, X, 'erva')
    msg.name = ['z_s', 'z_us', 'zd']
    with pytest.raises(MessageRejected, match='joint names'):
        msgs.parse_state(msg, 'erva')
    with pytest.raises(MessageRejected, match='joint names'):
        msgs.parse_state(msgs.state_msg(0, X, 'erva'), 'benchmark')
    with pytest.raises(MessageRejected, match='absurd'):
        msgs.parse_damping(msgs.damping_msg(0, [-1.0, 1e4], TS_NS), TS_NS)
    with pytest.raises(MessageRejected, match='not finite'):
        msgs.parse_damping(msgs.damping_msg(0, [1e4, math.nan], TS_NS), TS_NS)
    with pytest.raises(MessageRejected, match='time_from_start'):
        msgs.parse_damping(msgs.damping_msg(0, [1e4, 1e4], TS_NS // 2), TS_NS)
    with pytest.raises(MessageRejected, match='at least 11'):
        msgs.parse_preview(msgs.preview_msg(0, np.zeros(5), TS_NS), TS_NS, 11)
    with pytest.raises(MessageRejected, match='absurd'):
        msgs.parse_road_height(msgs.road_height_msg(0, 0.0, 2.0))


def test_rejections_are_counted_and_logged_at_a_limited_rate():
    lines, now = [], [0.0]
    rej = Rejections(lines.append, lambda: now[0], log_period_s=1.0)
    for i in range(50):
        now[0] = i * 0.1
        rej.reject('state', 'x is nan')
    assert rej.counts == {'state': 50} and rej.total == 50
    assert len(lines) == 5                    # t = 0, 1, 2, 3, 4 s
    assert '9 more not logged' in lines[1]


# -- the plant's command hold ----------------------------------------------------------------
def test_command_hold_uses_command_then_plan_then_passive():
    hold = CommandHold(TS_NS, c_e0=1e4, timeout_ns=10 * TS_NS)
    assert hold.select(0) == (1e4, 'passive')
    hold.update(TS_NS, np.array([100.0, 200.0, 300.0]))
    assert hold.select(TS_NS) == (100.0, 'command')
    assert hold.select(2 * TS_NS) == (200.0, 'plan')
    assert hold.select(3 * TS_NS) == (300.0, 'plan')
    assert hold.select(4 * TS_NS) == (1e4, 'passive')      # plan used up
    assert not hold.update(0, np.array([1.0]))               # older than the held one
    assert hold.out_of_order == 1
    short = CommandHold(TS_NS, c_e0=1e4, timeout_ns=TS_NS)
    short.update(0, np.full(10, 5.0))
    assert short.select(2 * TS_NS) == (1e4, 'passive')      # plan too old: timeout
    assert hold.counts == {'command': 1, 'plan': 2, 'passive': 2}


def test_command_hold_late_rule():
    # At t_k + d the newest command received by then acts (its plan entry for t_k); a
    # command received after its own instant never acts and is counted late.
    d = TS_NS // 4
    hold = CommandHold(TS_NS, c_e0=1e4, timeout_ns=10 * TS_NS)
    hold.update(0, np.array([100.0, 200.0, 300.0]), rx_ns=d - 1)
    assert hold.select(0, deadline_ns=d) == (100.0, 'command')
    hold.update(TS_NS, np.array([110.0, 210.0]), rx_ns=TS_NS + d + 1)   # late by 1 ns
    assert hold.select(TS_NS, deadline_ns=TS_NS + d) == (200.0, 'plan')
    assert hold.late == 1
    # ... but its plan serves the next instant, which it reached in time.
    assert hold.select(2 * TS_NS, deadline_ns=2 * TS_NS + d) == (210.0, 'plan')
    hold.update(3 * TS_NS, np.array([120.0]), rx_ns=3 * TS_NS + d)      # on the dot
    assert hold.select(3 * TS_NS, deadline_ns=3 * TS_NS + d) == (120.0, 'command')
    assert hold.select(3 * TS_NS) == (120.0, 'command')       # lock-step: no deadline
    assert hold.late == 1 and hold.counts == {'command': 3, 'plan': 2, 'passive': 0}


def test_grid_delay_and_period_jitter():
    assert next_grid_delay_ns(105, 0, 20) == 15
    assert next_grid_delay_ns(120, 0, 20) == 20
    assert next_grid_delay_ns(121, 1, 20) == 20
    p = PeriodStats(0.02)
    for t in (0.0, 0.021, 0.040, 0.062):
        p.mark(t)
    s = p.jitter.summary()
    assert s['samples'] == 3 and s['max'] == pytest.approx(2.0)


def test_sample_grid_skips_what_a_late_timer_missed_but_never_the_last_sample():
    g = SampleGrid(20, 6)                    # t_k = 1000 + 20 k, k = 0..5
    taken = [(now, g.due(now)) for now in (1000, 1019, 1021, 1085, 1090, 1200, 1300)]
    assert taken == [(1000, 0), (1019, None), (1021, 1), (1085, 4), (1090, None),
                     (1200, 5), (1300, None)]
    assert g.skipped == 2 and g.done      # samples 2 and 3; 5 taken late, at 1200
    assert all(g.stamp_ns(k) <= now for now, k in taken if k is not None)
    late = SampleGrid(20, 3)
    assert (late.due(0), late.due(500), late.skipped, late.done) == (0, 2, 1, True)


# -- parameters ------------------------------------------------------------------------------
@pytest.fixture
def ros_context():
    ctx = rclpy.Context()
    yield ctx
    rclpy.try_shutdown(context=ctx)


def _node(ctx, *ros_args):
    from rclpy.node import Node
    rclpy.init(args=['x', '--ros-args', *ros_args], context=ctx)
    return Node('nmpc_node', context=ctx)


@pytest.mark.ros
def test_parameters_get_descriptors_with_ranges(ros_context):
    node = _node(ros_context, '-p', 'alpha2:=1', '-p', 'seed:=7')
    values = declare_node_parameters(node, 'nmpc_node')
    assert values['M_s'] == PAPER_VALUES['M_s']
    assert values['alpha2'] == 1.0 and isinstance(values['alpha2'], float)   # 1 for a double
    assert node.get_parameter('alpha2').value == 1.0
    live = declare_schema(node, NodeSchema('x', ((LIVE, ('seed', 'preview_noise')),)))
    assert live == {'seed': 7, 'preview_noise': False}
    assert values['mode'] == 'realtime'
    desc = node.describe_parameter('M_s')
    assert desc.read_only and desc.floating_point_range[0].to_value == 5000.0
    assert node.describe_parameter('seed').integer_range[0].from_value == 0
    assert 'realtime' in node.describe_parameter('mode').additional_constraints
    node.destroy_node()


@pytest.mark.parametrize('arg, match', [
    ('M_s:=-3.0', r"'M_s' = -3.0 is out of range; allowed \[1, 5000\] kg"),
    ('horizon:=0', r"'horizon' = 0 is out of range"),
    ('mode:=fast', r"'mode' = 'fast' is not allowed; choose one of realtime, lockstep"),
    ('seed:=1.5', r"'seed' must be an integer"),
])
@pytest.mark.ros
def test_a_bad_parameter_is_one_line(ros_context, arg, match):
    node = _node(ros_context, '-p', arg)
    with pytest.raises(ParamError, match=match) as info:
        declare_node_parameters(node, 'nmpc_node')
        declare_schema(node, NodeSchema('x', ((LIVE, ('seed',)),)))
    assert '\n' not in str(info.value)
    node.destroy_node()


def test_live_tables_cover_the_defaults_and_live_yaml():
    specs, defaults = LIVE.specs(), LIVE.defaults()
    assert set(defaults) == set(specs)
    for key, value in defaults.items():
        assert specs[key].check(key, value) == value, key
    values = read_live_file(os.path.join(REPO, 'config', 'live.yaml'))
    assert validate_live(values) == validate_live({})     # the file states the defaults


def test_validate_live_and_live_file_errors(tmp_path):
    with pytest.raises(ParamError, match="'duration_s' = -1"):
        validate_live({'duration_s': -1.0})
    with pytest.raises(ParamError, match="'road' = 'moon'"):
        validate_live({'road': 'moon'})
    bad = tmp_path / 'live.yaml'
    bad.write_text('/**:\n  ros__parameters:\n    durration_s: 3.0\n')
    with pytest.raises(ParamError, match='unknown live parameter'):
        read_live_file(str(bad))


@pytest.mark.ros
def test_session_params_file_is_what_rclpy_gives_each_node(tmp_path, ros_context):
    cfg = RunConfig(controller='no_preview', alpha2=0.5, mode='lockstep', seed=3,
                    duration_s=1.0, session_dir=str(tmp_path),
                    live_overrides={'preview_noise': True})
    session = prepare_session(cfg, recording=False)
    doc = yaml.safe_load(open(session.params_file))
    assert doc['/**']['ros__parameters']['use_sim_time'] is True
    node = _node(ros_context, '-r', '__ns:=/erva', '--params-file', session.params_file)
    values = declare_node_parameters(node, 'nmpc_node')
    assert values['controller'] == 'no_preview' and values['alpha2'] == 0.5
    assert (values['mode'], values['duration_s'], values['state_timeout_periods']) == (
        'lockstep', 1.0, 3)
    assert values['c_e0'] == PAPER_VALUES['c_e0']
    assert values['session_id'] == session.session_id and len(session.session_id) == 16
    node.destroy_node()
    road = doc['/**/road_preview_node']['ros__parameters']
    assert road['seed'] == 3 and road['preview_noise'] is True


def test_one_command_delay_for_ocp_plant_and_ecu(tmp_path):
    # d is the live loop's (config/live.yaml), the same with and without --ecu; an option
    # wins, and it reaches the controller's settings and every node's section.
    shipped = LIVE.defaults()['command_delay_s']

    def session(name, **kw):
        cfg = RunConfig(session_dir=str(tmp_path / name), duration_s=1.0, **kw)
        return prepare_session(cfg, recording=False)

    for name, kw in (('full', {}), ('hil', {'ecu': 'virtual'})):
        s = session(name, **kw)
        assert s.settings.command_delay_s == s.live['command_delay_s'] == shipped
    s = session('opt', live_overrides={'command_delay_s': 0.004})
    assert s.settings.command_delay_s == 0.004
    doc = yaml.safe_load(open(s.params_file))
    sections = [v['ros__parameters'] for v in doc.values()]
    assert sum(p.get('command_delay_s') == 0.004 for p in sections) >= 1
    assert all(p.get('command_delay_s', 0.004) == 0.004 for p in sections)
    with pytest.raises(ParamError, match='command_delay_s'):
        session('bad', live_overrides={'command_delay_s': 0.02})


def test_road_file_is_read_and_bad_rows_are_one_line(tmp_path):
    good = tmp_path / 'road.csv'
    good.write_text('time_s, height_m\n0.0, 0.0\n1.0, 0.002\n2.0, 0.0\n')
    rows = load_road_file(str(good))
    assert rows.shape == (3, 2)
    cfg = validate_live({'road_file': str(good), 'duration_s': 2.0})
    assert build_road(cfg).height(0.5) == pytest.approx(0.001)
    bad = tmp_path / 'bad.csv'
    bad.write_text('0.0, 0.0\n1.0, x\n')
    with pytest.raises(ParamError, match='bad.csv:2'):
        load_road_file(str(bad))


# -- diagnostics and report -------------------------------------------------------------------
def test_status_reporter_publishes_on_change_and_when_due():
    sent = []
    report = NodeReport(node='/erva/nmpc_node', hardware_id='hw', session='s')
    rep = StatusReporter(report, sent.append, lambda: 0)
    rep.set(ERROR, 'no state')
    rep.set(ERROR, 'no state')             # unchanged: no second message
    assert len(sent) == 1
    got = report_from_status(decode_diagnostics(sent[0])[1][0])
    assert (got.node, got.level, got.message, got.hardware_id, got.session,
            got.status_seq, got.final) == ('/erva/nmpc_node', ERROR, 'no state', 'hw', 's',
                                           1, False)
    rep.after_sample()
    rep.on_timer(busy_window_s=10.0)       # busy: only marked due
    assert len(sent) == 1
    rep.after_sample()                     # published in the slack after a sample
    assert len(sent) == 2


def test_summary_json_has_no_nan_and_text_names_the_errors():
    assert jsonable({'a': [float('nan'), np.float64(1.5)], 'b': np.int64(3)}) == \
        {'a': [None, 1.5], 'b': 3}
    summary = {
        'scenario': {'controller': 'preview', 'weights': [1.0, 0.0], 'road': 'paper',
                     'seed': 0, 'mode': 'realtime', 'model': 'erva', 'duration_s': 4.0,
                     'ts': 0.02},
        'metrics': {'samples': 0}, 'commands': {'received': 0}, 'nmpc': {}, 'plant': {},
        'messages': {'dropped_total': 0, 'rejected_total': 0},
        'errors': ['nmpc_node died (exit status -9) while running'], 'wall_time_s': 1.0}
    text = format_summary(summary)
    assert 'ERROR     nmpc_node died' in text and 'skipped' not in text
    summary.update(road={'samples_published': 200, 'samples_skipped': 1},
                   plant={'road_gaps': 1})
    assert ('road      1 sample skipped (timer behind), 1 gap bridged by the plant'
            in format_summary(summary))
    summary['plant'] = {}             # HIL: the ECU's plant figures have no road gaps
    assert 'road      1 sample skipped (timer behind)\n' in format_summary(summary)


def test_duration_stats_take_no_memory_per_sample():
    # Every sample of a session counted (exactly), in memory allocated and written at
    # construction: a long session's stats grow nothing (they kept every sample, ~32
    # bytes each, before).  Traced, so the Python floats a deque kept would show.
    import tracemalloc
    from erva_ros.core.timing import DurationStats, PeriodStats, EXACT_SAMPLES
    stats, period = DurationStats(), PeriodStats(0.02)
    samples = np.random.default_rng(3).lognormal(np.log(1e-3), 0.5, 20 * EXACT_SAMPLES)
    for s in samples[:2 * EXACT_SAMPLES]:
        stats.add(s)
    tracemalloc.start()
    try:
        before = tracemalloc.take_snapshot()
        for i, s in enumerate(samples[2 * EXACT_SAMPLES:]):
            stats.add(s)
            period.mark(i * 0.02 + s)
        stats.summary()
        after = tracemalloc.take_snapshot()
    finally:
        tracemalloc.stop()
    grown = sum(d.size_diff for d in after.compare_to(before, 'filename') if d.size_diff > 0)
    assert grown < 2000, grown      # 36,000 samples: a byte per sample would be 36 kB
    assert len(stats) == 20 * EXACT_SAMPLES and len(period.jitter) == 18 * EXACT_SAMPLES - 1


def test_duration_stats_are_exact_then_binned_for_a_long_session():
    from erva_ros.core.timing import DurationStats, EXACT_SAMPLES
    from erva_ros.core.metrics import percentiles_ms
    rng = np.random.default_rng(5)
    samples = rng.lognormal(np.log(1e-3), 0.5, 3 * EXACT_SAMPLES)   # ~1 ms, long tail
    stats = DurationStats()
    for s in samples[:EXACT_SAMPLES]:
        stats.add(s)
    assert stats.summary() == percentiles_ms(samples[:EXACT_SAMPLES])   # exact so far
    for s in samples[EXACT_SAMPLES:]:
        stats.add(s)
    got, want = stats.summary(), percentiles_ms(samples)
    assert got['samples'] == want['samples'] == 3 * EXACT_SAMPLES == len(stats)
    assert got['max'] == want['max']                                     # exact
    for key in ('p50', 'p99'):                                           # every sample counts
        assert got[key] == pytest.approx(want[key], rel=0.003), key
    edge = DurationStats(exact=3)
    for s in (0.0, 5e3, 1e-12, 0.002, 0.003):                            # out of the bins' range
        edge.add(s)
    assert edge.summary()['max'] == 5e6 and edge.summary()['samples'] == 5


def test_stale_session_dirs_of_dead_runs_go_but_a_failed_runs_stay(tmp_path):
    from erva_ros.session.run.session_dirs import FAILED_NOTE, remove_stale_session_dirs
    import subprocess
    dead = subprocess.Popen(['true'])
    dead.wait()                                    # a pid that no longer runs
    for name in (f'erva_run_{dead.pid}_a', f'erva_run_{dead.pid}_b',
                 f'erva_run_{os.getppid()}_c', 'erva_run_x', 'other'):
        (tmp_path / name).mkdir()
    (tmp_path / f'erva_run_{dead.pid}_b' / FAILED_NOTE).write_text('nmpc_node died')
    assert remove_stale_session_dirs(str(tmp_path)) == [str(tmp_path / f'erva_run_{dead.pid}_a')]
    assert sorted(os.listdir(tmp_path)) == sorted([f'erva_run_{dead.pid}_b',
                                                   f'erva_run_{os.getppid()}_c',
                                                   'erva_run_x', 'other'])
