"""Grey-box identification of the ERVA's physical parameters from recorded sessions.

The model is the shared one (:func:`erva_ros.core.model.quarter_car.symbolic`), its parameters made
CasADi symbols, so the fit differentiates the very equations the plant, the NMPC and
the EKF use.  The data (:class:`Recording`) are what a session records on the sample
grid t_k = k·Ts: the road height at the tyre w(t_k), the damping the actuator applied
(c_e at t_k and its mean over the cycle before) and the measured outputs -- the ECU's
three sensors (z̈_s, z_s − z_us, φ̇ = v_gen/l) or, from a full-state session, the state
and z̈_s.

**Method: output error by multiple shooting.**  The recording is cut into segments of
``segment_s``; each segment is simulated from its own initial state (6 unknowns, no
continuity between segments), with the road linear between samples and, inside each
cycle, the previous c_e until the switch instant τ_k and the new one after it
(τ_k follows from c_e and its cycle mean: one switch per cycle, as the ECU latches a
command a few ms after the sample).  The unknowns -- the free parameters, as log-ratios
to the prior, and the segments' initial states -- minimise Σ ((ŷ − y)/σ)², each channel
weighted by its noise σ (first the sensors' specification, then the residual RMS of a
first fit).  Levenberg-Marquardt with exact derivatives: the step function carries the
sensitivities ∂x/∂(x_0, p) through RK4 (``substeps`` per cycle), and the segment states
are eliminated blockwise (Schur complement), so a step costs one simulation.

**What the data determine.**  The Fisher information of the parameters is that Schur
complement (the initial states estimated too).  A parameter whose relative standard
deviation, with every other free parameter estimated as well, exceeds
``max_rel_std`` is fixed to its prior, the worst first, until every free one is
determined; the reason names its strongest correlation (e.g. m_r with m_d: at small
amplitude only m_r + m_d enters, the inertia nonlinearity ε·r_1 separating them is
tiny).  c_e0 is not in the equations of motion (the passive command value) and is
always kept.  For each free parameter the relative standard deviation each channel
alone would give says which signal determines it.

**Intervals** are the Gauss-Newton covariance σ²·(JᵀJ)⁻¹ of the log-parameters (so
asymmetric in the parameter, never negative), 95 %: exp(±1.96·sd), plus what the
undetermined parameters' prior spread (±20 % uniform) does to the estimates through
their correlation (m_d takes up the error of m_r's prior).  They assume white residuals;
the fit reports the residuals' lag-1 autocorrelation to show how far that holds.

**Held-out fit:** on data not used by the fit, each contiguous run is simulated from an
initial state fitted to it (6 unknowns), and the normalised RMS fit per channel is
100·(1 − ‖y − ŷ‖/‖y − ȳ‖) %, as system-identification tools report it.
"""

from dataclasses import dataclass, field
import math
from typing import Dict, List, Optional, Sequence, Tuple

import casadi as ca
import numpy as np

from erva_ros.core.errors import CLIError
from erva_ros.core.model.quarter_car import QuarterCarModel, rk4
from erva_ros.core.model.params import ERVAParams, validate_erva
from erva_ros.core.settings.erva import ERVA_SPECS

#: Parameters in the equations of motion, in the order of the symbolic vector p.
PARAMETERS = tuple(k for k in ERVA_SPECS if k != 'c_e0')
#: Parameters the dynamics do not contain, with the reason they keep their prior value.
NOT_IN_MODEL = {'c_e0': 'not in the equations of motion (the passive command value)'}
#: Output channels and units: the ECU's sensors, and a full-state session's signals.
UNITS = {'sprung_accel': 'm/s^2', 'deflection': 'm', 'generator_speed': 'rad/s',
         'z_s': 'm', 'zdot_s': 'm/s', 'z_us': 'm', 'zdot_us': 'm/s', 'z_d': 'm',
         'zdot_d': 'm/s'}
ECU_CHANNELS = ('sprung_accel', 'deflection', 'generator_speed')
STATE_CHANNELS = ('sprung_accel', 'z_s', 'zdot_s', 'z_us', 'zdot_us', 'z_d', 'zdot_d')
#: Data needed at least, after the held-out part is set aside (s).
MIN_FIT_S = 5.0
#: Why a parameter was fixed, when the data do not determine it.
UNDETERMINED = 'not determined by the data'
#: Relative standard deviation of an undetermined parameter's prior, propagated into the
#: intervals of the others: a uniform spread of ±20 % around the prior.
PRIOR_REL_STD = 0.2 / math.sqrt(3)
#: Default relative standard deviation above which a parameter counts as undetermined:
#: its 95 % interval would span ±20 %, the spread a prototype's parameters are assumed to
#: have around the prior -- the data then say nothing the prior does not.
MAX_REL_STD = 0.10
Z95 = 1.959963984540054
NX = 6


class IdentifyError(CLIError):
    """The data cannot identify the model (bad input): one line, exit status 2."""


@dataclass
class Recording:
    """One session's data on the sample grid t_k = t0 + k·Ts (SI units; NaN = missing).

    ``u_now[k]`` is the damping acting at t_k (what z̈_s(t_k) depends on) and
    ``u_mean[k]`` its mean over [t_{k−1}, t_k]; a command held over each cycle has
    ``u_mean[k + 1] == u_now[k]``.
    """

    name: str
    ts: float
    w: np.ndarray                   # (n,) road height at the tyre, m
    u_now: np.ndarray               # (n,) Ns/m
    u_mean: np.ndarray              # (n,) Ns/m
    y: np.ndarray                   # (n, len(channels))
    channels: Tuple[str, ...] = ECU_CHANNELS
    t0: float = 0.0                 # s, time of sample 0 (for reports)

    def __post_init__(self):
        self.w = np.asarray(self.w, dtype=float)
        self.u_now = np.asarray(self.u_now, dtype=float)
        self.u_mean = np.asarray(self.u_mean, dtype=float)
        self.y = np.asarray(self.y, dtype=float).reshape(self.w.size, len(self.channels))
        if not self.w.size == self.u_now.size == self.u_mean.size:
            raise ValueError(f'{self.name}: w, u_now and u_mean differ in length')
        unknown = [c for c in self.channels if c not in UNITS]
        if unknown:
            raise ValueError(f'{self.name}: unknown channels {unknown}')

    @property
    def n(self) -> int:
        return int(self.w.size)

    @property
    def duration_s(self) -> float:
        return self.n * self.ts

    def part(self, start: int, stop: int, suffix: str = '') -> 'Recording':
        """Return samples [start, stop) as a recording of their own."""
        return Recording(self.name + suffix, self.ts, self.w[start:stop],
                         self.u_now[start:stop], self.u_mean[start:stop], self.y[start:stop],
                         self.channels, self.t0 + start * self.ts)

    def switches(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return, per cycle [t_k, t_k+1], (u before the switch, u after, switch delay τ_k s).

        From c_e at both ends and the cycle mean: u_a·τ + u_b·(Ts − τ) = Ts·u_mean.  No
        change in the cycle: τ = 0 (one piece).
        """
        ua, ub, mean = self.u_now[:-1], self.u_now[1:], self.u_mean[1:]
        du = ua - ub
        with np.errstate(invalid='ignore', divide='ignore'):
            frac = np.where(np.abs(du) > 1e-9 * (1 + np.abs(ua)), (mean - ub) / du, 0.0)
        frac = np.where(np.isfinite(frac), np.clip(frac, 0.0, 1.0), 0.0)
        whole = frac >= 1.0                   # the old value over the whole cycle
        return ua, np.where(whole, ua, ub), np.where(whole, 0.0, frac) * self.ts


@dataclass
class Segment:
    """Samples [start, stop) of recording ``rec``: simulated from their own initial state."""

    rec: int
    start: int
    stop: int

    @property
    def n(self) -> int:
        return self.stop - self.start


def _runs(rec: Recording) -> List[Tuple[int, int]]:
    """Return the maximal runs [a, b) of samples joined by cycles of known inputs.

    A sample needs w and c_e; the cycle from k to k+1 also the mean c_e over it.
    """
    good = np.isfinite(rec.w) & np.isfinite(rec.u_now)
    link = good[:-1] & good[1:] & np.isfinite(rec.u_mean[1:])
    runs = []
    k = 0
    while k < rec.n:
        if not good[k]:
            k += 1
            continue
        a = k
        while k < rec.n - 1 and link[k]:
            k += 1
        k += 1
        if k - a >= 2:
            runs.append((a, k))
    return runs


def make_segments(recs: Sequence[Recording], length: int, min_length: int = 10
                  ) -> List[Segment]:
    """Cut each recording's runs of known inputs into segments of ``length`` samples.

    A shorter last piece is kept when it has ``min_length`` samples, else joined to the
    segment before it.
    """
    out: List[Segment] = []
    for i, rec in enumerate(recs):
        for a, b in _runs(rec):
            starts = list(range(a, b, length))
            bounds = [(s, min(s + length, b)) for s in starts]
            if len(bounds) > 1 and bounds[-1][1] - bounds[-1][0] < min_length:
                last = bounds.pop()
                bounds[-1] = (bounds[-1][0], last[1])
            out += [Segment(i, s, e) for s, e in bounds if e - s >= min_length]
    return out


# ----------------------------------------------------------------------------- the model
class ParametricModel:
    """The shared model with its parameters as inputs, and its sensitivities.

    ``step``: (x, S, p, u_a, u_b, τ, w0, w1) -> (x⁺, S⁺), S = ∂x/∂(x_0, p) (6 × (6 + n_p)),
    one cycle Ts with u_a on [0, τ) and u_b on [τ, Ts), RK4 with ``substeps`` sub-steps
    over each piece;
    ``output``: (x, S, p, u, w) -> (y, ∂y/∂(x_0, p)) for ``channels``.
    The functions do not depend on parameter values, so they are built (and compiled)
    once per structure.
    """

    def __init__(self, structure: QuarterCarModel, channels: Sequence[str], ts: float,
                 substeps: int):
        self.channels = tuple(channels)
        self.ts = float(ts)
        self.substeps = int(substeps)
        npar = len(PARAMETERS)
        self.npar = npar
        p = ca.SX.sym('p', npar)
        # The model's own equations with its parameters as symbols.
        sym = structure.symbolic_with(ERVAParams(**{k: p[i] for i, k in enumerate(PARAMETERS)}))
        ode = ca.Function('ode', [sym.x, sym.u, sym.w, p], [sym.xdot])
        x, u, w = sym.x, sym.u, sym.w
        outputs = {'sprung_accel': sym.xdot[1], 'deflection': sym.deflection,
                   'generator_speed': sym.measurements[2]}
        outputs.update({name: x[i] for i, name in enumerate(
            ('z_s', 'zdot_s', 'z_us', 'zdot_us', 'z_d', 'zdot_d'))})
        y = ca.vertcat(*[outputs[c] for c in self.channels])
        nz = NX + npar
        s = ca.SX.sym('S', NX, nz)
        dy = ca.jacobian(y, x) @ s + ca.horzcat(ca.SX.zeros(len(self.channels), NX),
                                                ca.jacobian(y, p))
        self.output = ca.Function('ident_output', [x, s, p, u, w], [y, dy],
                                  ['x', 'S', 'p', 'u', 'w'], ['y', 'dy'])
        # The step with its sensitivities (forward variational equations through RK4,
        # exactly the derivative of the discrete step).
        xs = ca.SX.sym('x', NX)
        ss = ca.SX.sym('S', NX, nz)
        ua, ub, tau, w0, w1 = (ca.SX.sym(n) for n in ('ua', 'ub', 'tau', 'w0', 'w1'))
        z_sym = ca.SX.sym('z', NX + NX * nz)
        uz, wz = ca.SX.sym('u'), ca.SX.sym('w')
        xz = z_sym[:NX]
        sz = ca.reshape(z_sym[NX:], NX, nz)
        f = ode(xz, uz, wz, p)
        fs = ca.jacobian(f, xz) @ sz + ca.horzcat(ca.SX.zeros(NX, NX), ca.jacobian(f, p))
        aug = ca.Function('aug', [z_sym, uz, wz, p], [ca.vertcat(f, ca.vec(fs))])
        wm = w0 + (w1 - w0) * tau / self.ts
        z0 = ca.vertcat(xs, ca.vec(ss))
        na = self.substeps
        za = rk4(lambda z, wv: aug(z, ua, wv, p), z0, w0, wm, tau / na, na)
        zb = rk4(lambda z, wv: aug(z, ub, wv, p), za, wm, w1, (self.ts - tau) / self.substeps,
                 self.substeps)
        self.step = ca.Function('ident_step', [xs, ss, p, ua, ub, tau, w0, w1],
                                [zb[:NX], ca.reshape(zb[NX:], NX, nz)],
                                ['x', 'S', 'p', 'ua', 'ub', 'tau', 'w0', 'w1'],
                                ['x_next', 'S_next'])
        # The same step without sensitivities, for simulating only (3x cheaper).
        x_sim = rk4(lambda z, wv: ode(z, ua, wv, p), xs, w0, wm, tau / na, na)
        x_sim = rk4(lambda z, wv: ode(z, ub, wv, p), x_sim, wm, w1,
                    (self.ts - tau) / self.substeps, self.substeps)
        self.plain_step = ca.Function('ident_plain_step', [xs, p, ua, ub, tau, w0, w1], [x_sim])
        self.plain_output = ca.Function('ident_plain_output', [x, p, u, w], [y])
        self._segment_fns: Dict[Tuple[int, bool], ca.Function] = {}

    def segment_function(self, n: int, sensitivities: bool = True) -> ca.Function:
        """(x0, p, inputs 5 × (n−1), at-sample inputs 2 × n) -> Y m × n (and dY).

        With ``sensitivities`` also dY: (m·n) × (6 + n_p), rows sample-major.
        """
        key = (n, sensitivities)
        fn = self._segment_fns.get(key)
        if fn is not None:
            return fn
        nz = NX + self.npar
        x0 = ca.MX.sym('x0', NX)
        p = ca.MX.sym('p', self.npar)
        cyc = ca.MX.sym('cycles', 5, max(n - 1, 1))
        at = ca.MX.sym('at', 2, n)
        z0 = x0
        if sensitivities:
            z0 = ca.vertcat(x0, ca.vec(ca.horzcat(ca.MX.eye(NX), ca.MX.zeros(NX, self.npar))))
        zs = z0
        if n > 1:
            z = ca.MX.sym('z', z0.shape[0])
            inp = ca.MX.sym('inp', 5)
            pp = ca.MX.sym('pp', self.npar)
            if sensitivities:
                xn, sn = self.step(z[:NX], ca.reshape(z[NX:], NX, nz), pp, *ca.vertsplit(inp))
                zn = ca.vertcat(xn, ca.vec(sn))
            else:
                zn = self.plain_step(z, pp, *ca.vertsplit(inp))
            one = ca.Function('one', [z, inp, pp], [zn])
            acc = one.mapaccum('acc', n - 1, [0], [0])
            zs = ca.horzcat(z0, acc(z0, cyc[:, :n - 1], ca.repmat(p, 1, n - 1)))
        if sensitivities:
            outs = [self.output(zs[:NX, k], ca.reshape(zs[NX:, k], NX, nz), p, at[0, k],
                                at[1, k]) for k in range(n)]
            res = [ca.horzcat(*[o[0] for o in outs]), ca.vertcat(*[o[1] for o in outs])]
        else:
            out = self.plain_output.map(n)
            res = [out(zs, ca.repmat(p, 1, n), at[0, :], at[1, :])]
        fn = ca.Function(f'ident_segment_{n}_{int(sensitivities)}', [x0, p, cyc, at], res)
        self._segment_fns[key] = fn
        return fn


_MODELS: Dict[Tuple, ParametricModel] = {}


def parametric_model(structure: QuarterCarModel, channels: Sequence[str], ts: float,
                     substeps: int) -> ParametricModel:
    """Return the shared :class:`ParametricModel` of this structure (built once)."""
    key = (structure.kind, tuple(channels), float(ts), int(substeps))
    if key not in _MODELS:
        _MODELS[key] = ParametricModel(structure, channels, ts, substeps)
    return _MODELS[key]


def default_substeps(ts: float) -> int:
    """Return RK4 sub-steps per piece of a cycle: h ≤ 2.5 ms.

    With c_e switching between 0 and 20 kNs/m every cycle that is accurate to 4e-4 m/s²
    RMS on z̈_s against the plant's 0.5 ms (docs/model.md, identification).
    """
    return max(2, int(math.ceil(ts / 2.5e-3 - 1e-9)))


# ----------------------------------------------------------------------------- the data
@dataclass
class _SegData:
    """One segment's inputs and measurements, ready for its CasADi function."""

    seg: Segment
    cycles: np.ndarray      # 5 × (n−1): u_a, u_b, τ, w0, w1
    at: np.ndarray          # 2 × n: u_now, w
    y: np.ndarray           # n × m
    mask: np.ndarray        # n × m bool: measured


def _seg_data(recs: Sequence[Recording], segs: Sequence[Segment]) -> List[_SegData]:
    out = []
    for s in segs:
        rec = recs[s.rec]
        part = rec.part(s.start, s.stop)
        ua, ub, tau = part.switches()
        cycles = np.vstack([ua, ub, tau, part.w[:-1], part.w[1:]])
        if cycles.shape[1] == 0:
            cycles = np.zeros((5, 1))
        at = np.vstack([part.u_now, part.w])
        mask = np.isfinite(part.y)
        out.append(_SegData(s, cycles, at, np.where(mask, part.y, 0.0), mask))
    return out


# ----------------------------------------------------------------------------- results
@dataclass
class ParameterResult:
    """One parameter: prior, estimate, interval and why it is free or fixed."""

    name: str
    prior: float
    value: float
    free: bool
    rel_std: Optional[float] = None          # sd of log(value): ~ relative sd
    ci95: Optional[Tuple[float, float]] = None
    reason: str = ''                          # why fixed
    by_channel: Dict[str, Optional[float]] = field(default_factory=dict)  # rel sd, alone
    truth: Optional[float] = None             # for studies on simulated plants
    rel_std_data: Optional[float] = None      # from the data alone (fixed ones exact)


@dataclass
class FitResult:
    """What ``identify`` found: the parameters, the fit's quality, the data used."""

    params: ERVAParams
    prior: ERVAParams
    parameters: List[ParameterResult]
    channels: Tuple[str, ...]
    sigma: Dict[str, float]                   # residual RMS per channel (the weights)
    fit_pct: Dict[str, float]                 # on the fitted data
    heldout_fit_pct: Dict[str, float]         # identified model, on held-out data
    heldout_prior_fit_pct: Dict[str, float]   # prior model, on held-out data
    residual_lag1: Dict[str, float]           # lag-1 autocorrelation of the residuals
    iterations: int
    segments: int
    fit_samples: int
    heldout_samples: int
    condition: float                          # of the free parameters' information
    substeps: int
    notes: List[str] = field(default_factory=list)

    def free(self) -> List[str]:
        return [p.name for p in self.parameters if p.free]

    def fixed(self) -> List[str]:
        return [p.name for p in self.parameters if not p.free]


# ----------------------------------------------------------------------------- the fit
class _Problem:
    """Segments, weights and the current unknowns of one fit."""

    def __init__(self, model: ParametricModel, data: List[_SegData], sigma: np.ndarray):
        self.model = model
        self.data = data
        self.sigma = np.asarray(sigma, dtype=float)
        self._last = None       # (key, raw evaluation): one simulation serves many uses

    def raw(self, p: np.ndarray, x0s: np.ndarray):
        """Return per segment (ŷ n × m, ∂ŷ/∂(x0, p) n × m × (6 + n_p)), unweighted."""
        key = (p.tobytes(), np.asarray(x0s).tobytes())
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        m = len(self.model.channels)
        out = []
        for d, x0 in zip(self.data, x0s):
            y, dy = self.model.segment_function(d.seg.n)(x0, p, d.cycles, d.at)
            out.append((np.asarray(y).T, np.asarray(dy).reshape(d.seg.n, m, -1)))
        self._last = (key, out)
        return out

    def evaluate(self, p: np.ndarray, x0s: np.ndarray, channel: Optional[int] = None):
        """Return per segment (weighted residual e, ∂e/∂x0, ∂e/∂p) on the measured rows.

        ``channel``: that output channel's rows only.
        """
        out = []
        for d, (y, dy) in zip(self.data, self.raw(p, x0s)):
            e = (y - d.y) / self.sigma
            j = dy / self.sigma[None, :, None]
            mk = d.mask
            if channel is not None:
                e, j, mk = e[:, [channel]], j[:, [channel]], mk[:, [channel]]
            out.append((e[mk], j[mk][:, :NX], j[mk][:, NX:]))
        return out

    def simulated(self, p: np.ndarray, x0s: np.ndarray) -> List[np.ndarray]:
        """Return per segment the simulated outputs ŷ (n × m)."""
        return [np.asarray(self.model.segment_function(d.seg.n, False)(
            x0, p, d.cycles, d.at)).T for d, x0 in zip(self.data, x0s)]


def _normal(blocks, cols: Sequence[int], scale: np.ndarray):
    """Return per-segment blocks and the accumulated parameter blocks of JᵀJ and Jᵀe.

    ``cols``: the free parameters' columns of ∂e/∂p; ``scale``: ∂p/∂θ (log-parameters).
    """
    hpp = np.zeros((len(cols), len(cols)))
    gp = np.zeros(len(cols))
    segs = []
    for e, jx, jp in blocks:
        jt = jp[:, cols] * scale
        segs.append((jx.T @ jx, jx.T @ jt, jx.T @ e))
        hpp += jt.T @ jt
        gp += jt.T @ e
    return segs, hpp, gp


def _schur(segs, hpp, gp, mu: float = 0.0):
    """Eliminate the segment states: return (S, r, per-segment solves) of the θ system."""
    s, r = hpp.copy(), gp.copy()
    solves = []
    for hxx, hxp, gx in segs:
        a = hxx + mu * np.diag(np.diag(hxx)) + 1e-12 * np.eye(NX) * (np.trace(hxx) + 1e-30)
        try:
            inv_hxp = np.linalg.solve(a, hxp)
            inv_gx = np.linalg.solve(a, gx)
        except np.linalg.LinAlgError:
            pinv = np.linalg.pinv(a)
            inv_hxp, inv_gx = pinv @ hxp, pinv @ gx
        s -= hxp.T @ inv_hxp
        r -= hxp.T @ inv_gx
        solves.append((inv_hxp, inv_gx))
    return s, r, solves


def _information(problem: _Problem, p: np.ndarray, x0s: np.ndarray, cols: Sequence[int],
                 scale: np.ndarray, channel: Optional[int] = None) -> np.ndarray:
    """Return the Fisher information of the log-parameters ``cols`` (states eliminated).

    ``channel`` restricts the data to one output channel (pseudo-inverse for states
    that channel alone does not determine).
    """
    segs, hpp, _ = _normal(problem.evaluate(p, x0s, channel), cols, scale)
    f = hpp.copy()
    for hxx, hxp, _ in segs:
        f -= hxp.T @ np.linalg.pinv(hxx, rcond=1e-10) @ hxp
    return 0.5 * (f + f.T)


def _covariance(f: np.ndarray) -> np.ndarray:
    """Return F⁻¹ by eigen-decomposition, an undetermined direction given variance ~1e8.

    (Through the eigenvalues, clipped at 0, so no diagonal element comes out negative
    by round-off, as a plain inverse of a matrix with condition 1e16 can.)
    """
    lam, vec = np.linalg.eigh(0.5 * (f + f.T))
    return (vec / (np.maximum(lam, 0.0) + 1e-8)) @ vec.T


def _rel_std(f: np.ndarray) -> np.ndarray:
    """Return sqrt(diag(F⁻¹)): ~1e4 for a direction the data do not determine."""
    if f.size == 0:
        return np.zeros(0)
    return np.sqrt(np.diag(_covariance(f)))


def _correlations(f: np.ndarray) -> np.ndarray:
    cov = _covariance(f)
    d = np.sqrt(np.diag(cov))
    return cov / np.outer(d, d)


def _fit_states(problem: _Problem, p: np.ndarray, x0s: np.ndarray, iterations: int = 3
                ) -> np.ndarray:
    """Return the segments' initial states fitted with the parameters held (Gauss-Newton)."""
    x0s = x0s.copy()
    for _ in range(iterations):
        for i, (e, jx, _) in enumerate(problem.evaluate(p, x0s)):
            if e.size:
                step, *_ = np.linalg.lstsq(jx, -e, rcond=None)
                x0s[i] += step
    return x0s


def _lm(problem: _Problem, p: np.ndarray, x0s: np.ndarray, free: Sequence[int],
        max_iter: int = 40, tol: float = 1e-10
        ) -> Tuple[np.ndarray, np.ndarray, int, bool]:
    """Levenberg-Marquardt on (log-parameters ``free``, segment states).

    Returns (p, x0s, iterations, converged): converged when a step gains less than
    ``tol`` of the cost, or no damping finds a gain (a minimum), before ``max_iter``.
    """
    cols = list(free)
    blocks = problem.evaluate(p, x0s)
    cost = sum(float(e @ e) for e, _, _ in blocks)
    mu = 1e-3
    it = 0
    for it in range(1, max_iter + 1):
        segs, hpp, gp = _normal(blocks, cols, p[cols])
        gain = None
        for _ in range(12):
            s, r, solves = _schur(segs, hpp + mu * np.diag(np.diag(hpp) + 1e-12), gp, mu)
            try:
                dtheta = -np.linalg.solve(s, r)
            except np.linalg.LinAlgError:
                dtheta = -np.linalg.lstsq(s, r, rcond=None)[0]
            dtheta = np.clip(dtheta, -0.5, 0.5)      # a factor e^0.5 at most per step
            new_x0s = np.array([x0 - inv_gx - inv_hxp @ dtheta
                                for x0, (inv_hxp, inv_gx) in zip(x0s, solves)])
            new_p = p.copy()
            new_p[cols] = p[cols] * np.exp(dtheta)
            new_blocks = problem.evaluate(new_p, new_x0s)
            new_cost = sum(float(e @ e) for e, _, _ in new_blocks)
            if np.isfinite(new_cost) and new_cost < cost:
                gain = (cost - new_cost) / max(cost, 1e-300)
                p, x0s, blocks, cost = new_p, new_x0s, new_blocks, new_cost
                mu = max(mu / 3, 1e-9)
                break
            mu *= 10
        if gain is None or gain < tol:
            return p, x0s, it, True
    return p, x0s, it, False


def _prior_vector(prior: ERVAParams) -> np.ndarray:
    return np.array([getattr(prior, k) for k in PARAMETERS], dtype=float)


def _nrmse_fit(y: np.ndarray, yhat: np.ndarray, mask: np.ndarray) -> float:
    yy, hh = y[mask], yhat[mask]
    if yy.size < 2:
        return float('nan')
    den = np.linalg.norm(yy - yy.mean())
    return float(100 * (1 - np.linalg.norm(yy - hh) / den)) if den > 0 else float('nan')


def fit_per_channel(problem: _Problem, p: np.ndarray, x0s: np.ndarray) -> Dict[str, float]:
    """Return the normalised RMS fit (%) per channel over all segments of ``problem``."""
    sims = problem.simulated(p, x0s)
    out = {}
    for c, name in enumerate(problem.model.channels):
        y = np.concatenate([d.y[:, c] for d in problem.data])
        yh = np.concatenate([s[:, c] for s in sims])
        mk = np.concatenate([d.mask[:, c] for d in problem.data])
        out[name] = _nrmse_fit(y, yh, mk)
    return out


def _lag1(problem: _Problem, p, x0s) -> Dict[str, float]:
    sims = problem.simulated(p, x0s)
    out = {}
    for c, name in enumerate(problem.model.channels):
        num = den = 0.0
        for d, s in zip(problem.data, sims):
            r = np.where(d.mask[:, c], s[:, c] - d.y[:, c], np.nan)
            r = r - np.nanmean(r) if np.isfinite(r).any() else r
            a, b = r[:-1], r[1:]
            ok = np.isfinite(a) & np.isfinite(b)
            num += float(np.sum(a[ok] * b[ok]))
            den += float(np.nansum(r ** 2))
        out[name] = num / den if den > 0 else float('nan')
    return out


def _sigma_rms(problem: _Problem, p, x0s) -> np.ndarray:
    sims = problem.simulated(p, x0s)
    out = []
    for c in range(len(problem.model.channels)):
        r = np.concatenate([(s[:, c] - d.y[:, c])[d.mask[:, c]]
                            for d, s in zip(problem.data, sims)])
        out.append(float(np.sqrt(np.mean(r ** 2))) if r.size else 1.0)
    return np.maximum(np.asarray(out), 1e-12)


def check_data(recs: Sequence[Recording], min_fit_s: float = MIN_FIT_S) -> None:
    """Raise :class:`IdentifyError` (one line) when the data cannot identify anything."""
    if not recs:
        raise IdentifyError('no data to fit')
    ts = recs[0].ts
    usable = sum(b - a for r in recs for a, b in _runs(r)) * ts
    if usable < min_fit_s:
        raise IdentifyError(f'too short: {usable:.2f} s of samples with known road and '
                            f'damping to fit, at least {min_fit_s:g} s needed')
    u = np.concatenate([r.u_now for r in recs])
    u = u[np.isfinite(u)]
    spread = float(np.ptp(u)) if u.size else 0.0
    if spread <= max(100.0, 0.02 * float(np.mean(np.abs(u)))):
        raise IdentifyError(
            f'no excitation: the damping c_e stays at {np.mean(u):.0f} Ns/m '
            f'(range {spread:.0f} Ns/m), so the generator force cannot be told from the '
            f'masses and springs; record with the excite controller (controller: excite)')
    w = np.concatenate([r.w for r in recs])
    w = w[np.isfinite(w)]
    if w.size == 0 or float(np.ptp(w)) == 0.0:
        raise IdentifyError('the road height never changes: nothing moves the suspension')
    for r in recs:
        for c, name in enumerate(r.channels):
            if not np.isfinite(r.y[:, c]).any():
                raise IdentifyError(f'{r.name}: channel {name} has no measured sample')


def identify(recs: Sequence[Recording], prior_model: QuarterCarModel, *,
             heldout: Sequence[Recording] = (), sigma0: Optional[Dict[str, float]] = None,
             segment_s: float = 1.0, substeps: Optional[int] = None,
             max_rel_std: float = MAX_REL_STD, prior_rel_std: float = PRIOR_REL_STD,
             fix: Sequence[str] = (),
             estimate: Optional[Sequence[str]] = None, max_iter: int = 40,
             truth: Optional[ERVAParams] = None, progress=None) -> FitResult:
    """Identify ``prior_model``'s parameters from ``recs`` (module doc); hold out ``heldout``.

    ``prior_model``: the model identified, its parameters the prior.

    ``fix`` keeps parameters at the prior (known: e.g. a weighed mass); ``estimate`` names
    the only parameters to fit (no automatic fixing: an undetermined one is an
    :class:`IdentifyError` naming it).  The intervals include the spread
    ``prior_rel_std`` of the parameters fixed because the data do not determine them.
    ``sigma0`` gives the channels' noise std for the first fit (default: 1 % of each
    channel's RMS).  ``truth`` (a simulated plant) is only reported next to the result.
    """
    say = progress or (lambda text: None)
    if prior_model.nx != NX:
        raise IdentifyError(f'identification fits the ERVA model\'s {NX} states; the '
                            f'{prior_model.kind} model has {prior_model.nx}')
    prior = prior_model.params
    check_data(recs)
    channels = recs[0].channels
    ts = recs[0].ts
    for r in list(recs) + list(heldout):
        if r.channels != channels or abs(r.ts - ts) > 1e-12:
            raise IdentifyError(f'{r.name}: other channels or sample time than {recs[0].name}')
    for key in list(fix) + list(estimate or []):
        if key not in ERVA_SPECS:
            raise IdentifyError(f'unknown parameter {key!r}; known: {", ".join(ERVA_SPECS)}')
    substeps = substeps or default_substeps(ts)
    model = parametric_model(prior_model, channels, ts, substeps)
    length = max(2, int(round(segment_s / ts)))
    segs = make_segments(recs, length)
    if not segs:
        raise IdentifyError('too short: no segment of known road and damping')
    data = _seg_data(recs, segs)
    if sigma0:
        sigma = np.array([sigma0[c] for c in channels], dtype=float)
    else:
        ally = np.vstack([d.y for d in data])
        allm = np.vstack([d.mask for d in data])
        sigma = np.array([0.01 * math.sqrt(np.mean(ally[allm[:, c], c] ** 2)) or 1.0
                          for c in range(len(channels))])
    problem = _Problem(model, data, sigma)
    p_prior = _prior_vector(prior)
    p = p_prior.copy()
    x0s = _fit_states(problem, p, np.zeros((len(segs), NX)))
    say(f'{len(segs)} segments, {sum(d.mask.any(axis=1).sum() for d in data)} samples')

    fixed: Dict[str, str] = {k: NOT_IN_MODEL[k] for k in NOT_IN_MODEL}
    for k in fix:
        fixed.setdefault(k, 'fixed by the user (--fix)')
    if estimate is not None:
        for k in PARAMETERS:
            if k not in estimate:
                fixed.setdefault(k, 'not asked for (--estimate)')
    free = [k for k in PARAMETERS if k not in fixed]

    def select(p, x0s, free):
        """Fix the worst-determined parameter until all free ones are determined."""
        free = list(free)
        while free:
            cols = [PARAMETERS.index(k) for k in free]
            f = _information(problem, p, x0s, cols, p[cols])
            sd = _rel_std(f)
            worst = int(np.argmax(sd))
            if sd[worst] <= max_rel_std:
                return free, f
            if estimate is not None:
                raise IdentifyError(
                    'cannot determine ' + ', '.join(
                        f'{k} (relative sd {100 * s:.0f} %)' for k, s in zip(free, sd)
                        if s > max_rel_std)
                    + f' from these data (limit {100 * max_rel_std:g} %); fix them '
                      '(--fix) or record a longer or better excited session')
            corr = _correlations(f)[worst]
            corr[worst] = 0.0
            j = int(np.argmax(np.abs(corr)))
            why = (f'{UNDETERMINED}: relative sd {100 * sd[worst]:.0f} % '
                   f'> {100 * max_rel_std:g} %')
            if len(free) > 1 and abs(corr[j]) > 0.5:
                why += f' (correlation {corr[j]:+.2f} with {free[j]})'
            fixed[free[worst]] = why
            free.pop(worst)
        return free, np.zeros((0, 0))

    free, _ = select(p, x0s, free)
    if not free:
        raise IdentifyError('the data determine none of the parameters: '
                            + '; '.join(f'{k}: {v}' for k, v in fixed.items()))
    say('free: ' + ', '.join(free))
    total_it = 0
    for _round in range(4):
        cols = [PARAMETERS.index(k) for k in free]
        p, x0s, it, _ = _lm(problem, p, x0s, cols, max_iter)
        total_it += it
        # Weights from the residuals of this fit, then refit once with them.
        problem.sigma = _sigma_rms(problem, p, x0s)
        p, x0s, it, converged = _lm(problem, p, x0s, cols, max_iter)
        total_it += it
        new_free, f = select(p, x0s, free)
        if new_free == free:
            break
        free = new_free
        say('refit without ' + ', '.join(k for k in PARAMETERS if k not in free
                                         and k not in NOT_IN_MODEL))
    # The fixed parameters the data could not determine are not known either: their
    # prior's spread moves the estimates (m_d takes up m_r's error).  Linearised,
    # θ̂_f − θ_f = noise + G·(θ_u,prior − θ_u), G = −F_ff⁻¹·F_fu, so
    # Cov = F_ff⁻¹ + G·Σ_u·Gᵀ with Σ_u = prior_rel_std²·I (log-parameters).
    undetermined = [k for k, why in fixed.items() if why.startswith(UNDETERMINED)]
    cols = [PARAMETERS.index(k) for k in free]
    both = cols + [PARAMETERS.index(k) for k in undetermined]
    f_all = _information(problem, p, x0s, both, p[both])
    nf = len(cols)
    f = f_all[:nf, :nf]
    cov_data = _covariance(f)
    gain = -cov_data @ f_all[:nf, nf:]
    cov = cov_data + prior_rel_std ** 2 * gain @ gain.T
    sd = np.sqrt(np.diag(cov))
    sd_data = np.sqrt(np.diag(cov_data))
    eig = np.linalg.eigvalsh(f)
    condition = float(eig[-1] / max(eig[0], 1e-300))
    by_channel = {}
    for c, name in enumerate(channels):
        fc = _information(problem, p, x0s, cols, p[cols], channel=c)
        by_channel[name] = _rel_std(fc)
    fitted = dict(zip(PARAMETERS, p))
    values = dict(prior.as_dict(), **{k: float(fitted[k]) for k in free})
    try:
        params = validate_erva(values, source='identified')
    except Exception as exc:   # out of the physical envelope: the data say nonsense
        raise IdentifyError(f'the fit left the physical range: {exc}') from None
    results = []
    for k in ERVA_SPECS:
        t = getattr(truth, k) if truth is not None else None
        if k in free:
            i = free.index(k)
            v = values[k]
            bc = {name: (None if by_channel[name][i] > 10 else float(by_channel[name][i]))
                  for name in channels}
            results.append(ParameterResult(k, getattr(prior, k), v, True, float(sd[i]),
                                           (v * math.exp(-Z95 * sd[i]),
                                            v * math.exp(Z95 * sd[i])), '', bc, t,
                                           float(sd_data[i])))
        else:
            results.append(ParameterResult(k, getattr(prior, k), getattr(prior, k), False,
                                           reason=fixed[k], truth=t))
    fit_pct = fit_per_channel(problem, p, x0s)
    lag1 = _lag1(problem, p, x0s)
    sigma = dict(zip(channels, map(float, problem.sigma)))
    held, held_prior, held_n = {}, {}, 0
    if heldout:
        held_segs = make_segments(heldout, 10 ** 9)
        if held_segs:
            hp = _Problem(model, _seg_data(heldout, held_segs), problem.sigma)
            held_n = int(sum(d.mask.any(axis=1).sum() for d in hp.data))
            for vec, dest in ((p, held), (p_prior, held_prior)):
                xs = _fit_states(hp, vec, np.zeros((len(held_segs), NX)), 4)
                dest.update(fit_per_channel(hp, vec, xs))
    notes = []
    if not converged:
        notes.append(f'the fit stopped after {max_iter} iterations without converging: the '
                     f'numbers may not be a minimum')
    correlated = [c for c, v in lag1.items() if abs(v) > 0.5]
    if correlated:
        notes.append(f'the residuals of {", ".join(correlated)} are correlated (lag-1 '
                     f'autocorrelation > 0.5): model error, not white noise, dominates them, '
                     f'and the intervals are too narrow')
    return FitResult(params, prior, results, channels, sigma, fit_pct, held, held_prior, lag1,
                     total_it, len(segs), int(sum(d.mask.any(axis=1).sum() for d in data)),
                     held_n, condition, substeps, notes)


__all__ = ['PARAMETERS', 'NOT_IN_MODEL', 'UNITS', 'ECU_CHANNELS', 'STATE_CHANNELS',
           'MIN_FIT_S', 'MAX_REL_STD', 'PRIOR_REL_STD', 'UNDETERMINED', 'IdentifyError',
           'Recording', 'Segment',
           'make_segments', 'ParametricModel', 'parametric_model', 'default_substeps',
           'ParameterResult', 'FitResult', 'check_data', 'identify', 'fit_per_channel']
