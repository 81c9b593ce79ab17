"""Excitation for identification: c_e driven by a PRBS or a chirp, whatever the state.

``erva identify`` fits the model's parameters to a recorded session; the generator's
parameters (and the absolute scale of the masses, through the force c_e·v_gen) are
seen only where the damping changes.  This law ignores the state and the preview and
commands, at sample k (t_k = k·Ts from the first sample it is asked for):

``prbs``
    a maximum-length pseudo-random binary sequence (11-bit Fibonacci LFSR, taps 11 and
    9: period 2047 bits) between u_min and u_max, one bit per ``excite_bit_s``; its
    spectrum is flat to about 0.44/``excite_bit_s`` Hz (22 Hz at one bit per 20 ms,
    above the wheel-hop mode).  ``excite_seed`` picks the register's start: another
    seed is the same sequence shifted.
``chirp``
    u = (u_min + u_max)/2 + (u_max − u_min)/2·sin φ(t), a logarithmic sweep from
    ``excite_f0_hz`` to ``excite_f1_hz`` over ``excite_sweep_s``, repeated.

Always inside the actuator's range [u_min, u_max] (the settings' input box).  The plan
is the signal's next N values, so a plant that holds the plan (a late command) keeps
exciting.  Deterministic: the value at sample k depends on k and the settings only.
"""

import math

import numpy as np

from erva_ros.core.controllers.base import Controller
from erva_ros.core.settings.controller import EXCITE_SIGNALS as SIGNALS
#: LFSR of the PRBS: 11 bits, feedback from bits 11 and 9 (x^11 + x^9 + 1, maximal).
PRBS_BITS = 11
PRBS_PERIOD = 2 ** PRBS_BITS - 1


def prbs_bits(n: int, seed: int = 0) -> np.ndarray:
    """Return the first ``n`` bits (0/1) of the maximum-length sequence started by ``seed``."""
    state = seed % PRBS_PERIOD + 1            # any non-zero register
    out = np.empty(n, dtype=np.int8)
    for i in range(n):
        out[i] = state & 1
        bit = (state ^ (state >> 2)) & 1      # taps 11 and 9 of the shifted-out end
        state = (state >> 1) | (bit << (PRBS_BITS - 1))
    return out


class ExciteController(Controller):
    """c_e from an excitation signal (module doc); the state and the preview are ignored."""

    name = 'excite'

    def __init__(self, horizon: int, ts: float, u_min: float, u_max: float, c_e0: float,
                 signal: str = 'prbs', bit_s: float = 0.02, seed: int = 0,
                 f0_hz: float = 0.5, f1_hz: float = 15.0, sweep_s: float = 20.0):
        if signal not in SIGNALS:
            raise ValueError(f'excitation signal {signal!r}; choose one of {", ".join(SIGNALS)}')
        self.signal = signal
        self.bit_samples = max(1, int(round(bit_s / ts)))
        self.seed = int(seed)
        self.f0_hz, self.f1_hz, self.sweep_s = float(f0_hz), float(f1_hz), float(sweep_s)
        super().__init__(horizon, ts, u_min, u_max, c_e0)
        # One PRBS period, bit by bit: the signal repeats after it.
        self._bits = prbs_bits(PRBS_PERIOD, self.seed)

    def _reset_law(self) -> None:
        self._t0 = None

    def values(self, k) -> np.ndarray:
        """Return the command (Ns/m) at samples ``k`` (integers >= 0) since the first."""
        k = np.asarray(k)
        lo, hi = self.u_min, self.u_max
        if self.signal == 'prbs':
            bits = self._bits[(k // self.bit_samples) % PRBS_PERIOD]
            return np.where(bits == 1, hi, lo).astype(float)
        tau = (k * self.ts) % self.sweep_s
        rate = math.log(self.f1_hz / self.f0_hz) / self.sweep_s
        phase = 2 * math.pi * self.f0_hz * np.expm1(rate * tau) / rate
        return (lo + hi) / 2 + (hi - lo) / 2 * np.sin(phase)

    def _compute(self, x, preview, t):
        if self._t0 is None:
            self._t0 = t
        k = max(0, int(round((t - self._t0) / self.ts)))
        return self.values(k + np.arange(self.horizon)), 0


__all__ = ['ExciteController', 'SIGNALS', 'prbs_bits', 'PRBS_PERIOD']
