"""A run's segments by parameter set: from-to time, what changed, comfort and power in each.

A live parameter change (docs/live.md) takes effect at a sample; the samples from there to
the next change are one segment.  Where the sets come from:

* `erva run`: nmpc_node's reports on /diagnostics -- ``parameter_set`` (0, 1, ... as
  changes took effect), ``parameter_set_from_ns`` (the stamp of its first sample) and the
  ``live:`` values in force -- folded as they arrive (:class:`ParameterSetLog`; the node
  publishes its status at once when a set takes effect, so none is missed);
* `erva report BAG`: the same reports in the bag (:func:`bag_block`), and the bag's
  /parameter_events: when each change was accepted, and by which node;
* `erva sim --set`: the samples its schedule changed at.

Per segment, over its samples t_k: the chassis acceleration's RMS and 2-norm (z̈_s(t_k))
and the mean of P(t_k) = effort·velocity -- the power *at the samples*, not the plant's
integrated E_h/T of the whole run's ``power_w``.  With a command delay d > 0 the first
sample of a segment still has the previous set's command acting (it acts at t_k + d).
"""

from dataclasses import dataclass
import math
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from erva_ros.core import topics

from erva_ros.core.contract import CdrError, decode_parameter_event

from erva_ros.core.reports import NMPCReport


@dataclass(frozen=True)
class ParameterSet:
    """One set of live values in force from a sample on."""

    index: int                  # 0: the start's, then 1, 2, ... as changes took effect
    from_ns: int                # stamp of its first sample (0: from the start)
    values: Dict[str, Any]      # the live values in force, by name


def typed_value(text: str) -> Any:
    """Return a report's value text as a value: true/false, an int, a float, else the text."""
    if text in ('true', 'false'):
        return text == 'true'
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


class ParameterSetLog:
    """The parameter sets of a run, folded from nmpc_node's reports in arrival order."""

    def __init__(self):
        self.sets: List[ParameterSet] = []

    def add(self, report) -> None:
        """Take an NMPCReport; a new ``parameter_set`` number starts a set."""
        if not report.live:
            return
        if self.sets and report.parameter_set <= self.sets[-1].index:
            return
        self.sets.append(ParameterSet(report.parameter_set,
                                      report.parameter_set_from_ns if report.parameter_set
                                      else 0,
                                      {k: typed_value(v) for k, v in report.live.items()}))


def _fmt(value: Any) -> str:
    return f'{value:g}' if isinstance(value, float) else str(value).lower() \
        if isinstance(value, bool) else str(value)


def segments(sets: Sequence[Tuple[float, Mapping[str, Any]]], t: np.ndarray,
             accel: np.ndarray, power: np.ndarray, ts: float) -> List[Dict[str, Any]]:
    """Return the segments of ``sets`` = [(from_s, values)] over samples ``t`` (s from t_0).

    ``accel`` and ``power`` are z̈_s(t_k) and P(t_k) at ``t`` (NaN: not there).  A segment
    ends where the next begins, the last one after the last sample (t + Ts).  Its figures
    are over its samples; None where it has none.
    """
    t = np.asarray(t, dtype=float)
    accel = np.asarray(accel, dtype=float)
    power = np.asarray(power, dtype=float)
    end = (float(t[-1]) + ts) if t.size else 0.0
    out = []
    for i, (start, values) in enumerate(sets):
        stop = sets[i + 1][0] if i + 1 < len(sets) else end
        inside = (t >= start - 1e-9 * ts) & (t < stop - 1e-9 * ts)
        a, p = accel[inside], power[inside]
        a, p = a[np.isfinite(a)], p[np.isfinite(p)]
        before = sets[i - 1][1] if i else {}
        changed = {k: [before[k], v] for k, v in values.items() if i and before.get(k) != v}
        out.append({'set': i, 'from_s': round(float(start), 9), 'to_s': round(float(stop), 9),
                    'samples': int(inside.sum()), 'values': dict(values), 'changed': changed,
                    'acc_rms': float(np.sqrt(np.mean(a ** 2))) if a.size else None,
                    'acc_2norm': float(np.sqrt(np.sum(a ** 2))) if a.size else None,
                    'power_mean_w': float(np.mean(p)) if p.size else None})
    return out


def from_sets(sets: Sequence[ParameterSet], t0_ns: int, stamps_ns: np.ndarray,
              accel: np.ndarray, power: np.ndarray, ts: float) -> List[Dict[str, Any]]:
    """Return the segments of the sets a node reported, on samples stamped ``stamps_ns``."""
    starts = [(0.0 if s.index == 0 else (s.from_ns - t0_ns) * 1e-9, s.values) for s in sets]
    t = (np.asarray(stamps_ns, dtype=np.int64) - t0_ns) * 1e-9
    return segments(starts, t, accel, power, ts)


def block(segs: List[Dict[str, Any]], complete: bool = True,
          events: Optional[List[Dict[str, Any]]] = None) -> Dict[str, Any]:
    """Return the summary's ``tuning`` block: the segments (and the parameter events).

    ``complete`` false: the samples cover only the first part of the run (the monitor's
    trajectory cap), so later segments' figures cover what was kept.
    """
    out = {'sets': len(segs), 'segments': segs, 'samples_complete': complete}
    if events is not None:
        out['parameter_events'] = events
    return out


def lines(tuning: Optional[Mapping[str, Any]]) -> List[str]:
    """Return the summary's text lines of the segments (none for a run without changes)."""
    if not tuning or tuning.get('sets', 0) < 2:
        return []
    out = [f'  params    {tuning["sets"]} parameter sets (live changes); per segment the RMS '
           'of z̈_s and the mean of P at its samples']
    for seg in tuning['segments']:
        what = ', '.join(f'{k} {_fmt(old)} -> {_fmt(new)}'
                         for k, (old, new) in seg['changed'].items()) or 'start values'
        rms, p = seg['acc_rms'], seg['power_mean_w']
        figures = (f'RMS {rms:.4f} m/s², P {p:.4f} W' if rms is not None and p is not None
                   else 'no samples kept')
        out.append(f'{_INDENT}{seg["from_s"]:.3f}-{seg["to_s"]:.3f} s, {seg["samples"]} '
                   f'samples: {figures}; {what}')
    if not tuning.get('samples_complete', True):
        out.append(f'{_INDENT}(the figures cover the samples kept: the start of the run)')
    for e in tuning.get('parameter_events', []):
        changes = ', '.join(f'{k} = {_fmt(v)}' for k, v in e['changed'].items())
        out.append(f'{_INDENT}/parameter_events at {e["t_s"]:.3f} s: {e["node"]} set {changes}')
    for r in tuning.get('set', []):
        if r['accepted'] is False:
            out.append(f'{_INDENT}--set at {r["t_s"]:g} s refused: {r["reason"]}')
    return out


#: The summary's indentation of a block's further lines.
_INDENT = ' ' * 12


# -- from a bag ----------------------------------------------------------------------------
def bag_block(data) -> Dict[str, Any]:
    """Return the ``tuning`` block of a bag (erva_ros.session.bag.bag_report.SessionData).

    The sets from nmpc_node's recorded reports; the changes each accepted as
    /parameter_events recorded them (the session's namespace, from its first sample on;
    rclpy also announces every parameter as its node declares it at start-up).
    """
    log = ParameterSetLog()
    for _, report in data.reports:
        if isinstance(report, NMPCReport) and report.node.startswith(data.namespace + '/'):
            log.add(report)
    t0 = data.t0_ns
    gen = data.generator
    power = np.full(data.accel.n, math.nan)
    if gen.n and data.accel.n:
        p_of = dict(zip(gen.stamp_ns.tolist(), (gen.values[:, 1] * gen.values[:, 2]).tolist()))
        power = np.array([p_of.get(int(s), math.nan) for s in data.accel.stamp_ns])
    ts = _period(data.accel.stamp_ns)
    accel = data.accel.values[:, 0] if data.accel.n else np.zeros(0)
    segs = from_sets(log.sets, t0, data.accel.stamp_ns, accel, power, ts) if log.sets else []
    return block(segs, events=parameter_events(data.bag, data.namespace, t0))


def _period(stamps_ns: np.ndarray) -> float:
    d = np.diff(np.asarray(stamps_ns, dtype=np.int64)) * 1e-9
    d = d[d > 0]
    return float(np.median(d)) if d.size else 0.0


def parameter_events(bag, namespace: str, t0_ns: int) -> List[Dict[str, Any]]:
    """Return the changes on the bag's /parameter_events of the session's nodes, from t_0 on."""
    if topics.PARAMETER_EVENTS not in bag.topics:
        return []
    out = []
    prefix = namespace.rstrip('/') + '/'
    for m in bag.messages([topics.PARAMETER_EVENTS]):
        try:
            e = decode_parameter_event(m.data)
        except CdrError:
            continue
        # (a node announces each parameter as it declares it, before t_0: not a change)
        if e.node.startswith(prefix) and e.changed and e.stamp_ns > t0_ns:
            out.append({'t_s': (e.stamp_ns - t0_ns) * 1e-9, 'node': e.node,
                        'changed': dict(e.changed)})
    return out


__all__ = ['ParameterSet', 'ParameterSetLog', 'typed_value', 'segments', 'from_sets', 'block',
           'lines', 'bag_block', 'parameter_events']
