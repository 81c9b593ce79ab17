"""The plan's prediction (core/loop/prediction.py): it is the plant's trajectory under the plan.

Predictor rolls a plan out on the shared model; PlantSimulator, stepped with the same
commands (the acting one before t_k + d, then the plan) on the same road, must reach
the same states and outputs at every t_{k+j}: to rounding, with and without a delay.
The message is read back by rosbags' CDR decoder (a reader we did not write).
"""

import numpy as np
import pytest

from erva_ros.core import contract, topics
from erva_ros.core.loop.prediction import (PlanPredictor, prediction_errors,
                                           prediction_joint_names, prediction_steps, Predictor)
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import load_erva_params
from erva_ros.core.model.plant import PlantSimulator

TS, N = 0.02, 10


def _case(kind, seed=1):
    params = load_erva_params(None)
    rng = np.random.default_rng(seed)
    model = make_model(params, kind)
    x0 = rng.normal(0.0, 0.01, model.nx)
    plan = rng.uniform(0.0, 5000.0, N)
    road = rng.uniform(-0.02, 0.02, N + 1)
    return params, model, x0, 1234.0, plan, road


def _plant(params, kind, x0, acting, plan, road, delay, codegen):
    """Step PlantSimulator over the plan as the plant node would; return x, z̈_s, P."""
    sim = PlantSimulator(make_model(params, kind), TS, x0=x0, codegen=codegen)
    sim.prepare_delay(delay)
    xs, acc, pw, before = [x0.copy()], [], [], acting
    for j in range(N + 1):
        now = before if delay > 0 else plan[min(j, N - 1)]   # acting at t_{k+j}
        s = sim.sample(now, road[j])
        acc.append(s.sprung_accel)
        pw.append(s.power_w)
        if j < N:
            sim.step_delayed(before, plan[j], delay, road[j], road[j + 1])
            before = plan[j]
            xs.append(sim.x.copy())
    return np.array(xs), np.array(acc), np.array(pw)


@pytest.mark.parametrize('kind', ['erva', 'benchmark'])
@pytest.mark.parametrize('delay', [0.0, 0.005])
@pytest.mark.parametrize('codegen', ['off', 'auto'])
def test_the_prediction_is_the_plants_trajectory_under_the_plan(kind, delay, codegen):
    params, model, x0, acting, plan, road = _case(kind)
    got = Predictor(model, TS, N, delay, codegen)(x0, acting, plan, road)
    xs, acc, pw = _plant(params, kind, x0, acting, plan, road, delay, codegen)
    assert got.states.shape == (N + 1, model.nx)
    # Far from zero (a trajectory, not a rest state), equal to rounding.
    assert np.abs(xs[1:] - xs[0]).max() > 1e-3
    np.testing.assert_allclose(got.states, xs, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(got.sprung_accel, acc, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(got.power, pw, rtol=1e-12, atol=1e-12)


def test_the_delay_and_the_acting_command_matter():
    """With d > 0, [t_k, t_k + d) runs on the acting damping: another value, another x_1."""
    _, model, x0, acting, plan, road = _case('erva')
    delayed = Predictor(model, TS, N, 0.005)
    a, b = delayed(x0, acting, plan, road), delayed(x0, acting + 3000.0, plan, road)
    assert np.abs(a.states[1] - b.states[1]).max() > 1e-6
    assert a.sprung_accel[0] != b.sprung_accel[0]          # z̈_s(t_k) with the acting one
    now = Predictor(model, TS, N, 0.0)(x0, acting, plan, road)
    assert np.abs(now.states[1] - a.states[1]).max() > 1e-6
    with pytest.raises(ValueError, match='need 10 plan values and 11 preview heights'):
        delayed(x0, acting, plan[:5], road)
    with pytest.raises(ValueError, match='command delay'):
        Predictor(model, TS, N, TS)


def test_the_acting_command_follows_the_commands_published():
    params, model, x0, _, plan, road = _case('erva')
    ts_ns = int(TS * 1e9)
    p = PlanPredictor(model, TS, N, 0.005, params.c_e0)
    assert p.acting(10 * ts_ns) == params.c_e0                 # none yet: passive
    p.sample(10 * ts_ns, x0, plan, road)
    assert p.acting(11 * ts_ns) == plan[0]                      # u_10 acts until t_11 + d
    assert p.acting(13 * ts_ns) == plan[2]                      # missed samples: its plan
    assert p.acting((11 + N) * ts_ns) == params.c_e0            # plan used up: passive
    p.commanded(12 * ts_ns, np.full(N, 777.0))                  # a safe command
    assert p.acting(13 * ts_ns) == 777.0
    assert p.names == ('z_s', 'zdot_s', 'z_us', 'zdot_us', 'z_d', 'zdot_d',
                       'sprung_accel', 'power')


def test_the_message_round_trips_and_rosbags_reads_it():
    from rosbags.typesys import get_typestore, Stores
    _, model, x0, acting, plan, road = _case('erva')
    got = Predictor(model, TS, N, 0.005)(x0, acting, plan, road)
    names = prediction_joint_names(model.state_names)
    data = contract.encode_prediction(123 * 10 ** 9 + 7, names, got.table(), int(TS * 1e9))
    back = contract.decode_prediction(data)
    assert back.stamp_ns == 123 * 10 ** 9 + 7 and back.names == names
    np.testing.assert_array_equal(back.values, got.table())
    np.testing.assert_array_equal(back.column('power'), got.power)
    assert back.offsets_s == pytest.approx([j * TS for j in range(N + 1)], abs=1e-12)
    assert contract.DECODERS[topics.PREDICTION] is contract.decode_prediction
    store = get_typestore(Stores.ROS2_JAZZY)
    msg = store.deserialize_cdr(data, 'trajectory_msgs/msg/JointTrajectory')
    assert list(msg.joint_names) == list(names)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (123, 7)
    assert len(msg.points) == N + 1
    np.testing.assert_array_equal(msg.points[4].positions, got.table()[4])
    assert msg.points[4].time_from_start.nanosec == 4 * int(TS * 1e9)
    assert store.serialize_cdr(msg, 'trajectory_msgs/msg/JointTrajectory') == data
    with pytest.raises(contract.MessageRejected, match='positions for 8 joints'):
        contract.decode_prediction(contract.encode_prediction(0, names, [[1.0, 2.0]], 1))


def test_errors_h_steps_ahead_match_by_stamp():
    ts_ns = 20
    names = ('sprung_accel',)
    tables = [np.arange(N + 1, dtype=float).reshape(-1, 1) + k for k in range(3)]
    stamps = [0, 20, 40]
    actual = {'sprung_accel': (np.arange(0, 400, 20), np.zeros(20))}
    actual['sprung_accel'][1][2] = 1.0                     # the sample at t = 40
    errors = prediction_errors(stamps, tables, names, ts_ns, actual)
    assert prediction_steps(N) == (1, 5, N) and list(errors) == [1, 5, N]
    one = errors[1]['sprung_accel']
    # predicted 1 + k at t_{k+1}; actual 0 except 1 at t = 40 (k = 1): errors 1, 1, 3.
    assert one['samples'] == 3
    assert one['max'] == 3.0 and one['rms'] == pytest.approx(np.sqrt(11 / 3))
    assert prediction_steps(3) == (1, 3) and prediction_steps(1) == (1,)
    far = prediction_errors(stamps, tables, names, ts_ns, {'sprung_accel': (np.array([0]),
                                                                            np.zeros(1))})
    assert far[5]['sprung_accel']['samples'] == 0 and np.isnan(far[5]['sprung_accel']['rms'])
