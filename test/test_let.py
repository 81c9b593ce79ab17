"""Logical execution time in the plant's core: a command acts at its sample + d, exactly.

PlantLoop (plant_sim_node without ROS) driven sample by sample with the same controller
gives the offline closed loop with ``actuation_delay_s`` = d bit for bit; a realtime loop
whose commands arrive before t_k + d gives the same; a late one never acts (the late
rule, core/loop/command_hold.py) and is counted.
"""

import numpy as np
import pytest

from erva_ros.core.studies.closed_loop import simulate_closed_loop
from erva_ros.core.controllers import make_controller
from erva_ros.core.controllers.settings import ControllerSettings
from erva_ros.core.loop.plant_loop import PlantLoop
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import ERVAParams
from erva_ros.core.reports import PlantReport
from erva_ros.core.road.profiles import make_road

TS, D, DURATION = 0.02, 0.006, 1.6
TS_NS, D_NS = 20_000_000, 6_000_000
T0 = 1_000_000_000_000          # a realtime session's first stamp (ns)


def _cfg(mode, delay=D):
    return {'model': 'erva', 'ts': TS, 'mode': mode, 'duration_s': DURATION,
            'command_delay_s': delay, 'command_timeout_s': 0.2}


def _controller(delay=D):
    settings = ControllerSettings().with_(command_delay_s=delay)
    return make_controller('skyhook', make_model(ERVAParams()), settings)


def _drive(mode, arrival_ns, delay=D):
    """Run PlantLoop over the bump road; command k arrives arrival_ns(k) after t_k."""
    params, road = ERVAParams(), make_road('bump', DURATION + 1, TS)
    loop = PlantLoop(make_model(params), _cfg(mode, delay), PlantReport())
    ctrl = _controller(delay)
    ctrl.reset()
    t0 = T0 if mode == 'realtime' else 0
    xs, us = [], []
    loop.on_height(t0, float(road.height(0.0)))
    x = loop.plant.x.copy()
    for k in range(loop.n_steps):
        t_k = k * TS
        res = ctrl.compute(x, road.preview(t_k, ctrl.horizon, TS), t_k)
        stamp = t0 + k * TS_NS
        if loop.on_command(stamp, np.asarray(res.plan), stamp + arrival_ns(k)):
            loop.decide()
        xs.append(x)
        us.append(res.damping_cmd)
        # (k + 1)·Ts as the offline loop: t_k + Ts can differ from it in the last bit
        step, = loop.on_height(stamp + TS_NS, float(road.height((k + 1) * TS)))
        x = step.x_next
    loop.fill()
    return np.array(xs), np.array(us), loop.report


def _offline(delay=D):
    road = make_road('bump', DURATION + 1, TS)
    return simulate_closed_loop(make_model(ERVAParams()), _controller(delay), road, DURATION,
                                actuation_delay_s=delay)


@pytest.mark.parametrize('mode', ['lockstep', 'realtime'])
def test_commands_on_time_give_the_offline_loop_bit_for_bit(mode):
    ref = _offline()
    xs, us, report = _drive(mode, lambda k: D_NS - 1000)    # 1 us before the instant
    assert np.array_equal(xs, ref.x) and np.array_equal(us, ref.u)
    assert report.u_from_command == report.steps == ref.u.size
    assert report.late_commands == 0 and report.command_delay_ms == pytest.approx(6.0)


def test_d_zero_is_the_paper_loop():
    ref = _offline(0.0)
    xs, _, report = _drive('realtime', lambda k: TS_NS - 1000, delay=0.0)  # before w(t_k+1)
    assert np.array_equal(xs, ref.x) and report.late_commands == 0


def test_a_late_command_never_acts_and_is_counted():
    ref = _offline()
    late = {52, 56, 70}      # the bump starts at 1.0 s; u switches at 52 and 56
    xs, _, report = _drive('realtime', lambda k: D_NS + (1000 if k in late else -1000))
    assert report.late_commands == 3
    assert report.u_from_command == report.steps - 3 and report.u_from_plan == 3
    assert np.array_equal(xs[:53], ref.x[:53])          # x_52 is before u_52 could act
    assert not np.array_equal(xs[53], ref.x[53])        # the plan acted instead
    assert report.command_arrival_ms.samples == report.steps
    assert report.arrival_p999_ms == pytest.approx(6.001, abs=1e-6)


def test_passive_before_any_command_acted_is_a_warning_and_after_an_outage_an_error():
    # Sample 0 with d > 0: its command came after t_0 + d (a cold first solve), so it never
    # acts and there is no earlier plan: passive c_e0 by design, a WARN.  Once a command
    # has acted, passive damping means the commands stopped and the plan ran out: ERROR.
    from erva_ros.core.levels import ERROR, WARN
    loop = PlantLoop(make_model(ERVAParams()), _cfg('realtime'), PlantReport())
    loop.on_height(T0, 0.0)
    loop.on_command(T0, np.full(2, 3000.0), T0 + D_NS + 1000)           # late
    decisions = [s.decision for s in loop.on_height(T0 + TS_NS, 0.0)]
    assert decisions == [(WARN, 'first command late (after t_k + d): passive damping c_e0')]
    loop.on_command(T0 + TS_NS, np.full(2, 3000.0), T0 + TS_NS + D_NS - 1000)
    for k in (2, 3, 4):
        decisions += [s.decision for s in loop.on_height(T0 + k * TS_NS, 0.0)]
    assert [lvl for lvl, _ in decisions] == [WARN, 0, WARN, ERROR]
    assert decisions[-1] == (ERROR, 'no command and plan used up: passive damping c_e0')
    loop.fill()
    assert (loop.report.late_commands, loop.report.u_from_command, loop.report.u_from_plan,
            loop.report.u_from_passive) == (1, 1, 1, 2)
