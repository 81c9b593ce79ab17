"""The NMPC's converged reference: IPOPT on the very collocation NLP the real-time SQP solves.

``solver: ipopt`` runs it every sample (:class:`IpoptReference`, tol 1e-8), from
``ipopt_starts`` of the real-time SQP's starts, keeping the best local optimum: the OCP is
non-convex (bilinear u·v_gen, near bang-bang optima).  :func:`reference_gap` judges one
recorded real-time solve against it (`erva bench`'s ``step_gap_pct``); the clairvoyant
bound converges its starts with :func:`build_ipopt` too.
"""

from functools import lru_cache
from typing import NamedTuple

import casadi as ca
import numpy as np

from erva_ros.core.controllers.base import SolveFailure
from erva_ros.core.controllers.ocp import OCP
from erva_ros.core.controllers.sqp import plan_value_function

#: IPOPT tolerance of the converged reference.
IPOPT_TOL = 1e-8


@lru_cache(maxsize=32)
def build_ipopt(ocp: OCP, max_iter: int) -> ca.Function:
    """Return IPOPT on the OCP's NLP (the converged reference)."""
    zs = ca.SX.sym('z', ocp.nz)
    ps = ca.SX.sym('p', ocp.nlp.size1_in(1))
    f, g = ocp.nlp(zs, ps)
    opts = {'ipopt': {'print_level': 0, 'tol': IPOPT_TOL, 'max_iter': int(max_iter),
                      'sb': 'yes', 'mu_strategy': 'adaptive'},
            'print_time': False, 'error_on_fail': False}
    return ca.nlpsol('nmpc_ipopt', 'ipopt', {'x': zs, 'p': ps, 'f': f, 'g': g}, opts)


def converge_from(ocp: OCP, ipopt: ca.Function, x, a_prev, pb, starts):
    """Solve the OCP with IPOPT from each start plan (scaled inputs); keep the best.

    ``pb``: the OCP's parameters and the input box, as the real-time SQP takes them
    (:meth:`OCP.with_box`).  Returns (the best converged solution or None, the last
    return status, the iteration count of each start).
    """
    p = pb[:ocp.n_p]
    lbz, ubz = ocp.bounds(x, a_prev, tuple(pb[ocp.n_p:]))
    best, status, iterations = None, 'failed', []
    for u0 in starts:
        z0 = np.asarray(ocp.rollout(x, a_prev, u0, ocp.road_params(p))).ravel()
        sol = ipopt(x0=z0, p=p, lbx=lbz, ubx=ubz, lbg=0, ubg=0)
        stats = ipopt.stats()
        iterations.append(int(stats.get('iter_count', 0)))
        status = str(stats.get('return_status', '')) or status
        if not (stats.get('success') or status == 'Solved_To_Acceptable_Level'):
            continue
        if best is None or float(sol['f']) < float(best['f']):
            best = sol
    return best, status, iterations


class IpoptReference:
    """IPOPT converged every sample, called as the real-time SQP is (``solver: ipopt``).

    (x0, a_prev, u_guess, u_alt, p) -> (u, z, f, iterations), inputs scaled as in the
    OCP; it converges from the warm start ``u_guess`` and the first ``n_starts`` − 1
    columns of ``u_alt`` (the SQP's other starts, constant c_e0 first) and keeps the
    best; the iterations are those from the warm start (what warm starting is judged
    by).  Raises :class:`SolveFailure` when no start converges.
    """

    def __init__(self, ocp: OCP, max_iter: int, n_starts: int):
        self.ocp = ocp
        self.n_starts = int(n_starts)
        self._ipopt = build_ipopt(ocp, max_iter)

    def __call__(self, x, a_prev, u_guess, u_alt, p):
        starts = [u_guess] + [u_alt[:, j] for j in range(self.n_starts - 1)]
        if self.n_starts == 2 and np.allclose(u_guess, u_alt[:, 0]):
            starts = starts[:1]             # the same start twice
        best, status, iterations = converge_from(self.ocp, self._ipopt, x, a_prev, p, starts)
        if best is None:
            raise SolveFailure(f'ipopt: {status}')
        z = np.asarray(best['x']).ravel()
        return z[self.ocp.u_index], z, float(best['f']), iterations[0]


class RecordedProblem(NamedTuple):
    """One real-time solve, kept to be judged later (:func:`reference_gap`)."""

    x: np.ndarray           # x(t_k), SI
    a_prev: float           # x_a(k−1)
    u_guess: np.ndarray     # the warm start (scaled inputs)
    u_alt: np.ndarray       # the other starts, one per column (constant c_e0 first)
    p: np.ndarray           # the solver's parameters: the OCP's, then the box (OCP.with_box)
    u: np.ndarray           # the real-time solution (scaled inputs)
    f: float                # its objective as the solver returned it


def reference_gap(ocp: OCP, problem: RecordedProblem, ipopt_max_iter: int,
                  codegen: str = 'off') -> float:
    """Return a real-time solve's relative objective gap to a converged one (≥ 0).

    IPOPT starts from the warm start, from c_e0 and from the real-time solution
    itself, so the reference is never worse than what it judges:
    (f_rt − f_ref) / |f_ref|, f_rt the plan's cost on the collocation equations (the
    solver's own z may be a start's).
    """
    pr = problem
    f_rt = float(plan_value_function(ocp, codegen)(pr.x, pr.a_prev, pr.u,
                                                   pr.p[:ocp.n_p])[1])
    best, _, _ = converge_from(ocp, build_ipopt(ocp, ipopt_max_iter), pr.x, pr.a_prev, pr.p,
                               (pr.u_guess, pr.u_alt[:, 0], pr.u))
    f_ref = f_rt if best is None else min(f_rt, float(best['f']))
    return (f_rt - f_ref) / abs(f_ref) if f_ref != 0 else 0.0


__all__ = ['IPOPT_TOL', 'IpoptReference', 'RecordedProblem', 'build_ipopt', 'converge_from',
           'reference_gap']
