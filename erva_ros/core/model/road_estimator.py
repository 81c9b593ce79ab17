"""The road at the tyre, estimated: an augmented-state EKF on the shared model, and RTS smoothing.

:class:`erva_ros.core.model.estimator.ExtendedKalmanFilter` takes the road height at the tyre w as
a known input; a vehicle has no such sensor.  :class:`RoadEKF` makes w a state, driven by a
road model, and rebuilds the quarter car's state *and* w(t_k) from what the ECU measures
(every row is on ``ecu/measurements``, erva_ros/core/hil/topics.py):

=====  ==========================================  ===========================================
y      measurement                                 model output (erva_ros.core.model.quarter_car)
=====  ==========================================  ===========================================
y_1    sprung-mass acceleration z̈_s (m/s²)         ``measurements`` row 0 (ẋ_2, eq. (11))
y_2    suspension deflection z_s − z_us (m)        ``measurements`` row 1
y_3    generator speed φ̇ = v_gen / l (rad/s)       ``measurements`` row 2
y_4    generator force κ·i = c_e·v_gen (N)         c_e·``generator_velocity`` (hardware.py)
y_5    unsprung acceleration z̈_us (m/s²)           ẋ_4 of ``ode``; no such sensor ships
=====  ==========================================  ===========================================

A row is NaN when it was not measured (a lost CAN frame, or no such sensor).

Road model (:class:`RoadModel`), on the sample grid as every user of the road sees it
(linear between the samples):

``random_walk``  w_{k+1} = w_k + e_k, e_k ~ N(0, σ²).  ISO 8608's G_d(n) ∝ n⁻² is a random
                 walk in distance (:meth:`RoadModel.iso8608` gives σ of a class); σ = 1 m
                 (the default) is the unknown-input limit, no prior on the road.
``integrated``   w, ẇ with ẅ white of spectral density σ².

What is observable.  The dynamics and the sensors depend on z_s − z_us, z_us − w and on
velocity *differences*; the accelerometer's integral gives the body's motion only up to
its initial velocity.  So a common offset of (z_s, z_us, w) -- the absolute height of the
road and of the car -- is not observable, and a common vertical velocity only through the
road model's prior.  Everything relative is: the road's detail (its shape over metres),
the tyre and suspension deflections, the velocity differences.  The filter therefore works
in the coordinates ξ = x − S·w (S adds w to z_s and z_us: the car relative to the road
under it) and r = [w(, ẇ)]: ξ's transition x_{k+1} = F(x_k, u, w_k, w_{k+1}) (the shared
``rk4_step``) becomes ξ_{k+1} = F(ξ_k, u, 0, Δ_k) − S·Δ_k with Δ_k = w_{k+1} − w_k, so the
unobservable offset is w alone and never feeds back into ξ.  The road noise e_k enters ξ
too (x_{k+1} depends on w_{k+1}): the process covariance is G·Q_e·Gᵀ, G = ∂z_{k+1}/∂e, exact.

Variances (:class:`RoadEstimate`): ``var_w`` is that of the road height *relative to the
body* (ξ_0 = z_s − w, observable, bounded); ``var_w_abs`` that of w itself, which grows
without bound (the offset).  docs/road.md measures the errors of both kinds.

Smoother: :meth:`RoadEKF.smooth` runs the fixed-interval Rauch–Tung–Striebel pass over the
cycles since :meth:`RoadEKF.reset` (``keep_history=True``), for recorded drives.
"""

from dataclasses import dataclass, field
import math
from typing import List, Optional, Tuple

import casadi as ca
import numpy as np

from erva_ros.core.model.codegen import BufferedCall, compile_for
from erva_ros.core.model.estimator import acceleration_noise, EstimatorNoise, sequential_update
from erva_ros.core.model.hardware import GeneratorHardware
from erva_ros.core.model.quarter_car import QuarterCarModel, rk4_stable_substeps
from erva_ros.core.model.params import ParamError
from erva_ros.core.road.profiles import DEFAULT_SPEED_MPS, ISO_CLASSES

#: Measurement rows, in the order of y (NaN = not measured this cycle, or no such sensor).
ROAD_MEASUREMENTS = ('sprung_accel', 'deflection', 'generator_speed', 'generator_force',
                     'unsprung_accel')
ROAD_MODEL_KINDS = ('random_walk', 'integrated')
#: ISO 8608's reference spatial frequency n0 (cycle/m), as in erva_ros.core.road.profiles.
ISO_N0 = 0.1
#: DBC resolution of the ECU's signals (config/erva_ecu.dbc); ``current`` in A.
QUANTA = {'sprung_accel': 1e-3, 'deflection': 1e-5, 'generator_speed': 1e-3, 'current': 1e-3}
#: Process noise of the road estimator (m/s²): the model's unmodelled accelerations.  The
#: known-road EKF's q_accel_us = 1 m/s² stands for the road's error; here the road is a
#: state (docs/road.md: measured on development seeds 0-2).
ROAD_PROCESS_NOISE = 0.01


@dataclass(frozen=True)
class RoadModel:
    """Prior of the road at the tyre, sampled at Ts (see the module docstring)."""

    kind: str = 'random_walk'
    #: random_walk: std of w_{k+1} − w_k (m); integrated: sqrt of ẅ's spectral density
    #: (m/s^1.5).  The default, 1 m per sample, is the unknown-input limit.
    sigma: float = 1.0

    def __post_init__(self):
        if self.kind not in ROAD_MODEL_KINDS:
            raise ParamError(f'road model {self.kind!r}; choose one of '
                             f'{", ".join(ROAD_MODEL_KINDS)}')
        if not (isinstance(self.sigma, (int, float)) and math.isfinite(self.sigma)
                and self.sigma > 0):
            raise ParamError(f'road model sigma = {self.sigma!r} must be a number > 0')

    @staticmethod
    def iso8608(road_class: str = 'C', speed_mps: float = DEFAULT_SPEED_MPS,
                ts: float = 0.02) -> 'RoadModel':
        """Return the random walk of an ISO 8608 class driven at ``speed_mps``.

        The slope of an ISO road is white with one-sided PSD (2π·n0)²·G_d(n0), so the
        height's increment over Δx = v·Ts has variance (2π·n0)²·G_d(n0)·Δx / 2.
        """
        road_class = str(road_class).upper()
        if road_class not in tuple(ISO_CLASSES):
            raise ParamError(f'road class {road_class!r}; choose one of A, B, C, D, E')
        gd_n0 = 16e-6 * 4 ** ISO_CLASSES.index(road_class)
        slope_psd = (2 * math.pi * ISO_N0) ** 2 * gd_n0
        return RoadModel('random_walk', math.sqrt(slope_psd * speed_mps * ts / 2))

    @property
    def n_states(self) -> int:
        return 1 if self.kind == 'random_walk' else 2

    def matrices(self, ts: float) -> Tuple[np.ndarray, np.ndarray]:
        """Return (Φ, Q_e): r_{k+1} = Φ·r_k + e_k, cov(e_k) = Q_e, with w = r[0]."""
        if self.kind == 'random_walk':
            return np.array([[1.0]]), np.array([[self.sigma ** 2]])
        q = self.sigma ** 2
        return (np.array([[1.0, ts], [0.0, 1.0]]),
                q * np.array([[ts ** 3 / 3, ts ** 2 / 2], [ts ** 2 / 2, ts]]))


@dataclass(frozen=True)
class RoadSensors:
    """Standard deviations (SI units) of the rows of y; None: no such sensor."""

    sprung_accel: float
    deflection: float
    generator_speed: float
    generator_force: Optional[float]
    unsprung_accel: Optional[float] = None

    @staticmethod
    def of(noise: EstimatorNoise = EstimatorNoise(),
           hardware: GeneratorHardware = GeneratorHardware(), current_a: Optional[float] = 0.01,
           unsprung_accel: Optional[float] = None) -> 'RoadSensors':
        """Return the sensors the EKF's ``noise`` describes, plus the generator current.

        Each std gets the DBC's quantisation added as a uniform error (q/√12); the
        generator force κ·i has κ·σ_i (``current_a`` None: not used).  Defaults: the
        shipped simulated ECU (config/hil.yaml).
        """
        def std(sigma, quantum):
            return math.sqrt(sigma ** 2 + quantum ** 2 / 12)

        force = (None if current_a is None
                 else hardware.kappa_n_per_a * std(current_a, QUANTA['current']))
        return RoadSensors(std(noise.r_sprung_accel, QUANTA['sprung_accel']),
                           std(noise.r_deflection, QUANTA['deflection']),
                           std(noise.r_speed, QUANTA['generator_speed']), force, unsprung_accel)

    def r_diag(self) -> np.ndarray:
        """Return the variances of the rows (1 for rows without a sensor: never used)."""
        vals = (self.sprung_accel, self.deflection, self.generator_speed,
                self.generator_force, self.unsprung_accel)
        return np.array([1.0 if v is None else v ** 2 for v in vals])

    def present(self) -> np.ndarray:
        """Return the mask of rows this vehicle has a sensor for."""
        return np.array([True, True, True, self.generator_force is not None,
                         self.unsprung_accel is not None])


def damping_profile(u_mean: float, u_now: float, u_prev: Optional[float], ts: float
                    ) -> Tuple[float, float, float]:
    """Return (u_a, u_b, d): u_a acts on [0, d), u_b on [d, Ts) of an ECU period.

    The ECU reports the damping at the end of the period (u_now) and its mean; a command
    latched once, d after the sample (the HIL loop's ~6 ms), gives
    d = Ts·(u_mean − u_now)/(u_prev − u_now).  When that does not hold (no change, more
    than one, a timeout) the mean acts throughout: (u_mean, u_mean, 0).
    """
    if u_prev is None or abs(u_prev - u_now) <= 1e-9 * max(1.0, abs(u_now)):
        return u_mean, u_mean, 0.0
    d = ts * (u_mean - u_now) / (u_prev - u_now)
    if not -1e-3 * ts <= d <= ts * (1 + 1e-3):
        return u_mean, u_mean, 0.0
    return u_prev, u_now, min(max(d, 0.0), ts)


def road_noise() -> EstimatorNoise:
    """Return the road estimator's default noise (shipped sensors, ROAD_PROCESS_NOISE)."""
    return EstimatorNoise(q_accel_s=ROAD_PROCESS_NOISE, q_accel_us=ROAD_PROCESS_NOISE,
                          q_accel_d=ROAD_PROCESS_NOISE)


@dataclass
class RoadEstimate:
    """One cycle's result."""

    x: np.ndarray            # quarter-car state x̂ = ξ̂ + S·ŵ (m, m/s; offset unobservable)
    w: float                 # road height at the tyre (m; offset unobservable)
    var_w: float             # variance of the road height relative to the body (m²)
    var_w_abs: float         # variance of w itself (m²; grows: the offset)
    nis: float               # normalised innovation squared of the rows used
    rows: int                # measurement rows used


@dataclass
class SmoothedDrive:
    """RTS-smoothed estimates of a recorded drive, one row per cycle."""

    x: np.ndarray            # (n, nx)
    w: np.ndarray            # (n,) m
    var_w: np.ndarray        # (n,) m², relative to the body (as RoadEstimate.var_w)
    w_filtered: np.ndarray   # (n,) the filter's causal estimates
    var_filtered: np.ndarray  # (n,) m²


@dataclass
class _History:
    z_pred: List[np.ndarray] = field(default_factory=list)
    p_pred: List[np.ndarray] = field(default_factory=list)
    z_filt: List[np.ndarray] = field(default_factory=list)
    p_filt: List[np.ndarray] = field(default_factory=list)
    a: List[np.ndarray] = field(default_factory=list)


class RoadEKF:
    """EKF on ``QuarterCarModel.rk4_step`` with the road at the tyre as a state."""

    def __init__(self, model: QuarterCarModel, ts: float = 0.02,
                 noise: Optional[EstimatorNoise] = None, road: RoadModel = RoadModel(),
                 sensors: Optional[RoadSensors] = None, u_max: float = 22800.0,
                 codegen: str = 'auto', keep_history: bool = False):
        self.model = model
        self.params = model.params
        self.ts = float(ts)
        self.noise = noise or road_noise()
        self.road = road
        self.sensors = sensors or RoadSensors.of(self.noise)
        self.keep_history = keep_history
        nx, nr = self.model.nx, road.n_states
        self.nx, self.nz = nx, nx + nr
        self.substeps = rk4_stable_substeps(self.model, self.ts, max(u_max, 1.0))
        # rk4_flow as a loop (x, u, w0, w1, dt), stable to Ts: its Jacobians compile in
        # seconds, not minutes (model.py).
        flow = self.model.rk4_loop(None, self.substeps)
        phi, self.Qe = road.matrices(self.ts)
        self._shift = np.zeros(nx)
        self._shift[0] = self._shift[2] = 1.0           # S: z_s and z_us ride on w
        z, e = ca.MX.sym('z', self.nz), ca.MX.sym('e', nr)
        u = ca.MX.sym('u', 3)                           # u_a on [0, d), u_b on [d, Ts), d
        xi, r = z[:nx], z[nx:]
        r1 = ca.mtimes(ca.DM(phi), r) + e
        dw = r1[0] - r[0]
        wd = dw * u[2] / self.ts                        # the road at the switch
        xd = flow(xi, u[0], 0, wd, u[2])
        zn = ca.vertcat(flow(xd, u[1], wd, dw, self.ts - u[2]) - ca.DM(self._shift) * dw, r1)
        prediction = ca.Function('road_ekf_prediction', [z, u, e],
                                 [zn, ca.jacobian(zn, z), ca.jacobian(zn, e)])
        zn0, a, g = (ca.densify(v) for v in prediction(z, u, ca.DM.zeros(nr)))
        zs, u_now = ca.SX.sym('z', self.nz), ca.SX.sym('u_now')
        y = self._outputs(zs, u_now)
        h = ca.Function('road_ekf_h', [zs, u_now], [y, ca.densify(ca.jacobian(y, zs))])
        cycle = self._cycle_function(z, u, zn0, a, g, h)
        h, cycle = compile_for(codegen, (h, cycle), 'the road EKF')
        self._h = BufferedCall(h)
        self._cycle = BufferedCall(cycle)
        self.Qx = acceleration_noise(self.noise, nx, self.ts, self.nz)   # on ξ
        self._r = self.sensors.r_diag()
        self._present = self.sensors.present()
        self.reset()

    # -- the model ----------------------------------------------------------------------
    def _outputs(self, z, u_now):
        """Return y = h(z, u) in ROAD_MEASUREMENTS order, from the shared model."""
        m = self.model
        w = z[self.nx]
        x = z[:self.nx] + ca.DM(self._shift) * w
        return ca.vertcat(m.measurements(x, u_now, w), u_now * m.generator_velocity(x),
                          m.ode(x, u_now, w)[3])

    def _cycle_function(self, z, u, zn, a, g, hfun) -> ca.Function:
        """Predict + sequential update of one cycle as one CasADi function (R diagonal).

        The rows are applied one by one, each only where its mask is 1, with the output
        linearised once at the prior: equal to the batch update.
        """
        nz, ny, nr = self.nz, len(ROAD_MEASUREMENTS), self.road.n_states
        # The update in SX (elementwise, as before), called from the MX prediction.
        zn_s, a_s, g_s = ca.SX.sym('zn', nz), ca.SX.sym('A', nz, nz), ca.SX.sym('G', nz, nr)
        p, q = ca.SX.sym('P', nz, nz), ca.SX.sym('Q', nz, nz)
        qe = ca.SX.sym('Qe', nr, nr)
        u_now_s = ca.SX.sym('u_now')
        r, y, mask = ca.SX.sym('r', ny), ca.SX.sym('y', ny), ca.SX.sym('mask', ny)
        p1 = a_s @ p @ a_s.T + q + g_s @ qe @ g_s.T
        yh, hh = hfun(zn_s, u_now_s)
        zk, pk, nis = sequential_update(zn_s, p1, yh, hh, y, mask, r)
        update = ca.Function('road_ekf_update',
                             [zn_s, a_s, g_s, p, q, qe, r, u_now_s, y, mask],
                             [ca.densify(v) for v in (zk, pk, nis, p1)])
        pm, qm, qem = ca.MX.sym('P', nz, nz), ca.MX.sym('Q', nz, nz), ca.MX.sym('Qe', nr, nr)
        rm, ym, mask_m = ca.MX.sym('r', ny), ca.MX.sym('y', ny), ca.MX.sym('mask', ny)
        u_now_m = ca.MX.sym('u_now')
        zk, pk, nis, p1 = update(zn, a, g, pm, qm, qem, rm, u_now_m, ym, mask_m)
        return ca.Function('road_ekf_cycle', [z, pm, qm, qem, rm, u, u_now_m, ym, mask_m],
                           [zk, pk, nis, zn, p1, a],
                           ['z', 'P', 'Q', 'Qe', 'r', 'u_profile', 'u_now', 'y', 'mask'],
                           ['z_next', 'P_next', 'nis', 'z_pred', 'P_pred', 'A'])

    # -- the filter ---------------------------------------------------------------------
    def reset(self, x0: Optional[np.ndarray] = None, w0: float = 0.0) -> None:
        """Restart at ``x0`` (default rest) on road height ``w0``, with the prior covariance."""
        z = np.zeros(self.nz)
        if x0 is not None:
            z[:self.nx] = np.asarray(x0, dtype=float) - self._shift * w0
        z[self.nx] = w0
        self.z = z
        pos, vel = self.noise.p0_position ** 2, self.noise.p0_velocity ** 2
        self.P = np.diag([pos, vel] * (self.nx // 2) + [pos] + [vel] * (self.road.n_states - 1))
        self.k = 0
        self.history = _History() if self.keep_history else None

    @property
    def x(self) -> np.ndarray:
        """Return the quarter car's state estimate x̂ = ξ̂ + S·ŵ (m, m/s)."""
        return self.z[:self.nx] + self._shift * self.z[self.nx]

    @property
    def w(self) -> float:
        return float(self.z[self.nx])

    def _mask(self, y) -> Tuple[np.ndarray, np.ndarray]:
        y = np.asarray(y, dtype=float).ravel()
        if y.size != len(ROAD_MEASUREMENTS):
            raise ValueError(f'y needs {len(ROAD_MEASUREMENTS)} rows '
                             f'({", ".join(ROAD_MEASUREMENTS)}), got {y.size}')
        mask = np.isfinite(y) & self._present
        return np.where(mask, y, 0.0), mask

    def _estimate(self, nis: float, rows: int) -> RoadEstimate:
        return RoadEstimate(self.x, self.w, float(self.P[0, 0]),
                            float(self.P[self.nx, self.nx]), float(nis), rows)

    def start(self, y, u_now: float) -> RoadEstimate:
        """Correct the initial estimate with the first cycle's y (no prediction)."""
        y, mask = self._mask(y)
        yh, hh = self._h(self.z, u_now)
        z0, nis = self.z.copy(), 0.0
        for i in np.flatnonzero(mask):
            h = hh[i]
            nu = y[i] - (yh[i] + h @ (self.z - z0))
            ph = self.P @ h
            s = float(h @ ph + self._r[i])
            k = ph / s
            ikh = np.eye(self.nz) - np.outer(k, h)
            self.z = self.z + k * nu
            self.P = ikh @ self.P @ ikh.T + self._r[i] * np.outer(k, k)
            nis += nu * nu / s
        if self.history is not None:
            self.history = _History(z_filt=[self.z.copy()], p_filt=[self.P.copy()])
        return self._estimate(nis, int(mask.sum()))

    def cycle(self, y, u_mean: float, u_now: float, u_prev: Optional[float] = None
              ) -> RoadEstimate:
        """Predict over one ECU period with its damping, then correct with y.

        y in :data:`ROAD_MEASUREMENTS` order, NaN = missing (all NaN: a cycle without
        measurements, predicted only); ``u_now`` is the damping applied when the sensors
        were sampled, ``u_mean`` its mean over the period (the ECU's status frame) and
        ``u_prev`` the damping at the previous sample, in Ns/m.  With ``u_prev`` the
        period is predicted as the ECU applied it (:func:`damping_profile`), else with
        ``u_mean`` throughout.
        """
        y, mask = self._mask(y)
        profile = damping_profile(u_mean, u_now, u_prev, self.ts)
        z, p, nis, zp, pp, a = self._cycle(self.z, self.P, self.Qx, self.Qe, self._r,
                                           profile, u_now, y, mask.astype(float))
        self.z, self.P = z, p
        self.k += 1
        h = self.history
        if h is not None:
            if not h.z_filt:
                raise RuntimeError('RoadEKF with keep_history: call start() first')
            h.z_pred.append(zp)
            h.p_pred.append(pp)
            h.a.append(a)
            h.z_filt.append(z.copy())
            h.p_filt.append(p.copy())
        return self._estimate(nis, int(mask.sum()))

    def smooth(self) -> SmoothedDrive:
        """Return the fixed-interval RTS smoothing of every cycle since :meth:`start`."""
        h = self.history
        if h is None or not h.z_filt:
            raise RuntimeError('RoadEKF.smooth needs keep_history=True and start()')
        n = len(h.z_filt)
        zs, ps = [None] * n, [None] * n
        zs[-1], ps[-1] = h.z_filt[-1], h.p_filt[-1]
        for k in range(n - 2, -1, -1):
            pp = h.p_pred[k]
            c = np.linalg.solve(pp.T, (h.p_filt[k] @ h.a[k].T).T).T
            zs[k] = h.z_filt[k] + c @ (zs[k + 1] - h.z_pred[k])
            ps[k] = h.p_filt[k] + c @ (ps[k + 1] - pp) @ c.T
        zs = np.array(zs)
        iw = self.nx
        return SmoothedDrive(zs[:, :iw] + np.outer(zs[:, iw], self._shift), zs[:, iw],
                             np.array([p[0, 0] for p in ps]),
                             np.array([z[iw] for z in h.z_filt]),
                             np.array([p[0, 0] for p in h.p_filt]))


__all__ = ['ROAD_MEASUREMENTS', 'ROAD_MODEL_KINDS', 'QUANTA', 'ROAD_PROCESS_NOISE', 'RoadModel',
           'RoadSensors', 'RoadEKF', 'RoadEstimate', 'SmoothedDrive', 'damping_profile',
           'road_noise']
