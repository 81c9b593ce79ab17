"""Road profiles on a distance grid: the observable detail, and profile matching.

A road estimate's absolute height and its slow drift are not observable
(erva_ros/core/model/road_estimator.py), and every drive has its own.  What drives share is the
*detail*: :func:`highpass` removes a Gaussian-weighted local mean of standard deviation
``highpass_m`` (zero phase; NaN marks samples without data, which do not count).  With the
default 6 m, a 1.7 Hz wave at 15-20 m/s (λ ≥ 8.8 m) keeps ≥ 99.9 % of its amplitude, and
wavelengths beyond ~80 m are gone.

:func:`match` finds where a short profile lies on another: the offset δ maximising the
normalised cross-correlation of the two (each with its linear trend removed) over a
search range, refined to a fraction of the grid by a parabola through the peak.
"""

from dataclasses import dataclass
import math

import numpy as np

#: Default standard deviation of the high-pass's Gaussian local mean (m).
HIGHPASS_M = 6.0


def gaussian_lowpass(h: np.ndarray, dx: float, sigma_m: float) -> np.ndarray:
    """Return the Gaussian-weighted local mean of ``h`` (grid spacing ``dx``); NaN = no data.

    Normalised convolution: near the ends and gaps only the samples present count.
    """
    h = np.asarray(h, dtype=float)
    valid = np.isfinite(h)
    half = int(math.ceil(4 * sigma_m / dx))
    x = np.arange(-half, half + 1) * dx
    kernel = np.exp(-0.5 * (x / sigma_m) ** 2)
    # 'full' and the centre: 'same' returns the longer of the two (a drive shorter
    # than the kernel, 8·sigma_m).
    centre = slice(half, half + h.size)
    num = np.convolve(np.where(valid, h, 0.0), kernel)[centre]
    den = np.convolve(valid.astype(float), kernel)[centre]
    with np.errstate(invalid='ignore', divide='ignore'):
        out = num / den
    return np.where(valid, out, np.nan)


def highpass(h: np.ndarray, dx: float, sigma_m: float = HIGHPASS_M) -> np.ndarray:
    """Return ``h`` minus its Gaussian local mean: the profile's observable detail (m)."""
    return np.asarray(h, dtype=float) - gaussian_lowpass(h, dx, sigma_m)


def detrend(v: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Return ``v`` minus its least-squares line over ``x``.

    Closed form: it is the hot path of registration and alignment.
    """
    xc = x - x.mean()
    r = v - v.mean()
    den = float(xc @ xc)
    return r - (float(xc @ r) / den) * xc if den > 0 else r


@dataclass(frozen=True)
class Match:
    """Where a profile lies on another (see :func:`match`)."""

    offset_m: float          # add to the profile's positions to land on the reference
    correlation: float       # normalised cross-correlation at the offset, in [-1, 1]
    offset_std_m: float      # from the peak's width: how sharply the offset is determined
    points: int              # samples compared
    at_edge: bool            # the best offset is at the search range's edge


def match(s: np.ndarray, h: np.ndarray, ref_x0: float, ref_dx: float, ref_h: np.ndarray,
          center_m: float, search_m: float, step_m: float) -> Match:
    """Return the offset δ in center_m ± search_m at which h(s) best matches ref(s + δ).

    ``ref_h`` is a profile on the grid ref_x0 + i·ref_dx (NaN = no data); candidates are
    spaced ``step_m``.  A candidate needs 80 % of the points on data.  Both sides are
    detrended (a line), since the live estimate drifts.  ``offset_std_m`` is the
    half-width of the parabola through the peak at the height 1 − ρ below it: a broad or
    weak peak is uncertain.  Returns correlation −1 when no candidate had enough data.
    """
    s = np.asarray(s, dtype=float)
    h = np.asarray(h, dtype=float)
    cands = center_m + np.arange(-search_m, search_m + 0.5 * step_m, step_m)
    pos = (s[None, :] + cands[:, None] - ref_x0) / ref_dx
    i0 = np.floor(pos).astype(int)
    frac = pos - i0
    n = ref_h.size
    inside = (i0 >= 0) & (i0 + 1 < n)
    i0c = np.clip(i0, 0, max(n - 2, 0))
    samp = ref_h[i0c] * (1 - frac) + ref_h[np.minimum(i0c + 1, n - 1)] * frac
    samp = np.where(inside, samp, np.nan)
    rho = np.full(cands.size, -1.0)
    full = np.isfinite(samp).all(axis=1) & bool(np.isfinite(h).all()) & (s.size >= 4)
    if full.any():                   # every point on data: all such candidates at once
        a = detrend(h, s)
        xc = s - s.mean()
        r = samp[full] - samp[full].mean(axis=1, keepdims=True)
        den = float(xc @ xc)
        b = r - np.outer(r @ xc / den, xc) if den > 0 else r
        norm = np.sqrt(float(a @ a) * np.einsum('ij,ij->i', b, b))
        rho[full] = np.where(norm > 0, (b @ a) / np.where(norm > 0, norm, 1.0), 0.0)
    for j in np.flatnonzero(~full):
        ok = np.isfinite(samp[j]) & np.isfinite(h)
        if ok.sum() < max(4, 0.8 * s.size):
            continue
        a = detrend(h[ok], s[ok])
        b = detrend(samp[j][ok], s[ok])
        den = math.sqrt(float(a @ a) * float(b @ b))
        rho[j] = float(a @ b) / den if den > 0 else 0.0
    best = int(np.argmax(rho))
    if rho[best] <= -1.0:
        return Match(center_m, -1.0, math.inf, 0, False)
    offset, peak, width = float(cands[best]), float(rho[best]), math.inf
    if 0 < best < cands.size - 1 and rho[best - 1] > -1 and rho[best + 1] > -1:
        y0, y1, y2 = rho[best - 1], rho[best], rho[best + 1]
        curv = y0 - 2 * y1 + y2                      # < 0 at a peak
        if curv < 0:
            d = 0.5 * (y0 - y2) / curv
            offset += d * step_m
            peak = float(y1 - 0.25 * (y0 - y2) * d)
            a2 = -curv / (2 * step_m ** 2)           # ρ ≈ peak − a2·(δ − δ*)²
            width = math.sqrt(max(1.0 - peak, 1e-6) / a2)
    ok = np.isfinite(h)
    return Match(offset, min(peak, 1.0), width, int(ok.sum()),
                 best in (0, cands.size - 1))


__all__ = ['HIGHPASS_M', 'gaussian_lowpass', 'highpass', 'detrend', 'Match', 'match']
