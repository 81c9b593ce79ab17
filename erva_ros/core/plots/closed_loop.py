"""Closed-loop figures: time series like paper Figs. 5-7, Pareto, the results table, tornado."""

from typing import Mapping, Sequence

import numpy as np

from erva_ros.core.identify.fit import PARAMETERS
from erva_ros.core.plots.figures import save, subplots
from erva_ros.core.studies.sensitivity import unit


def timeseries_figure(runs: Mapping[str, object], path: str, title: str = '') -> str:
    """Write road, chassis acceleration, harvested power and damping vs time; return path.

    ``runs`` maps a label to a ClosedLoopResult (paper Figs. 5-7 show the first three
    for passive, NMPC without and with preview).
    """
    fig, axes = subplots(4, 1, figsize=(8, 9), sharex=True)
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
    return save(fig, path)


def pareto_figure(curve: Sequence[dict], baselines: Sequence[dict], path: str,
                  title: str = '') -> str:
    """Write chassis-acceleration RMS vs harvested power: the NMPC sweep and baselines."""
    fig, ax = subplots(figsize=(6.5, 5))
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
    return save(fig, path)


#: Comfort and power panels of the table figure: (row key, axis label).
TABLE_PANELS = (('acc_2norm', 'chassis acc. 2-norm, sampled (m/s²)'),
                ('power_w', 'average harvested power (W)'))
BOUND = 'clairvoyant'


def table_figure(rows: Sequence[dict], path: str, title: str = '') -> str:
    """Write the results table as bars: comfort and power per controller, with the bound.

    One row of panels per weighting (α1, α2): each causal controller's mean ± std over
    the seeds (``erva table`` rows), the clairvoyant bound as a hatched bar and a dashed
    line across, so the gap to it is read off directly.
    """
    weights = []
    for r in rows:
        if tuple(r['weights']) not in weights:
            weights.append(tuple(r['weights']))
    fig, axes = subplots(len(weights), len(TABLE_PANELS), squeeze=False,
                         figsize=(10, 2.9 * len(weights) + 0.6))
    for i, alpha in enumerate(weights):
        mine = [r for r in rows if tuple(r['weights']) == alpha]
        names = [r['controller'] for r in mine]
        for j, (key, label) in enumerate(TABLE_PANELS):
            ax = axes[i][j]
            mean = [r[key]['mean'] if r[key] else np.nan for r in mine]
            std = [r[key]['std'] if r[key] else 0.0 for r in mine]
            colors = ['0.85' if n == BOUND else f'C{k}' for k, n in enumerate(names)]
            bars = ax.bar(range(len(names)), mean, yerr=std, capsize=3, color=colors,
                          edgecolor='0.2')
            for n, bar in zip(names, bars):
                if n == BOUND:
                    bar.set_hatch('//')
                    ax.axhline(bar.get_height(), color='0.2', ls='--', lw=0.9,
                               label='clairvoyant (the bound on J)')
            ax.set_xticks(range(len(names)))
            ax.set_xticklabels(names, rotation=20, fontsize=8)
            ax.set_ylabel(label, fontsize=8)
            ax.set_title(f'(α1, α2) = ({alpha[0]:g}, {alpha[1]:g})', fontsize=9)
            ax.grid(axis='y', alpha=0.3)
            if BOUND in names:
                ax.legend(fontsize=7, loc='upper left')
    if title:
        fig.suptitle(title, fontsize=10)
    return save(fig, path)


def _label(row: Mapping) -> str:
    levels = ', '.join(f'{v["level"]:g}' for v in row['levels'])
    return f'{row["factor"]} ({levels} {unit(row["factor"])})'


def tornado_figure(rows: Sequence[Mapping], path: str, title: str = '') -> str:
    """Write the tornado plot: per weighting, each factor's ΔJ % at its levels, largest on top."""
    weights = []
    for r in rows:
        if r['weights'] not in weights:
            weights.append(r['weights'])
    fig, axes = subplots(1, len(weights), figsize=(6.5 * len(weights), 6), squeeze=False)
    for ax, alpha in zip(axes[0], weights):
        mine = sorted((r for r in rows if r['weights'] == alpha), key=lambda r: r['swing_pct'])
        for i, r in enumerate(mine):
            lv = [v for v in r['levels'] if v['dJ_pct'] is not None]
            lo = min(min(v['dJ_pct'] for v in lv), 0.0)
            hi = max(max(v['dJ_pct'] for v in lv), 0.0)
            ax.barh(i, hi - lo, left=lo, color='tab:blue', alpha=0.35)
            for v in lv:
                neg = v['level'] < 0 and r['factor'] in PARAMETERS
                ax.plot(v['dJ_pct'], i, 'v' if neg else '^',
                        color='tab:red' if neg else 'tab:green', ms=6)
        ax.set_yticks(range(len(mine)))
        ax.set_yticklabels([_label(r) for r in mine], fontsize=8)
        ax.axvline(0, color='k', lw=0.8)
        ax.use_sticky_edges = False       # bars stick to their ends: keep a margin
        ax.margins(x=0.05)
        ax.set_xlabel('ΔJ, % of |J nominal| (positive: worse)')
        ax.set_title(f'(α1, α2) = ({alpha[0]:g}, {alpha[1]:g})')
        ax.grid(True, axis='x', alpha=0.3)
    fig.suptitle((title + '\n' if title else '') + '▼ the model\'s parameter too low, '
                 '▲ too high (or an input error\'s level); bar: the range over the levels',
                 fontsize=9)
    return save(fig, path)


__all__ = ['timeseries_figure', 'pareto_figure', 'table_figure', 'tornado_figure']
