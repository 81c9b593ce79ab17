"""The clairvoyant bound: one optimal control problem over the whole run, perfect road.

Not a causal controller: it sees the entire road in advance and chooses the whole
damping sequence u_0..u_{n−1} at once, minimising the run's evaluation objective

    J(α) = α1·acc_rms² − α2·P_avg      (acc sampled at t_k as in erva_ros.core.metrics,
                                         P_avg = harvested energy / duration)

on the same collocation model as the NMPC (Radau IIA, one interval per Ts,
:func:`erva_ros.core.controllers.nmpc.build_ocp` with cost 'bound'), solved by IPOPT.
The problem is non-convex (bilinear u·v_gen, bang-bang optima), so it is solved
from several starts -- the constant plans u_min, c_e0, u_max and every causal
controller's closed-loop command sequence -- and each local optimum is *evaluated
in the real plant* (PlantSimulator, 0.5 ms RK4); the best plant value is the bound.
A start is never returned as the bound itself: if IPOPT ends worse than where it
started, that start simply loses, so ``test_ctrl_clairvoyant`` can catch a causal
controller that beats the bound (a leaking preview or a wrong plant).
"""

from dataclasses import dataclass, field
import time
from typing import Dict, Mapping, Optional, Tuple

import numpy as np

from erva_ros.core.closed_loop import ClosedLoopResult, evaluation_objective, simulate_closed_loop
from erva_ros.core.controllers.base import Controller
from erva_ros.core.controllers.nmpc import build_ipopt, build_ocp, stable_rollout_substep, U_SCALE
from erva_ros.core.model import get_model
from erva_ros.core.params import ERVAParams
from erva_ros.core.roads import Road

#: IPOPT iteration limit per start of the bound.
BOUND_MAX_ITER = 500


class ReplayController(Controller):
    """Apply a precomputed command sequence (open loop), e.g. the clairvoyant optimum."""

    name = 'clairvoyant'

    def __init__(self, commands: np.ndarray, ts: float, u_min: float, u_max: float,
                 c_e0: float, name: str = 'clairvoyant'):
        self.commands = np.asarray(commands, dtype=float).ravel()
        self.name = name
        super().__init__(1, ts, u_min, u_max, c_e0)

    def _compute(self, x, preview, t):
        k = min(int(round(t / self.ts)), self.commands.size - 1)
        return np.array([self.commands[k]]), 0


@dataclass
class BoundResult:
    """The bound's plant run, and the plant objective reached from every start."""

    run: ClosedLoopResult
    objective: float                    # J(α) of the best start, in the plant
    best_start: str
    starts: Dict[str, float] = field(default_factory=dict)   # start -> plant J(α)
    solve_s: float = 0.0


def _evaluate(params, commands, road, duration_s, ts, kind, u_min, u_max):
    ctrl = ReplayController(commands, ts, u_min, u_max, params.c_e0)
    return simulate_closed_loop(params, ctrl, road, duration_s, ts, kind=kind)


def clairvoyant_bound(params: ERVAParams, road: Road, duration_s: float, ts: float,
                      alpha: Tuple[float, float], u_min: float, u_max: float,
                      starts: Optional[Mapping[str, np.ndarray]] = None, kind: str = 'erva',
                      max_iter: int = BOUND_MAX_ITER) -> BoundResult:
    """Solve the whole-run OCP from every start; return the best, evaluated in the plant.

    ``starts`` maps a name (e.g. a causal controller) to its command sequence (Ns/m,
    length n = duration/ts); constant u_min, c_e0 and u_max starts are always added.
    """
    n = int(round(duration_s / ts))
    model = get_model(params, kind)
    ocp = build_ocp(model, ts, (1,) * n, 'bound', u_min, u_max, 0.0,
                    rollout_substep_s=stable_rollout_substep(model, u_max))
    solver = build_ipopt(ocp, max_iter)
    w = road.height(ts * np.arange(n + 1))
    p = np.r_[w, alpha[0] / n, alpha[1] / n]   # objective scaled to J(α)
    x0 = model.zero_state()
    a0 = float(model.sprung_accel(x0, params.c_e0, w[0]))
    lbz, ubz = ocp.bounds(x0, a0)
    all_starts = {'u_min': np.full(n, u_min), 'c_e0': np.full(n, params.c_e0),
                  'u_max': np.full(n, u_max)}
    for name, seq in (starts or {}).items():
        seq = np.asarray(seq, dtype=float).ravel()
        if seq.size != n:
            raise ValueError(f'start {name!r} has {seq.size} commands, need {n}')
        all_starts[name] = np.clip(seq, u_min, u_max)
    t0 = time.perf_counter()
    best: Optional[Tuple[float, str, ClosedLoopResult]] = None
    values: Dict[str, float] = {}
    for name, seq in all_starts.items():
        z0 = np.asarray(ocp.rollout(x0, a0, seq / U_SCALE, w)).ravel()
        sol = solver(x0=z0, p=p, lbx=lbz, ubx=ubz, lbg=0, ubg=0)
        u_opt = np.clip(np.asarray(sol['x']).ravel()[ocp.u_index] * U_SCALE, u_min, u_max)
        if not np.all(np.isfinite(u_opt)):
            continue
        run = _evaluate(params, u_opt, road, duration_s, ts, kind, u_min, u_max)
        value = evaluation_objective(run.metrics, alpha)
        values[name] = value
        if best is None or value < best[0]:
            best = (value, name, run)
    if best is None:
        raise RuntimeError('clairvoyant bound: IPOPT failed from every start')
    return BoundResult(best[2], best[0], best[1], values, time.perf_counter() - t0)


__all__ = ['ReplayController', 'BoundResult', 'clairvoyant_bound', 'BOUND_MAX_ITER']
