"""Figures (matplotlib, off-screen).  Kept apart from the cores, as do-mpc's graphics."""

from typing import Dict, Sequence

import matplotlib

matplotlib.use('Agg')  # noqa: E402 -- select the file backend before pyplot loads
import matplotlib.pyplot as plt  # noqa: E402


def fr_figure(curves: Dict[str, object], path: str, paper_marks: Sequence[float] = ()) -> str:
    """Two-panel frequency response (acceleration, power), as paper Fig. 4."""
    fig, (ax_a, ax_p) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    styles = {'erva': ('tab:blue', 'passive ERVA'),
              'benchmark': ('tab:orange', 'linear benchmark')}
    for name, curve in curves.items():
        color, label = styles.get(name, (None, name))
        ax_a.plot(curve.freqs, curve.accel, color=color, label=label)
        ax_p.plot(curve.freqs, curve.power, color=color, label=label)
    for f in paper_marks:
        for ax in (ax_a, ax_p):
            ax.axvline(f, color='grey', lw=0.8, ls=':')
    amp_mm = next(iter(curves.values())).amplitude_m * 1e3
    ax_a.set_ylabel('chassis acceleration amplitude (m/s²)')
    ax_p.set_ylabel('mean harvested power (W)')
    ax_p.set_xlabel('road tone frequency (Hz)')
    ax_a.set_title(f'Approximate FR, road amplitude {amp_mm:g} mm (dotted: paper resonances)')
    for ax in (ax_a, ax_p):
        ax.grid(True, alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
