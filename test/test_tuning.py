"""Live tuning without ROS: which settings change, the checks, the sample boundary, the hold.

The cores the live node and `erva sim --set` share (core/controllers/tuning.py,
core/loop/control_loop.py), the segments by parameter set (session/run/segments.py) and the
/parameter_events decoder, checked against rclpy's own serialization.
"""

import numpy as np
import pytest

from erva_ros.core import contract
from erva_ros.core.studies.closed_loop import simulate_closed_loop
from erva_ros.core.controllers import make_controller
from erva_ros.core.controllers.settings import ControllerSettings
from erva_ros.core.controllers.tuning import (Built, check_schedule, LIVE_KEYS, LiveSettings,
                                              parse_change, retuned, sample_of,
                                              ScheduledTuning)
from erva_ros.core.loop.control_loop import build_loop, NODE_LIVE_KEYS
from erva_ros.core.loop.validation import StampWindow
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.settings.schemas import SCHEMAS
from erva_ros.core.model.params import paper_params, ParamError
from erva_ros.core.reports import NMPCReport
from erva_ros.core.road.profiles import make_road
from erva_ros.core.topics import STATE_JOINTS
from erva_ros.session.run import segments

P = paper_params()
M = make_model(P)
S = ControllerSettings()
TS_NS = 20_000_000


def test_the_live_settings_are_those_their_specs_mark_live():
    assert set(LIVE_KEYS) == {'alpha1', 'alpha2', 'u_min', 'u_max', 'use_preview',
                              'road_prediction', 'fallback', 'time_budget_s'}
    assert set(SCHEMAS['nmpc_node'].live()) == set(NODE_LIVE_KEYS)
    for node in ('plant_sim_node', 'road_preview_node', 'recorder', 'foxglove_server'):
        assert SCHEMAS[node].live() == (), node


@pytest.mark.parametrize('changes, says', [
    ({'alpha1': -1.0}, "'alpha1' = -1.0 is out of range; allowed [0, 1e+06]"),
    ({'u_max': float('nan')}, "'u_max' = nan is out of range"),
    ({'u_min': 12000.0}, 'must keep the passive damping c_e0 = 10000 Ns/m inside'),
    ({'u_max': 5000.0}, 'must keep the passive damping c_e0 = 10000 Ns/m inside'),
    ({'u_min': 9000.0, 'u_max': 8000.0}, "'u_max' = 8000 must exceed u_min = 9000"),
    ({'alpha1': 0.0, 'alpha2': 0.0}, 'both 0'),
    ({'fallback': 'none'}, "'fallback' = 'none' is not allowed; choose one of plan, passive"),
    ({'horizon': 20}, "'horizon' is read-only while the controller runs: the compiled "
                      'solver is built for it'),
    ({'ts': 0.01}, "'ts' is read-only while the controller runs: it fixes the sample grid"),
    ({'horizn': 20}, "unknown parameter(s) horizn; did you mean 'horizon'?"),
])
def test_a_bad_change_is_refused_with_its_reason(changes, says):
    with pytest.raises(ParamError, match=None) as exc:
        retuned(Built.of(S, P.c_e0), S, changes)
    assert says in str(exc.value), str(exc.value)


def test_settings_a_law_does_not_have_are_refused():
    sky = Built.of(S.with_(controller='skyhook'), P.c_e0)
    with pytest.raises(ParamError, match='controller skyhook has no weights'):
        retuned(sky, S.with_(controller='skyhook'), {'alpha1': 0.5})
    assert retuned(sky, S.with_(controller='skyhook'), {'u_max': 15000.0}).u_max == 15000.0
    nopre = S.with_(controller='no_preview')
    with pytest.raises(ParamError, match='no_preview never uses the preview'):
        retuned(Built.of(nopre, P.c_e0), nopre, {'use_preview': False})
    with pytest.raises(ParamError, match='lock-step has no wall-clock budget'):
        retuned(Built.of(S, P.c_e0), S, {'time_budget_s': 0.02}, lockstep=True)
    ipopt = S.with_(solver='ipopt')
    with pytest.raises(ParamError, match='rollout is stable up to the u_max'):
        retuned(Built.of(ipopt, P.c_e0), ipopt, {'u_max': 30000.0})


def test_live_settings_take_effect_only_when_applied():
    ctrl = make_controller('skyhook', M, S)
    live = LiveSettings(ctrl, S, P.c_e0)
    with pytest.raises(ParamError):
        live.stage({'u_max': 1.0})
    assert live.staged is None and ctrl.u_max == 20000.0          # a refusal stages nothing
    live.stage({'u_max': 15000.0})
    assert ctrl.u_max == 20000.0 and live.applied == 0            # staged, not yet in force
    assert live.apply() and ctrl.u_max == 15000.0 and live.applied == 1
    assert not live.apply()                                       # nothing more staged


def test_parse_change_and_the_sample_it_names():
    assert parse_change('1.0:alpha1=0.5') == (1.0, 'alpha1', 0.5)
    assert parse_change('2:use_preview=false') == (2.0, 'use_preview', False)
    assert parse_change('0.5:fallback=passive') == (0.5, 'fallback', 'passive')
    for bad, says in (('1.0alpha1=0.5', 'write T:key=value'), ('0:alpha1=1', 'T must be'),
                      ('1:alpha1=x', "'alpha1' must be a number"),
                      ('1:horizon=3', 'read-only')):
        with pytest.raises(ParamError, match=says):
            parse_change(bad)
    assert [sample_of(t, 0.02) for t in (0.02, 0.0200000001, 0.021, 1.0, 0.999999)] == \
        [1, 1, 2, 50, 50]
    with pytest.raises(ParamError, match='at 1 s: .* must exceed u_min = 16000'):
        check_schedule(Built.of(S, P.c_e0), S,
                       [(0.5, 'u_max', 15000.0), (1.0, 'u_min', 16000.0)])


def test_erva_sim_set_changes_the_commands_from_that_sample_on():
    # The offline loop's sample boundary: up to the sample before T the commands are the
    # unchanged run's, bit for bit; from the sample at T on, the new weight's.
    road = make_road('paper', 0.6, seed=1)
    ref = simulate_closed_loop(M, make_controller('preview', M, S), road, 0.6)
    ctrl = make_controller('preview', M, S)
    tuner = ScheduledTuning(ctrl, S, P.c_e0, [(0.3, 'alpha2', 1.0)])
    run = simulate_closed_loop(M, ctrl, road, 0.6, before_sample=tuner.before_sample)
    k = 15
    assert np.array_equal(run.u[:k], ref.u[:k]) and np.array_equal(run.x[:k + 1], ref.x[:k + 1])
    assert not np.allclose(run.u[k:], ref.u[k:])
    assert [k for k, _ in tuner.sets] == [0, 15] and tuner.sets[1][1]['alpha2'] == 1.0
    segs = segments.segments([(k * 0.02, v) for k, v in tuner.sets], run.t,
                             run.sprung_accel, run.power, 0.02)
    assert [(s['from_s'], s['to_s'], s['samples']) for s in segs] == \
        [(0.0, 0.3, 15), (0.3, 0.6, 15)]
    assert segs[1]['changed'] == {'alpha2': [0.0, 1.0]}
    assert segs[0]['acc_rms'] == pytest.approx(np.sqrt(np.mean(run.sprung_accel[:15] ** 2)))
    assert segs[1]['power_mean_w'] == pytest.approx(np.mean(run.power[15:]))


# -- the live node's core -----------------------------------------------------------------------
def _loop(mode, controller='passive', **extra):
    p = {**SCHEMAS['nmpc_node'].defaults(), 'mode': mode, 'controller': controller,
         'duration_s': 1.0, 'publish_prediction': False, **extra}
    report = NMPCReport()
    return build_loop(p, StampWindow(10**18, 10**18), report), report


def _job(loop, k, now=0):
    x = np.zeros(6)
    t = k * TS_NS
    loop.on_state(contract.encode_state(t, x, STATE_JOINTS), now)
    return loop.on_preview(contract.encode_preview(t, np.zeros(11), TS_NS), now)


def test_a_change_takes_effect_at_the_next_sample_and_the_report_says_from_which():
    loop, report = _loop('lockstep')
    loop.solve(_job(loop, 0))
    assert (report.parameter_set, report.live['u_max']) == (0, '20000.0')
    loop.stage({'u_max': 15000.0, 'state_timeout_periods': 5})
    assert loop.controller.u_max == 20000.0 and report.parameter_set == 0   # not mid-run
    out = loop.solve(_job(loop, 1))
    assert loop.controller.u_max == 15000.0 and loop.timeout_periods == 5
    assert (report.parameter_set, report.parameter_set_from_ns) == (1, TS_NS)
    assert report.live['u_max'] == '15000.0' and report.live['state_timeout_periods'] == '5'
    assert loop.announcement() == ('parameter set 1 from t = 0.020 s: u_max 15000.0 (was '
                                   '20000.0), state_timeout_periods 5 (was 3)')
    assert loop.announcement() is None and out.stamp_ns == TS_NS
    with pytest.raises(ParamError, match='must exceed u_min'):   # refused: none staged
        loop.stage({'u_min': 16000.0})
    loop.solve(_job(loop, 2))
    assert report.parameter_set == 1 and loop.controller.u_min == 0.0


def test_lockstep_holds_the_sample_of_lockstep_hold_s_until_a_request_came():
    loop, _ = _loop('lockstep', lockstep_hold_s=0.04)       # sample 2
    for k in (0, 1):
        job = _job(loop, k)
        assert not loop.holds(job)
        loop.solve(job)
    job = _job(loop, 2)
    assert loop.holds(job)                                   # waits for the request
    loop.stage({'u_max': 15000.0, 'lockstep_hold_s': 0.08})  # and moves the hold on
    assert not loop.holds(job)
    loop.solve(job)
    assert loop.controller.u_max == 15000.0
    job = _job(loop, 3)
    assert not loop.holds(job)                               # one hold per time
    loop.solve(job)
    # A request that came before its sample arrived releases that sample's hold too.
    loop.stage({'fallback': 'passive'})
    job = _job(loop, 4)
    assert not loop.holds(job)
    loop.solve(job)
    assert loop.controller.fallback == 'passive'
    realtime, _ = _loop('realtime', lockstep_hold_s=0.02)
    realtime.solve(_job(realtime, 0, 10**9))
    realtime.sched.armed = True                              # (its period's tick came)
    assert not realtime.holds(_job(realtime, 1, 10**9))      # real time never holds


# -- the segments of reported sets, and /parameter_events ---------------------------------------
def test_the_set_log_keeps_each_reported_set_once_in_order():
    log = segments.ParameterSetLog()
    for n, frm, alpha in ((0, 0, '1.0'), (0, 0, '1.0'), (1, 500, '0.5'), (1, 500, '0.5'),
                          (2, 900, '0.25')):
        log.add(NMPCReport(parameter_set=n, parameter_set_from_ns=frm,
                           live={'alpha1': alpha, 'use_preview': 'true'}))
    assert [(s.index, s.from_ns, s.values) for s in log.sets] == [
        (0, 0, {'alpha1': 1.0, 'use_preview': True}),
        (1, 500, {'alpha1': 0.5, 'use_preview': True}),
        (2, 900, {'alpha1': 0.25, 'use_preview': True})]
    t = np.arange(10) * 100
    segs = segments.from_sets(log.sets, 0, t, np.arange(10.0), np.ones(10), 100e-9)
    assert [s['samples'] for s in segs] == [5, 4, 1]
    assert segs[2]['changed'] == {'alpha1': [0.5, 0.25]}
    assert segments.lines(segments.block(segs))[1].strip().startswith('0.000-0.000 s, 5')


def test_parameter_events_decode_as_rclpy_serializes_them():
    from rcl_interfaces.msg import ParameterEvent
    from rclpy.parameter import Parameter
    from rclpy.serialization import serialize_message
    msg = ParameterEvent(node='/erva/nmpc_node')
    msg.stamp.sec, msg.stamp.nanosec = 1, 500
    values = {'alpha1': 0.5, 'use_preview': False, 'state_timeout_periods': 4,
              'fallback': 'passive', 'topics': ['state', '/clock'], 'w': [1.0, 2.5],
              'metadata': 'x' * 70_000}
    msg.changed_parameters = [Parameter(k, value=v).to_parameter_msg()
                              for k, v in values.items()]
    msg.deleted_parameters = [Parameter('gone', value=1).to_parameter_msg()]
    event = contract.decode_parameter_event(serialize_message(msg))
    assert (event.stamp_ns, event.node) == (1_000_000_500, '/erva/nmpc_node')
    assert event.changed == values and event.new == {} and event.deleted == ('gone',)
    data = serialize_message(msg)
    with pytest.raises(contract.CdrError):
        contract.decode_parameter_event(data[:len(data) // 2])
