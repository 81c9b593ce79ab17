"""Figures written to files (matplotlib), kept apart from the cores, as do-mpc's graphics.

Every figure is a bare :class:`matplotlib.figure.Figure` saved with ``savefig``, which
draws PNGs with Agg by itself: no pyplot, no figure registry, and no backend chosen for
the process -- importing this module (or ``erva_ros`` in a notebook) leaves the user's
matplotlib backend as it was.  :func:`subplots` and :func:`save` are what the figure
modules (this one, ``plots_closed_loop``, ``bag/report_plots``) use.
"""

from typing import Dict, Mapping, Optional, Sequence

import numpy as np


def subplots(nrows: int = 1, ncols: int = 1, figsize=None, **kw):
    """Return ``(figure, axes)`` as ``pyplot.subplots`` does, on a bare Figure."""
    from matplotlib.figure import Figure
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(nrows, ncols, **kw)


def save(fig, path: str, dpi: int = 110) -> str:
    """Lay ``fig`` out tightly and write it to ``path`` (PNG by its extension); return path."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    return path


def fr_figure(curves: Dict[str, object], path: str, paper_marks: Sequence[float] = (),
              bode: bool = False) -> str:
    """Two-panel frequency response (acceleration, power); write it to ``path``.

    Linear axes as paper Fig. 4 (amplitude in m/s², mean power in W), or with ``bode`` as
    an engineer's Bode magnitude plot: log frequency, the gain road → chassis acceleration
    |z̈_s| / |w| in dB re 1 s⁻² (20·log10) and the harvested power per squared road
    amplitude P / |w|² in dB re 1 W/m² (10·log10, a power).  Both are per unit of road
    amplitude, so they hold for any amplitude where the response is linear.
    """
    fig, (ax_a, ax_p) = subplots(2, 1, figsize=(7, 6), sharex=True)
    styles = {'erva': ('tab:blue', 'passive ERVA'),
              'benchmark': ('tab:orange', 'linear benchmark')}
    for name, curve in curves.items():
        color, label = styles.get(name, (None, name))
        accel, power = (curve.gain_db, curve.power_db) if bode else (curve.accel, curve.power)
        ax_a.plot(curve.freqs, accel, color=color, label=label)
        ax_p.plot(curve.freqs, power, color=color, label=label)
    for f in paper_marks:
        for ax in (ax_a, ax_p):
            ax.axvline(f, color='grey', lw=0.8, ls=':')
    amp_mm = next(iter(curves.values())).amplitude_m * 1e3
    if bode:
        from matplotlib.ticker import NullFormatter
        ax_p.set_xscale('log')
        freqs = np.concatenate([np.asarray(c.freqs, dtype=float) for c in curves.values()])
        ticks = [f for f in (0.1, 0.2, 0.5, 1, 2, 3, 5, 10, 20, 50, 100)
                 if freqs.min() <= f <= freqs.max()]
        ax_p.set_xticks(ticks, [f'{f:g}' for f in ticks])    # plain Hz, not 10^n
        ax_p.xaxis.set_minor_formatter(NullFormatter())
        ax_a.set_ylabel('|z̈_s| / |w| (dB re 1 s⁻²)')
        ax_p.set_ylabel('P / |w|² (dB re 1 W/m²)')
        ax_a.set_title(f'Frequency response, Bode magnitude (road amplitude {amp_mm:g} mm; '
                       'dotted: paper resonances)', fontsize=10)
    else:
        ax_a.set_ylabel('chassis acceleration amplitude (m/s²)')
        ax_p.set_ylabel('mean harvested power (W)')
        ax_a.set_title(f'Approximate FR as paper Fig. 4 (linear axes), road amplitude '
                       f'{amp_mm:g} mm (dotted: paper resonances)', fontsize=10)
    ax_p.set_xlabel('road tone frequency (Hz)')
    for ax in (ax_a, ax_p):
        ax.grid(True, which='both', alpha=0.3)
        ax.legend()
    return save(fig, path, dpi=120)


def solve_time_cdf_figure(samples_ms: Mapping[str, np.ndarray], budget_ms: float, path: str,
                          title: str = '', period_ms: Optional[float] = None) -> str:
    """Write the empirical CDF of solve times (ms, log axis) against the budget; return path.

    ``samples_ms`` maps a label (solver) to its solve times; each curve's legend gives
    p50 / p99 / max and how many solves went over ``budget_ms`` (the solver's budget, a
    slower solve counts late); ``period_ms``, the sample period, is drawn too.
    """
    fig, ax = subplots(figsize=(7.5, 4.4))
    for label, values in samples_ms.items():
        x = np.sort(np.asarray(values, dtype=float))
        x = x[np.isfinite(x)]
        if not x.size:
            continue
        y = np.arange(1, x.size + 1) / x.size
        late = int(np.sum(x > budget_ms))
        ax.step(x, y, where='post',
                label=f'{label}: p50 {np.percentile(x, 50):.2f}, p99 '
                      f'{np.percentile(x, 99):.2f}, max {x[-1]:.2f} ms; {late} of {x.size} '
                      'over budget')
    ax.axvline(budget_ms, color='tab:red', ls='--', label=f'solver budget {budget_ms:g} ms')
    if period_ms:
        ax.axvline(period_ms, color='0.3', ls=':', label=f'sample period Ts {period_ms:g} ms')
    ax.set_xscale('log')
    ax.set_ylim(0.0, 1.02)
    ax.set_xlabel('solve time (ms)')
    ax.set_ylabel('fraction of solves ≤ x')
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(fontsize=7, loc='lower right')
    if title:
        ax.set_title(title, fontsize=10)
    return save(fig, path)


__all__ = ['subplots', 'save', 'fr_figure', 'solve_time_cdf_figure']
