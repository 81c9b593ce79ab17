"""State estimator (EKF) of the ERVA quarter car from the ECU's sensors on the shared model.

The vehicle measures, at every ECU cycle t_k (Ts = 0.02 s):

=====  ==========================================  =======================================
y      measurement                                 h(x, u, w) (core/model/quarter_car.py)
=====  ==========================================  =======================================
y_1    sprung-mass acceleration z̈_s (m/s²)         ``sprung_accel(x, u, w)`` = ẋ_2, eq. (11)
y_2    suspension deflection z_s − z_us (m)        x_1 − x_3
y_3    generator speed φ̇ = v_gen / l (rad/s)       ``generator_velocity(x)`` / l, eq. (10)
=====  ==========================================  =======================================

and it knows two inputs: the damping c_e the ECU applied (its status frame: the
cycle-mean c_e for the prediction, the current c_e for y_1) and the road height at the
tyre w (``/erva/road/height``: the road model in simulation, the preview sensor's
estimate on a vehicle).  Absolute positions z_s, z_us, z_d are observable only through
the dynamics with w known; the modes are damped, so the filter is detectable and
converges from a wrong initial state (tested).

Model.  x_{k+1} = F_d(x_k, u_k, w_k, w_{k+1}) is ``QuarterCarModel.rk4_step`` (paper
eq. (11), the only copy of the equations) with enough RK4 sub-steps to be stable up to
the hardware's largest c_e (the dynamics are stiff, docs/model.md); its Jacobian
A = ∂F_d/∂x and the output Jacobian H = ∂h/∂x are CasADi's exact derivatives of the
same expressions, evaluated in one call each.

Noise (:class:`EstimatorNoise`, all standard deviations in SI units):

* process: unmodelled accelerations of the sprung mass, the unsprung mass and the
  rotor (``q_accel_s``, ``q_accel_us``, ``q_accel_d``, m/s²), each a piecewise-constant
  white acceleration over a sample (discrete white-noise-acceleration model:
  Q = σ²·[[Ts⁴/4, Ts³/2], [Ts³/2, Ts²]] per position/velocity pair).  The unsprung
  value also absorbs road-height error (0.3 mm at the tyre is k_t·0.3 mm / M_us ≈ 1.3 m/s²);
* measurement: ``r_sprung_accel``, ``r_deflection``, ``r_speed`` — the sensors' noise
  plus the DBC's quantisation.  Defaults match the simulated ECU's sensors
  (:class:`erva_ros.core.hil.ecu_sim.SensorNoise`).

A missing measurement (a dropped CAN frame) is a NaN in y: only the present rows are
used.  The update is the Joseph form, so P stays symmetric positive semi-definite.
Because the measurement noises are independent (R diagonal), the rows can also be
applied one by one as they arrive (:meth:`ExtendedKalmanFilter.correct`), with the
same result as the batch :meth:`ExtendedKalmanFilter.update`.
"""

from dataclasses import asdict, dataclass
from typing import Dict, Optional, Tuple

import casadi as ca
import numpy as np

from erva_ros.core.model.codegen import BufferedCall, compile_for
from erva_ros.core.model.quarter_car import QuarterCarModel, rk4_stable_substeps
from erva_ros.core.settings.files import shipped_checked
from erva_ros.core.settings.hil import NOISE_SPECS

#: Measurement names, in the order of y.
MEASUREMENTS = ('sprung_accel', 'deflection', 'generator_speed')

#: Default noise: the state_estimator_node section of the shipped config/hil.yaml.
_DEFAULT_NOISE = shipped_checked(NOISE_SPECS, 'hil.yaml', 'state_estimator_node')


@dataclass(frozen=True)
class EstimatorNoise:
    """Standard deviations of the EKF's noise model (see the module docstring)."""

    q_accel_s: float = _DEFAULT_NOISE['q_accel_s']
    q_accel_us: float = _DEFAULT_NOISE['q_accel_us']
    q_accel_d: float = _DEFAULT_NOISE['q_accel_d']
    r_sprung_accel: float = _DEFAULT_NOISE['r_sprung_accel']
    r_deflection: float = _DEFAULT_NOISE['r_deflection']
    r_speed: float = _DEFAULT_NOISE['r_speed']
    p0_position: float = _DEFAULT_NOISE['p0_position']
    p0_velocity: float = _DEFAULT_NOISE['p0_velocity']

    def as_dict(self) -> Dict[str, float]:
        return asdict(self)


@dataclass
class UpdateResult:
    """Innovation of one measurement update."""

    innovation: np.ndarray    # y − h(x⁻), rows that were measured
    nis: float                # normalised innovation squared νᵀS⁻¹ν (χ² with len(ν) dof)
    used: np.ndarray          # bool mask of the rows used


class ExtendedKalmanFilter:
    """Discrete EKF on ``QuarterCarModel.rk4_step`` (paper eq. (11)) with the ECU's sensors."""

    def __init__(self, model: QuarterCarModel, ts: float = 0.02,
                 noise: EstimatorNoise = EstimatorNoise(), u_max: float = 22800.0,
                 substeps: Optional[int] = None, codegen: str = 'auto'):
        self.model = model
        self.params = model.params
        self.ts = float(ts)
        self.noise = noise
        nx = self.model.nx
        self.nx = nx
        # Stable over the whole input box (stiff at high c_e, docs/model.md).
        self.substeps = substeps or rk4_stable_substeps(self.model, self.ts, max(u_max, 1.0))
        # rk4_step as a loop: its Jacobian compiles in seconds, not a minute (model.py).
        step = self.model.rk4_loop(self.ts, self.substeps)
        x, u = ca.MX.sym('x', nx), ca.MX.sym('u')
        w0, w1 = ca.MX.sym('w0'), ca.MX.sym('w1')
        xn = step(x, u, w0, w1)
        a = ca.densify(ca.jacobian(xn, x))
        self._pred = ca.Function('ekf_predict', [x, u, w0, w1], [xn, a],
                                 ['x', 'u', 'w0', 'w1'], ['xn', 'A'])
        xs, us, ws = ca.SX.sym('x', nx), ca.SX.sym('u'), ca.SX.sym('w')
        y = self.model.measurements(xs, us, ws)
        self._meas = ca.Function('ekf_measure', [xs, us, ws], [y, ca.jacobian(y, xs)],
                                 ['x', 'u', 'w'], ['y', 'H'])
        self._cycle = self._cycle_function(x, xn, a, u, w0, w1)
        # As the NMPC: C when a compiler is there (2x faster).
        self._pred, self._meas, self._cycle = compile_for(
            codegen, (self._pred, self._meas, self._cycle), 'the EKF')
        # The node's per-cycle call through fixed buffers: 0.02 ms instead of 0.14 ms
        # (erva_ros/core/model/codegen.py BufferedCall).
        self._cycle = BufferedCall(self._cycle)
        self.Q = self._process_noise()
        self.R = np.diag([noise.r_sprung_accel, noise.r_deflection, noise.r_speed]) ** 2
        self._r = np.diag(self.R).copy()
        self.reset()

    def _cycle_function(self, x, xn, a, u_mean, w0, w1) -> ca.Function:
        """Return predict + update of one ECU cycle as one CasADi function (see :meth:`cycle`).

        The rows are applied one by one (R diagonal: equal to the batch update), each
        only where its mask is 1, with the output linearised once at the prior.
        """
        nx = self.nx
        # The update in SX (elementwise, as before), called from the MX prediction.
        xn_s, a_s = ca.SX.sym('xn', nx), ca.SX.sym('A', nx, nx)
        p, q = ca.SX.sym('P', nx, nx), ca.SX.sym('Q', nx, nx)
        r, w_s = ca.SX.sym('r', 3), ca.SX.sym('w')
        u_now, y, mask = ca.SX.sym('u_now'), ca.SX.sym('y', 3), ca.SX.sym('mask', 3)
        p1 = a_s @ p @ a_s.T + q
        yh, hh = self._meas(xn_s, u_now, w_s)     # the SX function: inlined
        xk, pk, nis = sequential_update(xn_s, p1, yh, hh, y, mask, r)
        update = ca.Function('ekf_update', [xn_s, a_s, p, q, r, u_now, w_s, y, mask],
                             [xk, pk, nis])
        pm, qm, rm = ca.MX.sym('P', nx, nx), ca.MX.sym('Q', nx, nx), ca.MX.sym('r', 3)
        u_now_m, ym, mask_m = ca.MX.sym('u_now'), ca.MX.sym('y', 3), ca.MX.sym('mask', 3)
        return ca.Function('ekf_cycle', [x, pm, qm, rm, u_mean, u_now_m, w0, w1, ym, mask_m],
                           update(xn, a, pm, qm, rm, u_now_m, w1, ym, mask_m),
                           ['x', 'P', 'Q', 'r', 'u_mean', 'u_now', 'w0', 'w1', 'y', 'mask'],
                           ['x_next', 'P_next', 'nis'])

    def cycle(self, y, u_mean: float, u_now: float, w0: float, w1: float
              ) -> Tuple[np.ndarray, float]:
        """Predict over one cycle and update with y (NaN = missing), in one C call.

        Equal to :meth:`predict` (u_mean, w0 → w1) then :meth:`update` (y, u_now, w1);
        returns (x̂, NIS of the rows used).  The node's per-cycle path: a few Python
        operations instead of dozens (each one costs much more cold than in a loop).
        """
        y = np.asarray(y, dtype=float)
        mask = np.isfinite(y)
        x, p, nis = self._cycle(self.x, self.P, self.Q, self._r, u_mean, u_now, w0, w1,
                                np.where(mask, y, 0.0), mask.astype(float))
        self.x = np.asarray(x).ravel()
        self.P = np.asarray(p)
        self.k += 1
        return self.x, float(nis)

    def _process_noise(self) -> np.ndarray:
        return acceleration_noise(self.noise, self.nx, self.ts)

    def reset(self, x0: Optional[np.ndarray] = None) -> None:
        """Restart from ``x0`` (default rest) with the initial covariance P0."""
        self.x = np.zeros(self.nx) if x0 is None else np.array(x0, dtype=float)
        pos, vel = self.noise.p0_position ** 2, self.noise.p0_velocity ** 2
        self.P = np.diag([pos, vel] * (self.nx // 2))
        self.k = 0

    def predict(self, u: float, w0: float, w1: float) -> np.ndarray:
        """Propagate one sample Ts with damping u (Ns/m) and road w0 → w1 (m)."""
        xn, a = self._pred(self.x, u, w0, w1)
        a = np.asarray(a)
        self.x = np.asarray(xn).ravel()
        self.P = a @ self.P @ a.T + self.Q
        self.k += 1
        return self.x

    def predict_output(self, u: float, w: float) -> np.ndarray:
        """Return h(x̂, u, w): the measurements the current estimate predicts."""
        return np.asarray(self._meas(self.x, u, w)[0]).ravel()

    def update(self, y, u: float, w: float) -> UpdateResult:
        """Correct with measurements y (NaN = missing) taken with damping u and road w."""
        y = np.asarray(y, dtype=float).ravel()
        used = np.isfinite(y)
        if not used.any():
            return UpdateResult(np.zeros(0), 0.0, used)
        yh, h = self._meas(self.x, u, w)
        h = np.asarray(h)[used]
        nu = y[used] - np.asarray(yh).ravel()[used]
        r = self.R[np.ix_(used, used)]
        s = h @ self.P @ h.T + r
        k = np.linalg.solve(s, h @ self.P).T
        self.x = self.x + k @ nu
        ikh = np.eye(self.nx) - k @ h
        self.P = ikh @ self.P @ ikh.T + k @ r @ k.T
        return UpdateResult(nu, float(nu @ np.linalg.solve(s, nu)), used)

    def linearize_output(self, u: float, w: float) -> np.ndarray:
        """Fix the output linearisation h(x̂⁻) + H·(x − x̂⁻) for :meth:`correct`; return h(x̂⁻)."""
        yh, h = self._meas(self.x, u, w)
        self._lin = (self.x.copy(), np.asarray(yh).ravel(), np.asarray(h))
        return self._lin[1]

    def correct(self, i: int, y_i: float) -> Tuple[float, float]:
        """Update with measurement row ``i`` alone; return (innovation, its ν²/s).

        With R diagonal, correcting the rows one after the other with the output
        linearised once at the prior (:meth:`linearize_output`) gives exactly the batch
        update -- so a node can use each measurement the moment it arrives.
        """
        x0, yh, hh = self._lin
        h = hh[i]
        r = self.R[i, i]
        nu = float(y_i - (yh[i] + h @ (self.x - x0)))
        ph = self.P @ h
        s = float(h @ ph + r)
        k = ph / s
        self.x = self.x + k * nu
        ikh = np.eye(self.nx) - np.outer(k, h)
        self.P = ikh @ self.P @ ikh.T + r * np.outer(k, k)
        return nu, nu * nu / s

    def step(self, y, u_mean: float, u_now: float, w0: float, w1: float
             ) -> Tuple[np.ndarray, UpdateResult]:
        """Predict over the last cycle (mean damping u_mean, road w0 → w1), then update."""
        self.predict(u_mean, w0, w1)
        return self.x, self.update(y, u_now, w1)

    def std(self) -> np.ndarray:
        """Return the standard deviations of the state estimate (sqrt of diag P)."""
        return np.sqrt(np.maximum(np.diag(self.P), 0.0))


def sequential_update(x, p, yh, hh, y, mask, r):
    """Return symbolic (x⁺, P⁺, NIS): the rows of y applied one by one where mask is 1.

    The output is linearised once at the prior (y ≈ yh + hh·(x − x_prior)); with R
    diagonal (variances ``r``) this equals the batch update.  Joseph form.
    """
    n = x.shape[0]
    xk, pk, nis = x, p, 0
    for i in range(y.shape[0]):
        h = hh[i, :]
        nu = y[i] - (yh[i] + h @ (xk - x))
        ph = pk @ h.T
        s = h @ ph + r[i]
        k = ph / s
        ikh = ca.SX.eye(n) - k @ h
        xk = ca.if_else(mask[i], xk + k * nu, xk)
        pk = ca.if_else(mask[i], ikh @ pk @ ikh.T + r[i] * (k @ k.T), pk)
        nis = nis + mask[i] * nu * nu / s
    return xk, pk, nis


def acceleration_noise(noise: EstimatorNoise, nx: int, ts: float,
                       size: Optional[int] = None) -> np.ndarray:
    """Return Q of the unmodelled accelerations on the first ``nx`` states (module doc).

    One piecewise-constant white acceleration per position/velocity pair over a sample;
    ``size`` (default nx) pads Q with zeros for states of an augmented filter.
    """
    sig = [noise.q_accel_s, noise.q_accel_us, noise.q_accel_d][:nx // 2]
    q = np.zeros((size or nx, size or nx))
    block = np.array([[ts ** 4 / 4, ts ** 3 / 2], [ts ** 3 / 2, ts ** 2]])
    for i, s in enumerate(sig):
        q[2 * i:2 * i + 2, 2 * i:2 * i + 2] = s ** 2 * block
    return q


def validate_noise(values: Dict, source: str = '') -> EstimatorNoise:
    """Validate noise parameters (missing keys keep their defaults); one-line errors."""
    base = EstimatorNoise().as_dict()
    out = {k: spec.check(k, values.get(k, base[k]), source)
           for k, spec in NOISE_SPECS.items()}
    return EstimatorNoise(**out)
