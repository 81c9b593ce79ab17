"""Closed-loop figures (matplotlib, Agg): time series like paper Figs. 5-7, and the Pareto plot."""

from typing import Mapping, Sequence

import numpy as np


def _pyplot():
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def timeseries_figure(runs: Mapping[str, object], path: str, title: str = '') -> str:
    """Write road, chassis acceleration, harvested power and damping vs time; return path.

    ``runs`` maps a label to a ClosedLoopResult (paper Figs. 5-7 show the first three
    for passive, NMPC without and with preview).
    """
    plt = _pyplot()
    fig, axes = plt.subplots(4, 1, figsize=(8, 9), sharex=True)
    first = next(iter(runs.values()))
    axes[0].plot(first.t, first.w * 1e3, color='0.3')
    axes[0].set_ylabel('road z_r (mm)')
    for label, r in runs.items():
        m = r.metrics
        axes[1].plot(r.t, r.sprung_accel,
                     label=f'{label} (2-norm {m["acc_2norm"]:.2f} m/s²)')
        axes[2].plot(r.t, r.power, label=f'{label} (mean {m["power_w"]:.3f} W)')
        axes[3].step(r.t, r.u / 1e3, where='post', label=label)
    axes[1].set_ylabel('chassis z̈_s (m/s²)')
    axes[2].set_ylabel('harvested P (W)')
    axes[3].set_ylabel('damping c_e (kNs/m)')
    axes[3].set_xlabel('time (s)')
    for ax in axes[1:]:
        ax.legend(fontsize=7, loc='upper right')
        ax.grid(alpha=0.3)
    axes[0].grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def pareto_figure(curve: Sequence[dict], baselines: Sequence[dict], path: str,
                  title: str = '') -> str:
    """Write chassis-acceleration RMS vs harvested power: the NMPC sweep and baselines."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 5))
    p = np.array([c['power_w'] for c in curve])
    a = np.array([c['acc_rms'] for c in curve])
    ax.plot(p, a, 'o-', label='NMPC, α2/α1 sweep')
    for c in curve:
        ax.annotate(f'{c["ratio"]:g}', (c['power_w'], c['acc_rms']), fontsize=7,
                    textcoords='offset points', xytext=(4, 4))
    for b in baselines:
        ax.plot(b['power_w'], b['acc_rms'], 's', markersize=8, label=b['controller'])
    ax.set_xlabel('average harvested power (W)')
    ax.set_ylabel('chassis acceleration RMS (m/s²)')
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


__all__ = ['timeseries_figure', 'pareto_figure']
