"""Figures of ``erva report`` (matplotlib, no backend chosen); kept apart from their data."""

import os
from typing import List, Mapping, Optional

import numpy as np

from erva_ros.core.loop.prediction import prediction_steps
from erva_ros.core.plots.figures import save, subplots


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


def write_all(data, out_dir: str, timing: bool = True, actual=None,
              deadlines: Optional[Mapping[str, float]] = None) -> List[str]:
    """Write acceleration, damping command, power, road/preview, prediction (and timing) PNGs.

    ``actual``: what happened by prediction joint name, (stamps ns, values)
    (session/bag/bag_report.py actual_signals).  ``deadlines``: the session's sample period
    ``ts`` and command delay ``d`` (s), marked on timing.png.
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

    paths.append(_road_preview(data, t0, title, os.path.join(out_dir, 'road_preview.png')))

    paths.append(_prediction(data, actual or {}, t0, title,
                             os.path.join(out_dir, 'prediction.png')))

    if timing and data.cmd.n > 2:
        paths.append(_timing(data, deadlines or {}, title, os.path.join(out_dir, 'timing.png')))
    return paths


#: Previews drawn on road_preview.png, about this many per second.
PREVIEWS_PER_S = 2


def _road_preview(data, t0: int, title: str, path: str) -> str:
    """Draw the road at the tyre with some previews over it, and each preview's error.

    A preview is the road the NMPC was given at t_k for t_k .. t_k + N·Ts: each drawn one
    starts at its dot (t_k).  Below, the preview against the road that came: its error
    one step and N steps ahead, at every t_k.
    """
    fig, (ax, ax_err) = subplots(2, 1, figsize=(8, 5.6), sharex=True,
                                 gridspec_kw={'height_ratios': [2, 1]})
    road_t = _t(data.road, t0) if data.road.n else np.zeros(0)
    road_w = data.road.values[:, 1] * 1e3 if data.road.n else np.zeros(0)
    if data.road.n:
        ax.plot(road_t, road_w, color='k', lw=1.0, zorder=3,     # over the previews
                label='road height at the tyre w(t)')
    n = len(data.previews)
    horizon = min((len(p) for p in data.previews), default=0) - 1
    if n:
        span = (data.preview_stamp_ns[-1] - data.preview_stamp_ns[0]) * 1e-9 if n > 1 else 0
        every = max(1, int(round(n / max(1.0, span * PREVIEWS_PER_S))))
        for k, i in enumerate(range(0, n, every)):
            start = (data.preview_stamp_ns[i] - t0) * 1e-9
            x, w = start + data.preview_dt[i], data.previews[i] * 1e3
            ax.plot(x, w, color='tab:orange', lw=3.0, alpha=0.7,
                    label=(f'preview made at t_k (dot): the road ahead to t_k + N·Ts, '
                           f'N = {horizon} (every {every} samples)') if k == 0 else None)
            ax.plot(x[:1], w[:1], 'o', color='tab:orange', ms=3)
    if not data.road.n and not n:
        _empty(ax, 'road data')
    else:
        ax.legend(loc='lower left', bbox_to_anchor=(0.0, 1.0), ncol=1, fontsize=8,
                  frameon=False)
    ax.set(ylabel='road height w (mm)')
    ax.set_title(f'{title}: road and preview', pad=34)
    ax.grid(True, alpha=0.3)
    errors = preview_errors(data)
    for h, (t, e) in errors.items():
        ax_err.plot(t, e, lw=1, label=f'{h} step{"s" if h > 1 else ""} ahead (max |e| '
                                      f'{np.max(np.abs(e)):.2g} mm)')
    if errors:
        ax_err.legend(loc='upper right', fontsize=8, ncol=2)
    else:
        _empty(ax_err, 'preview and road to compare')
    ax_err.axhline(0.0, color='grey', lw=0.8)
    ax_err.set(xlabel='time t_k (s)', ylabel='preview − road (mm)')
    ax_err.grid(True, alpha=0.3)
    return _save(fig, path)


def preview_errors(data):
    """Return {h: (t_k s, preview − road at t_k + h·Ts in mm)} for h = 1 and N.

    t_k counts from ``data.t0_ns``; a preview whose point has no road sample within Ts/2
    of it (past the recorded road's end) is left out.
    """
    horizon = min((len(p) for p in data.previews), default=0) - 1
    if horizon < 1 or data.road.n < 2:
        return {}
    t0 = data.t0_ns
    road_t, road_w = _t(data.road, t0), data.road.values[:, 1] * 1e3
    ts = float(np.median(np.diff(road_t)))
    out = {}
    for h in sorted({1, horizon}):
        t_k = (data.preview_stamp_ns - t0) * 1e-9
        at = np.array([t + dt[h] for t, dt in zip(t_k, data.preview_dt)])
        j = np.clip(np.searchsorted(road_t, at), 1, road_t.size - 1)
        j -= (at - road_t[j - 1]) < (road_t[j] - at)           # the nearest road sample
        ok = np.abs(road_t[j] - at) <= ts / 2
        e = np.array([p[h] * 1e3 for p in data.previews]) - road_w[j]
        if ok.any():
            out[h] = (t_k[ok], e[ok])
    return out


def _timing(data, deadlines: Mapping[str, float], title: str, path: str) -> str:
    """Command period and state → command latency, with p50 / p99 and the deadlines."""
    fig, (ax1, ax2) = subplots(1, 2, figsize=(10, 3.8))
    period = np.diff(np.sort(data.cmd.pub_ns)) * 1e-6
    lat = (data.cmd.pub_ns - data.cmd.stamp_ns) * 1e-6
    lat = lat[np.abs(lat) < 1e3]
    ts_ms = deadlines.get('ts', 0.0) * 1e3
    d_ms = deadlines.get('d', 0.0) * 1e3
    marks1 = [(ts_ms, 'Ts', 'tab:green', '-'),
              (1.5 * ts_ms, '1.5·Ts: a longer one is late', 'tab:red', '--')] if ts_ms else []
    marks2 = ([(d_ms, 'd: commands act at t_k + d', 'tab:red', '--')] if d_ms else []) + \
        ([(ts_ms, 'Ts: the next sample', 'tab:green', '-')] if ts_ms else [])
    for ax, values, color, marks, xlabel, name in (
            (ax1, period, 'tab:blue', marks1, 'command period, publish times (ms)',
             'command period'),
            (ax2, lat, 'tab:purple', marks2, 'state stamp t_k → command publish (ms)',
             'state → command latency')):
        ax.hist(values, bins=50, color=color, alpha=0.8)
        if values.size:
            for q, ls in ((50, '-'), (99, ':')):
                v = float(np.percentile(values, q))
                ax.axvline(v, color='k', ls=ls, lw=1, label=f'p{q} {v:.2f} ms')
        for x, label, c, ls in marks:
            ax.axvline(x, color=c, ls=ls, lw=1.2, label=f'{label} = {x:g} ms')
        ax.set(xlabel=xlabel, title=name)
        ax.legend(fontsize=7, loc='upper right')
        ax.grid(True, alpha=0.3)
    ax1.set_ylabel('count')
    fig.suptitle(f'{title}: timing ({data.cmd.n} commands)', fontsize=10)
    return _save(fig, path)


def _prediction(data, actual, t0: int, title: str, path: str) -> str:
    """Predicted vs actual z̈_s and power: each plan's value h steps ahead at t_k + h·Ts."""
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


__all__ = ['write_all', 'preview_errors']
