"""Comfort and energy metrics, defined once for `erva sim`, `erva table`, `erva run` and reports.

* ``acc_2norm``: Euclidean norm of the chassis-acceleration samples at the control
  period, sqrt(Σ_k z̈_s(t_k)²) in m/s² -- the paper's "2-norm" (§IV.B).  It grows with
  the number of samples, so only runs of equal length and Ts are compared by it.
* ``acc_rms``: sqrt(mean_k z̈_s(t_k)²), m/s², length-independent.
* ``power_w``: average harvested power E_h / T in W, with E_h integrated by the plant.
"""

from typing import Dict, Sequence

import numpy as np


def comfort_power(sprung_accel: Sequence[float], harvested_j: float,
                  duration_s: float) -> Dict[str, float]:
    a = np.asarray(sprung_accel, dtype=float)
    return {
        'acc_2norm': float(np.sqrt(np.sum(a ** 2))),
        'acc_rms': float(np.sqrt(np.mean(a ** 2))) if a.size else float('nan'),
        'power_w': float(harvested_j / duration_s) if duration_s > 0 else float('nan'),
    }


def evaluation_objective(metrics: Dict, alpha) -> float:
    """Return J(α) = α1·acc_rms² − α2·P_avg of a run (what the clairvoyant bound minimises)."""
    return float(alpha[0] * metrics['acc_rms'] ** 2 - alpha[1] * metrics['power_w'])


def percentiles_ms(samples_s: Sequence[float]) -> Dict[str, float]:
    """p50 / p99 / max in milliseconds, and the sample count, of durations given in seconds."""
    s = np.asarray(samples_s, dtype=float) * 1e3
    if s.size == 0:
        return {'p50': float('nan'), 'p99': float('nan'), 'max': float('nan'), 'samples': 0}
    return {'p50': float(np.percentile(s, 50)), 'p99': float(np.percentile(s, 99)),
            'max': float(np.max(s)), 'samples': int(s.size)}
