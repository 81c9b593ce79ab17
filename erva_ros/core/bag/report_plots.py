"""Figures of ``erva report`` (matplotlib, no backend chosen); kept apart from their data."""

import os
from typing import List

import numpy as np

from erva_ros.core.plots import save, subplots


def _t(series, t0_ns: int) -> np.ndarray:
    return (series.stamp_ns - t0_ns) * 1e-9


def _is_number(text) -> bool:
    try:
        return np.isfinite(float(text))
    except (TypeError, ValueError):
        return False


def _save(fig, path: str) -> str:
    return save(fig, path)


def _empty(ax, what: str) -> None:
    ax.text(0.5, 0.5, f'no {what} in this bag', ha='center', va='center',
            transform=ax.transAxes, color='grey')


def write_all(data, out_dir: str, timing: bool = True, actual=None) -> List[str]:
    """Write acceleration, damping command, power, road/preview, prediction (and timing) PNGs.

    ``actual``: what happened by prediction joint name, (stamps ns, values)
    (session/bag_report.py actual_signals).
    """
    t0 = data.t0_ns
    title = os.path.basename(os.path.normpath(data.bag.bag_dir or data.bag.mcap_paths[0]))
    paths = []

    fig, ax = subplots(figsize=(8, 3.2))
    if data.accel.n:
        ax.plot(_t(data.accel, t0), data.accel.values[:, 0], lw=1)
    else:
        _empty(ax, 'sprung_accel')
    ax.set(xlabel='time (s)', ylabel='chassis acceleration z̈_s (m/s²)',
           title=f'{title}: chassis acceleration')
    ax.grid(True, alpha=0.3)
    paths.append(_save(fig, os.path.join(out_dir, 'acceleration.png')))

    fig, ax = subplots(figsize=(8, 3.2))
    if data.cmd.n:
        ax.step(_t(data.cmd, t0), data.cmd.values[:, 0] * 1e-3, where='post', lw=1)
    else:
        _empty(ax, 'damping_cmd')
    ax.set(xlabel='time (s)', ylabel='damping command c_e (kNs/m)',
           title=f'{title}: damping command (held over each period)')
    ax.grid(True, alpha=0.3)
    paths.append(_save(fig, os.path.join(out_dir, 'damping_cmd.png')))

    fig, ax = subplots(figsize=(8, 3.2))
    energy = [((log_ns - t0) * 1e-9, r.harvested_j) for log_ns, r in data.reports
              if _is_number(getattr(r, 'harvested_j', None))]
    if data.generator.n:
        t = _t(data.generator, t0)
        p = data.generator.values[:, 1] * data.generator.values[:, 2]
        ax.plot(t, p, lw=1, label='P(t_k) = effort·velocity')
        ax2 = ax.twinx()
        energy = [(te, e) for te, e in energy if t[0] - 0.1 <= te <= t[-1] + 1.0]
        if energy:
            te, e = zip(*energy)
            ax2.plot(te, e, color='tab:green', marker='o', ms=3, lw=1.2,
                     label='harvested energy (plant, exact)')
        dt = np.median(np.diff(t)) if t.size > 1 else 0.0
        ax2.plot(t, np.cumsum(p) * dt, color='tab:green', ls=':', lw=1,
                 label='Σ P(t_k)·Ts (samples only)')
        ax2.set_ylabel('harvested energy (J)', color='tab:green')
        ax2.legend(loc='lower right', fontsize=8)
        ax.legend(loc='upper left', fontsize=8)
    else:
        _empty(ax, 'generator')
    ax.set(xlabel='time (s)', ylabel='harvested power (W)', title=f'{title}: harvested power')
    ax.grid(True, alpha=0.3)
    paths.append(_save(fig, os.path.join(out_dir, 'power.png')))

    fig, ax = subplots(figsize=(8, 3.6))
    if data.road.n:
        ax.plot(_t(data.road, t0), data.road.values[:, 1] * 1e3, color='k', lw=1.2,
                label='road height at the tyre')
    if data.previews:
        n = len(data.previews)
        span = (data.preview_stamp_ns[-1] - data.preview_stamp_ns[0]) * 1e-9 if n > 1 else 0
        every = max(1, int(round(n / max(1.0, span * 2))))  # about two previews per second
        for i in range(0, n, every):
            start = (data.preview_stamp_ns[i] - t0) * 1e-9
            ax.plot(start + data.preview_dt[i], data.previews[i] * 1e3, color='tab:orange',
                    lw=0.8, alpha=0.8, label='preview' if i == 0 else None)
    if not data.road.n and not data.previews:
        _empty(ax, 'road data')
    else:
        ax.legend(loc='upper right')
    ax.set(xlabel='time (s)', ylabel='road height w (mm)', title=f'{title}: road and preview')
    ax.grid(True, alpha=0.3)
    paths.append(_save(fig, os.path.join(out_dir, 'road_preview.png')))

    paths.append(_prediction(data, actual or {}, t0, title,
                             os.path.join(out_dir, 'prediction.png')))

    if timing and data.cmd.n > 2:
        fig, (ax1, ax2) = subplots(1, 2, figsize=(9, 3.2))
        d = np.diff(np.sort(data.cmd.pub_ns)) * 1e-6
        ax1.hist(d, bins=50)
        ax1.set(xlabel='command period, publish times (ms)', ylabel='count',
                title='command period')
        lat = (data.cmd.pub_ns - data.cmd.stamp_ns) * 1e-6
        ax2.hist(lat[np.abs(lat) < 1e3], bins=50, color='tab:purple')
        ax2.set(xlabel='state stamp → command publish (ms)', title='state → command latency')
        paths.append(_save(fig, os.path.join(out_dir, 'timing.png')))
    return paths


def _prediction(data, actual, t0: int, title: str, path: str) -> str:
    """Predicted vs actual z̈_s and power: each plan's value h steps ahead at t_k + h·Ts."""
    from erva_ros.core.loop.prediction import prediction_steps
    fig, axes = subplots(2, 1, figsize=(8, 5.6), sharex=True)
    n = len(data.predictions)
    steps = prediction_steps(min((len(t) for t in data.predictions), default=1) - 1)
    ts_ns = (int(np.median(np.diff(data.prediction_stamp_ns))) if n > 1 else 0)
    for ax, name, label in zip(axes, ('sprung_accel', 'power'),
                               ('chassis acceleration z̈_s (m/s²)', 'harvested power P (W)')):
        if name in actual:
            stamps, values = actual[name]
            ax.plot((np.asarray(stamps) - t0) * 1e-9, values, color='k', lw=1.2,
                    label='actual')
        if n and name in data.prediction_names:
            col = data.prediction_names.index(name)
            for h in steps:
                t = (data.prediction_stamp_ns + h * ts_ns - t0) * 1e-9
                v = [table[h, col] for table in data.predictions]
                ax.plot(t, v, lw=0.9, alpha=0.8, label=f'predicted {h} step'
                        + ('s' if h > 1 else '') + ' ahead')
            ax.legend(loc='upper right', fontsize=8)
        else:
            _empty(ax, 'prediction')
        ax.set(ylabel=label)
        ax.grid(True, alpha=0.3)
    axes[0].set_title(f'{title}: the plans\' prediction vs what happened')
    axes[1].set_xlabel('time (s)')
    return _save(fig, path)


__all__ = ['write_all']
