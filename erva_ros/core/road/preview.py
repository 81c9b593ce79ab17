"""Preview error model: what an imperfect road-preview estimator delivers (paper §IV.B).

The paper assumes the road ahead is known "using methods in [profile1, profile2]"
and does not model the estimate's error.  :class:`PreviewErrorModel` degrades a
perfect preview vector p[k] = w(t + k·Ts), k = 0..N, in two documented ways:

* **delay** ``delay_s``: the estimate is ``delay_s`` old, so the value reported for
  t + k·Ts is really w(t + k·Ts − delay_s); the vector is shifted by delay_s/Ts
  samples (linear interpolation between elements, the first element held where the
  shift runs past the start).
* **noise** ``snr_db``: independent Gaussian errors on p[1..N] with standard
  deviation rms(p)/10^(SNR/20), where rms(p) is the RMS of the (delayed) preview
  vector itself (``signal_rms_m`` fixes it instead).  p[0], the height measured now
  at the tyre, is kept.

The noise is a pure function of (seed, t): calling ``apply`` twice for the same
sample time gives the same vector, so offline and lock-step runs agree.
"""

from dataclasses import dataclass
import math
from typing import Optional

import numpy as np


@dataclass(frozen=True)
class PreviewErrorModel:
    """Noise at ``snr_db`` (None: none) and a ``delay_s`` on a preview sampled at ``ts``."""

    snr_db: Optional[float] = None
    delay_s: float = 0.0
    seed: int = 0
    ts: float = 0.02
    signal_rms_m: Optional[float] = None

    def __post_init__(self):
        if self.snr_db is not None and not math.isfinite(self.snr_db):
            raise ValueError(f'preview snr_db must be finite, got {self.snr_db}')
        if not (math.isfinite(self.delay_s) and self.delay_s >= 0):
            raise ValueError(f'preview delay_s must be >= 0, got {self.delay_s}')
        if not self.ts > 0:
            raise ValueError(f'preview ts must be > 0, got {self.ts}')

    @property
    def is_perfect(self) -> bool:
        """Return True when the model changes nothing."""
        return self.snr_db is None and self.delay_s == 0

    def apply(self, preview: np.ndarray, t: float) -> np.ndarray:
        """Return the degraded copy of ``preview`` (m) for sample time ``t`` (s)."""
        p = np.array(preview, dtype=float).ravel()
        if self.delay_s > 0:
            idx = np.arange(p.size) - self.delay_s / self.ts
            p = np.interp(idx, np.arange(p.size), p)  # holds p[0] for negative indices
            p[0] = preview[0]
        if self.snr_db is not None and p.size > 1:
            rms = self.signal_rms_m
            if rms is None:
                rms = float(np.sqrt(np.mean(np.square(p))))
            sigma = rms / 10 ** (self.snr_db / 20)
            # Seeded by (seed, sample index): deterministic for a given t.
            k = int(round(t / self.ts * 1000))
            rng = np.random.default_rng([int(self.seed) & 0xFFFFFFFF, k & 0xFFFFFFFFFFFF])
            p[1:] = p[1:] + sigma * rng.standard_normal(p.size - 1)
        return p


__all__ = ['PreviewErrorModel']
