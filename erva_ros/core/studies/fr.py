"""Approximate frequency response by steady-state simulation (paper §IV.A, Fig. 4).

For each sinusoidal road tone w(t) = a·sin(2πft) the nonlinear model is simulated
with constant damping u = c_e0 until the response is periodic; the tone's
chassis-acceleration amplitude and mean harvested power are then measured over
an integer number of periods.  :func:`linear_response` gives the analytic
response of the model linearised at rest, used to check the simulation.
"""

from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Sequence

import casadi as ca
import numpy as np

from erva_ros.core.model.quarter_car import linearize, QuarterCarModel

#: Steady state is declared when two successive windows agree to this relative tolerance.
SETTLE_RTOL = 1e-3


@dataclass
class ToneResult:
    """Steady-state response to one road tone."""

    freq_hz: float
    accel_amp: float        # m/s², half peak-to-peak chassis acceleration
    accel_rms: float        # m/s²
    power_mean_w: float     # W, mean harvested power
    settle_s: float         # s simulated before the measurement window


@dataclass
class FRCurve:
    """A swept frequency response of one model."""

    model: str
    damping: float
    amplitude_m: float
    tones: List[ToneResult] = field(default_factory=list)

    @property
    def freqs(self) -> np.ndarray:
        return np.array([t.freq_hz for t in self.tones])

    @property
    def accel(self) -> np.ndarray:
        return np.array([t.accel_amp for t in self.tones])

    @property
    def power(self) -> np.ndarray:
        return np.array([t.power_mean_w for t in self.tones])

    @property
    def gain_db(self) -> np.ndarray:
        """Return |z̈_s| / |w| in dB re 1 s⁻² (20·log10; -inf where there is no response)."""
        with np.errstate(divide='ignore'):
            return 20 * np.log10(self.accel / self.amplitude_m)

    @property
    def power_db(self) -> np.ndarray:
        """Return P / |w|² in dB re 1 W/m² (10·log10, a power; -inf where none)."""
        with np.errstate(divide='ignore'):
            return 10 * np.log10(self.power / self.amplitude_m ** 2)


def tone_response(model: QuarterCarModel, freq_hz: float, amplitude_m: float, damping: float,
                  dt: float = 5e-4, window_s: float = 2.0, max_s: float = 60.0) -> ToneResult:
    """Simulate one tone to steady state; measure over whole periods of the last window."""
    n = int(round(window_s / dt))
    x = model.zero_state()
    t0 = 0.0
    prev: Optional[tuple] = None
    period_samples = 1.0 / (freq_hz * dt)
    whole = int(np.floor(n / period_samples) * period_samples)
    if whole < 1:
        raise ValueError(f'window {window_s} s is shorter than one period at {freq_hz} Hz')
    u = np.full(n, damping)
    while True:
        t = t0 + dt * np.arange(n + 1)
        w = amplitude_m * np.sin(2 * np.pi * freq_hz * t)
        xs = model.simulate(x, u, w, dt)
        acc, pw = model.outputs_along(xs[-whole - 1:-1], damping, w[-whole - 1:-1])
        cur = (0.5 * (acc.max() - acc.min()), float(np.sqrt(np.mean(acc ** 2))),
               float(np.mean(pw)))
        x, t0 = xs[-1], t0 + n * dt
        if prev is not None:
            scale = np.maximum(np.abs(np.array(cur)), 1e-12)
            if np.all(np.abs(np.array(cur) - np.array(prev)) <= SETTLE_RTOL * scale):
                break
        if t0 >= max_s:
            break
        prev = cur
    return ToneResult(freq_hz, float(cur[0]), cur[1], cur[2], t0 - n * dt)


def sweep(model: QuarterCarModel, freqs: Sequence[float], amplitude_m: float, damping: float,
          progress: Optional[Callable[[int, int], None]] = None, **kw) -> FRCurve:
    """Frequency response over ``freqs`` (Hz) at constant damping ``damping`` (Ns/m)."""
    curve = FRCurve(model.kind, damping, amplitude_m)
    if progress:
        progress(0, len(freqs))
    for i, f in enumerate(freqs):
        curve.tones.append(tone_response(model, float(f), amplitude_m, damping, **kw))
        if progress:
            progress(i + 1, len(freqs))
    return curve


def find_peaks(freqs: np.ndarray, values: np.ndarray, min_rel: float = 0.02) -> List[float]:
    """Interior local maxima, refined by a parabola through the three samples (Hz).

    A maximum must exceed both neighbours and be at least ``min_rel`` of the
    curve's largest value, so flat numerical ripple is not reported as a resonance.
    """
    peaks = []
    vmax = float(np.max(values)) if len(values) else 0.0
    for i in range(1, len(values) - 1):
        local_max = values[i] > values[i - 1] and values[i] >= values[i + 1]
        if local_max and values[i] >= min_rel * vmax:
            y0, y1, y2 = values[i - 1], values[i], values[i + 1]
            denom = y0 - 2 * y1 + y2
            shift = 0.5 * (y0 - y2) / denom if denom != 0 else 0.0
            step = 0.5 * (freqs[i + 1] - freqs[i - 1])
            peaks.append(float(freqs[i] + shift * step))
    return peaks


def linear_response(model: QuarterCarModel, freqs: Sequence[float], amplitude_m: float,
                    damping: float) -> Dict[str, np.ndarray]:
    """Analytic steady-state response of the model linearised at rest.

    Returns the chassis-acceleration amplitude (m/s²) and mean harvested power
    P̄ = u·|V_gen|²·a²/2 (W) at each frequency.
    """
    a, _, bw = linearize(model, u0=damping)
    # The generator velocity is linear in x (v_gen = G·x), so G is its Jacobian.
    gen_jac = ca.Function('gen_jac', [model.x_sym],
                          [ca.jacobian(model.generator_velocity(model.x_sym), model.x_sym)])
    g_row = np.asarray(gen_jac(np.zeros(model.nx)))
    acc, pw = [], []
    for f in freqs:
        s = 2j * np.pi * f
        xw = np.linalg.solve(s * np.eye(model.nx) - a, bw).ravel()
        acc.append(abs((a[1] @ xw) + bw[1, 0]) * amplitude_m)
        v = complex((g_row @ xw).item()) * amplitude_m
        pw.append(damping * abs(v) ** 2 / 2)
    return {'accel_amp': np.array(acc), 'power_mean_w': np.array(pw)}
