"""The road of a car: two ISO 8608 tracks, coherent by the isotropic model, and four corners.

A car's left and right wheels run on two parallel tracks ``track_m`` apart; its rear
wheels meet the front wheels' road ``wheelbase_m`` later, i.e. delayed by
τ = wheelbase_m / speed_mps.  :func:`make_two_track_road` builds, from one seed:

* the **left track**: the single-track road of the seed, ``make_road('iso8608', ...)``
  with the same duration, ts, margin, class and speed -- the same object a quarter-car
  run of that seed drives (so a seed's left track is reproducible on its own);
* the **right track**: an ISO 8608 profile of its class whose coherence with the left
  one is the isotropic surface's (Dodds & Robson 1973; Kamash & Robson 1978; docs/model.md):
  for the ISO 8608 spectrum G_d(n) ∝ n^-2 the normalised cross-spectral density of two
  parallel tracks B apart is real and equals

      ρ(n) = 2π·n·B · K₁(2π·n·B)                     (K₁: modified Bessel function)

  and the (magnitude-squared) coherence is γ²(n) = ρ(n)².  Line by line, with the left
  track's lines A_k·e^{iφ_k} and independent phases ψ_k,

      right_k = A'_k·(ρ_k·e^{iφ_k} + √(1 − ρ_k²)·e^{iψ_k}),

  which has the expected spectrum A'_k² (the right class) and the cross-spectrum
  ρ_k·A_k·A'_k.  The ψ_k are the first draw of the seed's first child stream,
  ``SeedSequence(seed).spawn(1)[0]``, which no other road draws from;
* the **four corners** FL, FR, RL, RR as :class:`~erva_ros.core.road.profiles.Road` objects
  (``height(t)``, ``preview(t, n, ts)``, ``distance(t)``, ``times``/``heights``), so the
  closed loop, the road node and the bag tools take a corner's road as they take any road.
  FL is the left track, FR the right one; RL and RR are FL and FR delayed by τ: their grid
  nodes are the front's nodes at t + τ with the same heights (bit for bit), preceded by
  the flat approach (the front's first height, 0) from t = 0.  Between nodes both are the
  same linear interpolation.

The same seed, duration, ts, margin, classes, speed, track and wheelbase give the same
four roads wherever they are built (sim, live, studies).  As for the single-track ISO
road, the profile is synthesised over the whole grid: a longer run is another profile.
"""

from dataclasses import dataclass
import math
from typing import Dict, Optional

import numpy as np

from erva_ros.core.road.profiles import (DEFAULT_SPEED_MPS, ISO_CLASSES, iso8608_amplitudes,
                                         iso8608_lines, make_road, profile_from_lines, Road,
                                         RoadError)

#: The corners of a car, in this order everywhere (front/rear, left/right).
CORNERS = ('fl', 'fr', 'rl', 'rr')


def bessel_k1(x) -> np.ndarray:
    """Return the modified Bessel function of the second kind K₁(x) for x > 0.

    From K₁(x) = ∫₀^∞ exp(−x·cosh t)·cosh t dt by the trapezoidal rule with step 0.1:
    the integrand is analytic in the strip |Im t| < π/2 and decays double-exponentially,
    so the rule's error is below e^-40 relative (tested against tabulated values and
    against the defining integral); no SciPy here.  Evaluated in chunks of 4096 values.
    """
    x = np.asarray(x, dtype=float)
    if np.any(~np.isfinite(x)) or np.any(x <= 0):
        raise ValueError('bessel_k1 needs finite x > 0')
    flat = x.reshape(-1)
    out = np.empty_like(flat)
    for lo in range(0, flat.size, 4096):
        chunk = flat[lo:lo + 4096]
        # up to where x·cosh t > 750: the integrand is below e^-700 of its start there
        t = np.arange(0.0, math.acosh(max(750.0 / float(chunk.min()), 1.0)) + 1.0, 0.1)
        weights = np.full(t.size, 0.1) * np.cosh(t)
        weights[0] *= 0.5
        out[lo:lo + 4096] = np.exp(-np.outer(chunk, np.cosh(t))) @ weights
    return out.reshape(x.shape)


def isotropic_coherency(n, track_m: float) -> np.ndarray:
    """Return ρ(n) = 2πnB·K₁(2πnB), the normalised cross-spectrum of two tracks B apart.

    ``n`` spatial frequencies (cycle/m, ≥ 0), ``track_m`` = B (m).  ρ(0) = 1 (the long
    waves are common to both tracks); the coherence is ρ².  Valid for the ISO 8608
    spectrum's waviness w = 2 (module doc).
    """
    n = np.asarray(n, dtype=float)
    x = 2 * math.pi * np.abs(n) * float(track_m)
    out = np.ones_like(x)
    pos = x > 0
    if np.any(pos):
        out[pos] = x[pos] * bessel_k1(x[pos])
    return out


def delayed_road(front: Road, delay_s: float, name: Optional[str] = None) -> Road:
    """Return ``front`` delayed by ``delay_s`` (s): the road a rear wheel meets.

    Its nodes are the front's at t + delay_s with the same heights; before them (t <
    delay_s) the flat approach at the front's first height.  A paper road's noise-free
    preview (``preview_heights``) is delayed alike.
    """
    delay_s = float(delay_s)
    if not math.isfinite(delay_s) or delay_s <= 0:
        raise RoadError(f'rear delay {delay_s!r} s must be a positive finite number')
    times = np.concatenate(([0.0], front.times + delay_s))
    heights = np.concatenate((front.heights[:1], front.heights))
    preview = None
    if front.preview_heights is not None:
        preview = np.concatenate((front.preview_heights[:1], front.preview_heights))
    return Road(name or f'{front.name} +{delay_s:g} s', times, heights, front.speed_mps,
                preview)


@dataclass(frozen=True)
class TwoTrackRoad:
    """The four corner roads of a car on two tracks (module doc)."""

    fl: Road
    fr: Road
    rl: Road
    rr: Road
    track_m: float
    wheelbase_m: float
    seed: int

    @property
    def speed_mps(self) -> float:
        """Return the speed both tracks are driven at (m/s)."""
        return self.fl.speed_mps

    @property
    def rear_delay_s(self) -> float:
        """Return τ = wheelbase / speed (s): how much later a rear wheel meets a bump."""
        return self.wheelbase_m / self.speed_mps

    def corner(self, name: str) -> Road:
        """Return the road of corner ``name`` (one of :data:`CORNERS`)."""
        key = str(name).lower()
        if key not in CORNERS:
            raise RoadError(f'corner {name!r}; choose one of {", ".join(CORNERS)}')
        return getattr(self, key)

    def corners(self) -> Dict[str, Road]:
        """Return {corner: road} in the order of :data:`CORNERS`."""
        return {c: getattr(self, c) for c in CORNERS}

    def coherency(self, n) -> np.ndarray:
        """Return the model's ρ(n) between the left and right tracks (cycle/m)."""
        return isotropic_coherency(n, self.track_m)


def _length(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise RoadError(f'road option {name}={value!r} is not a number') from None
    if not (math.isfinite(v) and 0.1 <= v <= 10.0):
        raise RoadError(f'road option {name}={value!r} must be a length in [0.1, 10] m')
    return v


def make_two_track_road(duration_s: float, *, track_m: float, wheelbase_m: float,
                        ts: float = 0.02, seed: int = 0, road_class: str = 'C',
                        right_class: Optional[str] = None,
                        speed_mps: float = DEFAULT_SPEED_MPS,
                        margin_s: float = 5.0) -> TwoTrackRoad:
    """Build the four corner roads of a car on ISO 8608 tracks (see the module doc).

    ``road_class`` is the left track's class (A-E), ``right_class`` the right one's
    (default: the same); ``track_m`` the distance between the wheel paths and
    ``wheelbase_m`` between the axles (m), both taken from the car's parameters.
    Bad options raise :class:`RoadError` (one line).
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise RoadError(f'road seed {seed!r} must be a non-negative integer')
    track_m = _length('track_m', track_m)
    wheelbase_m = _length('wheelbase_m', wheelbase_m)
    left = make_road('iso8608', duration_s, ts, int(seed), margin_s, road_class=road_class,
                     speed_mps=speed_mps)           # validates the common options
    left_class = str(road_class).upper()
    right_class = str(left_class if right_class is None else right_class).upper()
    if right_class not in tuple(ISO_CLASSES):
        raise RoadError(f'road option right_class={right_class!r}; choose one of A, B, C, D, E')
    speed = left.speed_mps
    # the left track's own lines: make_road's generator of the seed, first draw
    lines = iso8608_lines(left.times.size, left_class, speed, np.random.default_rng(int(seed)))
    child = np.random.default_rng(np.random.SeedSequence(int(seed)).spawn(1)[0])
    psi = child.uniform(0.0, 2 * math.pi, lines.n.size)
    rho = np.zeros_like(lines.n)     # only lines the profile has (amp > 0) need it
    has = lines.amp > 0
    rho[has] = isotropic_coherency(lines.n[has], track_m)
    phasor = rho * np.exp(1j * lines.phase) + np.sqrt(1.0 - rho ** 2) * np.exp(1j * psi)
    right_amp = iso8608_amplitudes(left.times.size, right_class, speed)[2]
    right_h = profile_from_lines(lines, phasor, right_amp)
    name = (f'two-track iso8608-{left_class}/{right_class}({speed:g} m/s, '
            f'track {track_m:g} m, seed={seed})')
    fl = Road(f'{name} FL', left.times, left.heights, speed)
    fr = Road(f'{name} FR', left.times, right_h, speed)
    delay = wheelbase_m / speed
    return TwoTrackRoad(fl, fr, delayed_road(fl, delay, f'{name} RL'),
                        delayed_road(fr, delay, f'{name} RR'), track_m, wheelbase_m, int(seed))


__all__ = ['CORNERS', 'TwoTrackRoad', 'make_two_track_road', 'isotropic_coherency',
           'bessel_k1', 'delayed_road']
