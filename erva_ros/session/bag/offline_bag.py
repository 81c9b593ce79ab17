"""Write an offline closed-loop run (``erva_ros.core.studies.closed_loop``) as a session bag.

The bag has the live system's topic layout (``erva_ros.core.topics``), so ``erva report``,
``erva replay`` and Foxglove treat it like a recorded session.  Per control step k,
with t_k = t0 + k·Ts, it holds what the controller saw and did, in causal order::

    /erva/road/height   PointStamped    x = distance (m), z = w(t_k) (m)
    /erva/road/preview  JointTrajectory the preview the controller used, w(t_k + i·Ts)
    /erva/state         JointState      [z_s, z_us, z_d] positions (m), velocities (m/s)
                                        ([z_s, z_us] of the linear benchmark model)
    /erva/damping_cmd   JointTrajectory plan u_k .. u_{k+N-1} (Ns/m), stamp = state stamp
    /erva/sprung_accel  AccelStamped    z̈_s(t_k) (m/s²)
    /erva/generator     JointState      the model's generator (QuarterCarModel.generator):
                                        position z_d - (z_s - z_us), velocity v_gen,
                                        effort u·v_gen (P = effort·velocity, W)
    /diagnostics        DiagnosticArray once a second and after the last step: the
                                        plant's harvested energy up to the end of the
                                        step (J), the controller's solve times, counters

An offline run has no transport: log time = publish time = header stamp.  The plant's
cumulative energy per step comes from re-running the plant with the recorded commands
(deterministic: same CasADi function, same inputs), which also checks the states.
"""

import argparse
from dataclasses import dataclass
import dataclasses
import sys
import time
from typing import Dict, List, Mapping, Optional, Sequence

import numpy as np

from erva_ros.core import contract as wire, topics as contract
from erva_ros.core.bag import BagError
from erva_ros.core.bag.qos import control_profile
from erva_ros.core.bag.session import session_metadata
from erva_ros.core.bag.writer import BagWriter
from erva_ros.core.controllers import load_controller_settings, make_controller
from erva_ros.core.metrics import percentiles_ms
from erva_ros.core.model.params import load_erva_params, ParamError
from erva_ros.core.model.plant import PlantSimulator
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.reports import NMPCReport, PlantReport, report_status, Timing
from erva_ros.core.road.profiles import make_road, RoadError
from erva_ros.core.settings.controller import NUMERIC_SPECS
from erva_ros.core.studies.closed_loop import simulate_closed_loop
from erva_ros.core.topics import STATE_JOINTS

TOPIC = {name: f'{contract.NAMESPACE}/{name}' for name in (
    contract.STATE, contract.SPRUNG_ACCEL, contract.GENERATOR, contract.ROAD_HEIGHT,
    contract.ROAD_PREVIEW, contract.DAMPING_CMD)}
#: Names of the offline session's reports (typed as the live nodes' reports).
PLANT_STATUS = 'offline/plant'
CONTROLLER_STATUS = 'offline/controller'
#: Session metadata 'source' of offline sessions (their timing is not measured).
OFFLINE_SOURCE = 'offline closed loop'


@dataclass
class StepLog:
    """What one control step saw and did (SI units)."""

    t: float
    x: np.ndarray          # [z_s, ż_s, z_us, ż_us(, z_d, ż_d)]
    w: float
    distance_m: float
    preview: np.ndarray    # w(t + i·Ts), i = 0..N, as the controller got it
    plan: np.ndarray       # u_k .. u_{k+N-1}
    accel: float
    harvested_j: float     # J harvested from the start up to t_k + Ts
    solve_time_s: float
    status: str
    gen_position: float = float('nan')   # m, the model's generator displacement at t_k
    v_gen: float = float('nan')          # m/s, the model's generator velocity at t_k


class _CapturingController:
    """Delegate to a controller and keep the preview it was given at each step."""

    def __init__(self, controller):
        self._inner = controller
        self.previews: List[np.ndarray] = []

    def __getattr__(self, name):
        return getattr(self._inner, name)

    def reset(self):
        self.previews.clear()
        self._inner.reset()

    def compute(self, x, preview, t):
        self.previews.append(np.array(preview, dtype=float))
        return self._inner.compute(x, preview, t)


def step_messages(step: StepLog, stamp_ns: int, ts: float,
                  joints: Sequence[str] = STATE_JOINTS) -> List:
    """Return [(topic, CDR bytes)] of one step in causal order (module doc).

    ``joints``: the model's state joints (``QuarterCarModel.joints``).
    """
    ts_ns = wire.s_to_ns(ts)
    return [(TOPIC[contract.ROAD_HEIGHT], wire.encode_road_height(stamp_ns, step.distance_m,
                                                                  step.w)),
            (TOPIC[contract.ROAD_PREVIEW], wire.encode_preview(stamp_ns, step.preview, ts_ns)),
            (TOPIC[contract.STATE], wire.encode_state(stamp_ns, step.x, joints)),
            (TOPIC[contract.DAMPING_CMD], wire.encode_command(stamp_ns, step.plan, ts_ns)),
            (TOPIC[contract.SPRUNG_ACCEL], wire.encode_accel(stamp_ns, step.accel)),
            (TOPIC[contract.GENERATOR], wire.encode_generator(stamp_ns, step.gen_position,
                                                              step.v_gen, step.plan[0]))]


def diagnostics_message(stamp_ns: int, harvested_j: float, solve_s: List[float],
                        counters: Mapping[str, int], controller: str) -> bytes:
    """Return the offline session's DiagnosticArray: a plant and a controller report.

    Plant: ``harvested_j``, ``steps``; controller: ``solve_ms``, ``commands``,
    ``deadline_misses`` (the controller's late solves) and its own counters.
    """
    plant = PlantReport(node=PLANT_STATUS, message='offline plant', hardware_id='erva',
                        harvested_j=float(harvested_j), steps=int(counters.get('steps', 0)))
    nmpc = NMPCReport(node=CONTROLLER_STATUS, message='offline controller',
                      hardware_id='erva', controller=controller, commands=len(solve_s),
                      deadline_misses=int(counters.get('late', 0)),
                      solve_ms=Timing.of(percentiles_ms(solve_s)))
    for key, n in counters.items():
        setattr(nmpc, f'controller_{key}', int(n))
    return wire.encode_diagnostics(stamp_ns, [report_status(plant), report_status(nmpc)])


def write_session(bag_dir: str, steps: List[StepLog], ts: float, controller: str,
                  session: Optional[Mapping[str, str]] = None, t0_ns: Optional[int] = None,
                  diagnostics_period_s: float = 1.0,
                  final_counters: Optional[Mapping[str, int]] = None,
                  joints: Sequence[str] = STATE_JOINTS) -> Dict:
    """Write ``steps`` (of a model with state ``joints``) as a session bag; return its metadata.

    The controller counters on /diagnostics count step statuses as they go; the last
    message carries ``final_counters`` (the controller's own, e.g. late) too.
    """
    t0_ns = time.time_ns() if t0_ns is None else int(t0_ns)
    session = {'source': OFFLINE_SOURCE, **(session or {})}
    offered = [control_profile()]
    writer = BagWriter(bag_dir, session=session, custom_data=session)
    try:
        for name, topic in TOPIC.items():
            writer.add_topic(topic, contract.TOPIC_TYPES[topic], offered)
        writer.add_topic(contract.DIAGNOSTICS, contract.TOPIC_TYPES[contract.DIAGNOSTICS],
                         offered)
        every = max(1, int(round(diagnostics_period_s / ts)))
        counters: Dict[str, int] = {'steps': 0, 'ok': 0, 'fallback_plan': 0,
                                    'fallback_passive': 0}
        solve: List[float] = []
        for k, step in enumerate(steps):
            stamp = t0_ns + int(round(step.t * 1e9))
            for topic, data in step_messages(step, stamp, ts, joints):
                writer.write(topic, data, stamp, stamp)
            counters['steps'] += 1
            if step.status in counters:
                counters[step.status] += 1
            solve.append(step.solve_time_s)
            if k == len(steps) - 1 and final_counters:
                counters.update(final_counters)
            if (k + 1) % every == 0 or k == len(steps) - 1:
                writer.write(contract.DIAGNOSTICS, diagnostics_message(
                    stamp, step.harvested_j, solve, counters, controller), stamp, stamp)
        return writer.close()
    except BaseException:
        writer.abort()
        raise


def run_and_record(bag_dir: str, model, controller, road, duration_s: float,
                   preview_model=None, session: Optional[Mapping[str, str]] = None,
                   t0_ns: Optional[int] = None):
    """Run the offline closed loop on ``model``'s plant and write it as a session.

    Returns (result, metadata).
    """
    session = {'model': model.kind, **(session or {})}
    capture = _CapturingController(controller)
    result = simulate_closed_loop(model, capture, road, duration_s,
                                  preview_model=preview_model, keep_plans=True)
    # Energy harvested up to t_k + Ts: re-run the plant with the commands applied.
    plant = PlantSimulator(model, result.ts)
    energy = np.empty(result.t.size)
    gen = np.empty((result.t.size, 2))
    for k, t_k in enumerate(result.t):
        if not np.allclose(plant.x, result.x[k], rtol=0, atol=1e-12):
            raise RuntimeError(f'plant re-run diverged from the closed loop at t = {t_k:g} s')
        gen[k] = plant.generator(result.x[k], result.u[k])[:2]
        plant.step(result.u[k], road.height(t_k), road.height((k + 1) * result.ts))
        energy[k] = plant.harvested_j
    steps = [StepLog(float(result.t[k]), result.x[k], float(result.w[k]),
                     float(road.distance(result.t[k])), capture.previews[k],
                     result.plans[k], float(result.sprung_accel[k]), float(energy[k]),
                     float(result.solve_time_s[k]), result.status[k], *map(float, gen[k]))
             for k in range(result.t.size)]
    meta = write_session(bag_dir, steps, result.ts, result.controller, session, t0_ns,
                         final_counters=result.counters, joints=model.joints)
    return result, meta


__all__ = ['StepLog', 'step_messages', 'diagnostics_message', 'write_session',
           'run_and_record', 'PLANT_STATUS', 'CONTROLLER_STATUS']


def main(argv=None) -> int:
    """Write an offline session bag (``python -m erva_ros.session.bag.offline_bag DIR``)."""
    parser = argparse.ArgumentParser(
        prog='python -m erva_ros.session.bag.offline_bag',
        description='Run the offline closed loop and write it as a session bag with the '
                    'live topic layout (used for bags/sample).')
    parser.add_argument('bag_dir', help='bag directory to create')
    parser.add_argument('--controller', default=None, help='default: from config/nmpc.yaml')
    parser.add_argument('--road', default='paper', help='road kind (default paper)')
    parser.add_argument('--seed', type=int, default=1, help='road seed (default 1)')
    parser.add_argument('--duration', type=float, default=4.0, help='seconds (default 4)')
    parser.add_argument('--params', default=None, help='ERVA parameter file')
    parser.add_argument('--settings', default=None, help='controller settings file')
    parser.add_argument('--keep-budget', action='store_true',
                        help='keep the settings\' wall-clock solve budget (default: lift it '
                             'to its maximum, as lock-step does, since offline is not real '
                             'time and a budget would make the run depend on the machine)')
    args = parser.parse_args(argv)
    try:
        params = load_erva_params(args.params)
        overrides = {'controller': args.controller}
        if not args.keep_budget:
            overrides['time_budget_s'] = NUMERIC_SPECS['time_budget_s'].hi
        settings = load_controller_settings(args.settings, overrides)
        road = make_road(args.road, args.duration, settings.ts, seed=args.seed)
        model = make_model(params)
        controller = make_controller(settings.controller, model, settings)
        session = session_metadata(args.road, parameters={
            'erva': dataclasses.asdict(params), 'controller': settings.as_dict(),
            'road': {'kind': args.road, 'duration_s': args.duration}},
            seed=args.seed, controller=settings.controller)
        result, meta = run_and_record(args.bag_dir, model, controller, road, args.duration,
                                      session=session)
    except (BagError, ParamError, RoadError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 2
    m = result.metrics
    print(f'wrote {args.bag_dir}: {meta["message_count"]} messages, acc 2-norm '
          f'{m["acc_2norm"]:.4f} m/s², power {m["power_w"]:.4f} W')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
