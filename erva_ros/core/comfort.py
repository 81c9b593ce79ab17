"""Ride comfort as ISO 2631-1:1997 measures it: the frequency-weighted RMS acceleration a_w.

The weightings (ISO 2631-1:1997, Annex A; the same parameters in ISO 8041) are analog
transfer functions in s = j2πf, the product of

* band limiting, a 2nd-order Butterworth high-pass at f1 and low-pass at f2 (Q = 1/√2):
  H_h = 1 / (1 + √2·ω1/s + (ω1/s)²),   H_l = 1 / (1 + √2·s/ω2 + (s/ω2)²);
* the acceleration-velocity transition:
  H_t = (1 + s/ω3) / (1 + s/(Q4·ω4) + (s/ω4)²);
* the upward step (W_k only):
  H_s = (1 + s/(Q5·ω5) + (s/ω5)²) / (1 + s/(Q6·ω6) + (s/ω6)²) · (ω5/ω6)²;

with ω_i = 2π·f_i and the gain K (:data:`WEIGHTINGS`).  W_k weights vertical (z)
acceleration at the seat, W_d horizontal (x, y).

**Applied in the frequency domain.**  :func:`weight` multiplies the DFT of a sampled
acceleration by the analog H(j2πf) at each bin and transforms back; :func:`weighted_rms`
is the RMS of that signal, sqrt(Σ|H·X|²)/N by Parseval.  At every DFT frequency the
weighting is the standard's analog one to rounding, at any sampling rate -- the plant's
z̈_s comes at the control rate (50 Hz), where a bilinear (Tustin) filter would be off by
0.47 dB at 10 Hz and 8 dB at 20 Hz (W_k; docs/comfort.md), and the 100 Hz band limit lies
above Nyquist.
The record is taken as one period of a stationary signal (no start transient, as a
time-domain filter from rest would have); what that costs for a record whose ends do
not match is leakage between bins, measured in docs/comfort.md.  A signal sampled at fs
holds nothing above fs/2: the weighting there is not applied, because there is nothing
to apply it to.

For the body of a car, :func:`point_vertical_acceleration` gives the vertical
acceleration at a point (x forward, y left of the centre of gravity) from the body's
heave, pitch and roll accelerations, z̈_p = z̈_c − x·θ̈ + y·φ̈ (small angles, the car
model's ISO 8855 axes: θ pitch, positive nose down; φ roll, positive left side up), and
:func:`point_weighted_rms` its a_w with W_k: the driver's seat comfort figure.
"""

from dataclasses import dataclass
import math
from typing import Optional

import numpy as np

#: Nominal one-third-octave band centres (Hz) of ISO 2631-1's tables, 0.1-400 Hz.
THIRD_OCTAVE_NOMINAL_HZ = (0.1, 0.125, 0.16, 0.2, 0.25, 0.315, 0.4, 0.5, 0.63, 0.8, 1.0,
                           1.25, 1.6, 2.0, 2.5, 3.15, 4.0, 5.0, 6.3, 8.0, 10.0, 12.5, 16.0,
                           20.0, 25.0, 31.5, 40.0, 50.0, 63.0, 80.0, 100.0, 125.0, 160.0,
                           200.0, 250.0, 315.0, 400.0)


class ComfortError(ValueError):
    """An input to the comfort metrics is invalid (one-line message)."""


@dataclass(frozen=True)
class Weighting:
    """One ISO 2631-1 frequency weighting's parameters (Hz; None: the filter is absent)."""

    name: str
    f1: float                       # high-pass band limit
    f2: float                       # low-pass band limit
    f3: Optional[float]             # acceleration-velocity transition
    f4: Optional[float]
    q4: Optional[float]
    f5: Optional[float]             # upward step
    q5: Optional[float]
    f6: Optional[float]
    q6: Optional[float]
    gain: float = 1.0

    def response(self, f_hz) -> np.ndarray:
        """Return the complex analog response H(j2πf) at the frequencies ``f_hz`` (Hz)."""
        f = np.asarray(f_hz, dtype=float)
        s = 2j * math.pi * f
        w1, w2 = 2 * math.pi * self.f1, 2 * math.pi * self.f2
        with np.errstate(divide='ignore', invalid='ignore'):
            h = 1.0 / (1.0 + math.sqrt(2.0) * w1 / s + (w1 / s) ** 2)
        h = np.where(f == 0, 0.0, h)        # the high-pass's zero at DC
        h = h / (1.0 + math.sqrt(2.0) * s / w2 + (s / w2) ** 2)
        if self.f3 is not None:
            w3, w4 = 2 * math.pi * self.f3, 2 * math.pi * self.f4
            h = h * (1.0 + s / w3) / (1.0 + s / (self.q4 * w4) + (s / w4) ** 2)
        if self.f5 is not None:
            w5, w6 = 2 * math.pi * self.f5, 2 * math.pi * self.f6
            h = h * ((1.0 + s / (self.q5 * w5) + (s / w5) ** 2)
                     / (1.0 + s / (self.q6 * w6) + (s / w6) ** 2) * (w5 / w6) ** 2)
        return self.gain * h


#: ISO 2631-1:1997 Annex A (the parameters as ISO 8041 tabulates them): W_k vertical, W_d
#: horizontal.
WEIGHTINGS = {
    'k': Weighting('W_k', 0.4, 100.0, 12.5, 12.5, 0.63, 2.37, 0.91, 3.35, 0.91),
    'd': Weighting('W_d', 0.4, 100.0, 2.0, 2.0, 0.63, None, None, None, None),
}


def weighting_of(name) -> Weighting:
    """Return the weighting ``name`` ('k' / 'W_k' / 'Wk', 'd' ...); one-line ComfortError."""
    key = str(name).lower()
    key = key[2:] if key.startswith('w_') else key[1:] if key.startswith('w') else key
    if key not in WEIGHTINGS:
        raise ComfortError(f'weighting {name!r}; choose one of k (vertical), d (horizontal)')
    return WEIGHTINGS[key]


def _signal(acc, fs) -> np.ndarray:
    a = np.asarray(acc, dtype=float)
    if a.ndim != 1 or a.size < 2:
        raise ComfortError(f'acceleration must be 1-D with at least 2 samples, got shape '
                           f'{a.shape}')
    bad = int(np.count_nonzero(~np.isfinite(a)))
    if bad:
        raise ComfortError(f'acceleration has {bad} non-finite sample(s) (NaN or inf)')
    try:
        fs = float(fs)
    except (TypeError, ValueError):
        raise ComfortError(f'sampling rate fs={fs!r} is not a number') from None
    if not (math.isfinite(fs) and fs > 0):
        raise ComfortError(f'sampling rate fs={fs!r} must be a positive finite number (Hz)')
    return a


def weight(acc, fs: float, weighting='k') -> np.ndarray:
    """Return the frequency-weighted acceleration a_w(t) of ``acc`` sampled at ``fs`` Hz."""
    a = _signal(acc, fs)
    w = weighting_of(weighting)
    f = np.fft.rfftfreq(a.size, d=1.0 / float(fs))
    return np.fft.irfft(np.fft.rfft(a) * w.response(f), a.size)


def weighted_rms(acc, fs: float, weighting='k') -> float:
    """Return a_w = RMS of the weighted acceleration (m/s², ISO 2631-1 clause 6).

    ``acc`` in m/s² at ``fs`` Hz, ``weighting`` 'k' (vertical, seat) or 'd' (horizontal).
    """
    return float(np.sqrt(np.mean(weight(acc, fs, weighting) ** 2)))


def point_vertical_acceleration(heave_acc, pitch_acc, roll_acc, x_m: float,
                                y_m: float) -> np.ndarray:
    """Return z̈ = z̈_c − x·θ̈ + y·φ̈ (m/s²) at the body point (x_m forward, y_m left, m).

    ``heave_acc`` z̈_c (m/s²), ``pitch_acc`` θ̈ and ``roll_acc`` φ̈ (rad/s²) of the body at
    its centre of gravity, sampled alike; the axes of the car model (core/model/full_car.py,
    ISO 8855): θ positive nose down, φ positive left side up.
    """
    arrays = [np.asarray(v, dtype=float) for v in (heave_acc, pitch_acc, roll_acc)]
    if len({a.shape for a in arrays}) != 1 or arrays[0].ndim != 1:
        raise ComfortError('heave, pitch and roll accelerations must be 1-D of one length, got '
                           + ', '.join(str(a.shape) for a in arrays))
    for name, v in (('x_m', x_m), ('y_m', y_m)):
        if not math.isfinite(float(v)):
            raise ComfortError(f'seat position {name}={v!r} must be finite (m)')
    return arrays[0] - float(x_m) * arrays[1] + float(y_m) * arrays[2]


def point_weighted_rms(heave_acc, pitch_acc, roll_acc, fs: float, x_m: float,
                       y_m: float) -> float:
    """Return a_w (W_k, m/s²) of the vertical acceleration at the body point (x_m, y_m)."""
    return weighted_rms(point_vertical_acceleration(heave_acc, pitch_acc, roll_acc, x_m, y_m),
                        fs, 'k')


def bilinear_error_db(f_hz, fs: float, weighting='k') -> np.ndarray:
    """Return how far a bilinear (Tustin) discretisation at ``fs`` is off the analog |H| (dB).

    The bilinear map s = 2·fs·(z − 1)/(z + 1) puts the analog response at ω_a =
    2·fs·tan(πf/fs) where the digital filter is at f: its magnitude error at f is
    20·lg|H(jω_a)/H(j2πf)|.  For the documentation's comparison with :func:`weight`.
    """
    f = np.asarray(f_hz, dtype=float)
    w = weighting_of(weighting)
    warped = 2 * float(fs) * np.tan(math.pi * f / float(fs)) / (2 * math.pi)
    return 20 * np.log10(np.abs(w.response(warped)) / np.abs(w.response(f)))


__all__ = ['THIRD_OCTAVE_NOMINAL_HZ', 'ComfortError', 'Weighting', 'WEIGHTINGS', 'weighting_of',
           'weight', 'weighted_rms', 'point_vertical_acceleration', 'point_weighted_rms',
           'bilinear_error_db']
