"""The verdict of an `erva run` session: a WARN line per way it fell short.

A run can finish, record everything and stop cleanly, and still not have been real
time: deadlines missed, the controller without a state, road samples skipped by a late
timer, a long pause between commands.  With the map's preview (``--preview map:``) it
can also have run without it: previews that fell back to the no-preview prediction,
points without a recent alignment with the map, alignments refused.  Each, above its
threshold (config/session.yaml, ``erva_run``), is one warning with the count and the
worst instance (when it happened, from the first state's stamp); with ``--strict`` the
warnings fail the run (exit 1).  Lock-step sessions run on simulated time: nothing here
applies to them.
"""

from typing import Any, Dict, List, Mapping, Optional

from erva_ros.core.settings.schemas import QUALITY
from erva_ros.core.settings.specs import check_all
from erva_ros.session.run.monitor_stats import Worst


def _worst(worst: Worst, t0: int, offset_ms: float = 0.0) -> Optional[str]:
    """Return 'X ms at t = Y s' of a series' largest value (None if it had none).

    ``offset_ms`` is added to the value: a latency timed from a state's stamp that lies
    that far after the sample instant (hil_summary.from_sample_instant).
    """
    if not worst.count:
        return None
    return (f'{worst.value_s * 1e3 + offset_ms:.0f} ms at t = '
            f'{(worst.at_ns - t0) * 1e-9:.2f} s')


def _plural(n: int, word: str) -> str:
    return f'{n} {word}{"" if n == 1 else "s"}'


def _streak(streak: Mapping[str, Any], unit: str) -> str:
    """Return 'N <unit>s in a row, t = A–B s' of a map streak of the summary."""
    return (f'{_plural(streak["count"], unit)} in a row, t = {streak["from_s"]:.2f}'
            f'–{streak["to_s"]:.2f} s')


def map_warnings(summary: Mapping[str, Any], limits: Mapping[str, Any]) -> List[str]:
    """Return the warnings of the map's preview (none without one; module doc)."""
    m = (summary.get('road') or {}).get('map')
    if not m:
        return []
    out: List[str] = []
    n = m['fallback_samples']
    if n > limits['max_preview_fallback_samples']:
        why = ', '.join(f'{m[key]} {what}' for key, what in (
            ('before_start_points', "before the map's start"),
            ('beyond_end_points', "beyond its end"), ('gap_points', 'in a gap'),
            ('unmatched_points', 'unmatched')) if m[key])
        out.append(f'{n} of {m["samples"]} map previews fell back to the no-preview '
                   f'prediction ({m["fallback_points"]} of {m["points"]} points: {why}; '
                   f'longest {_streak(m["fallback_streak"], "preview")})')
    n = m['unmatched_points']
    if n > limits['max_unmatched_preview_points']:
        out.append(f'{n} preview points unmatched: no alignment with the map accepted '
                   f'recently (longest {_streak(m["unmatched_streak"], "preview")})')
    n = m['alignments_refused']
    if n > limits['max_refused_alignments']:
        out.append(f'{n} of {_plural(m["tries"], "alignment")} with the map refused '
                   f'(longest {_streak(m["refused_streak"], "refusal")})'
                   + ('; none accepted: is the map of this road?' if not m['alignments']
                      else ''))
    return out


def warnings(obs, summary: Mapping[str, Any], limits: Mapping[str, Any]) -> List[str]:
    """Return the warnings of a realtime session (see the module doc).

    ``obs`` is the session's Observations, ``summary`` its figures.  The pauses between
    commands were counted as they came, over the Observations' ``command_gap_s``: it
    must be ``limits``' ``max_command_gap_s``.
    """
    st = obs.streams
    pauses = st.commands.pauses
    if pauses.over_s != limits['max_command_gap_s']:
        raise ValueError(f'max_command_gap_s is {limits["max_command_gap_s"]} s, the '
                         f'monitor counted pauses over {pauses.over_s} s')
    out: List[str] = []
    t0 = st.state_rx.first or 0          # arrivals: from the first state's
    s0 = st.state_stamp.first or 0       # stamps: from its sample
    nmpc, road = summary.get('nmpc') or {}, summary.get('road') or {}
    # Commands carry the state's stamp: with the road estimated, that far after t_k.
    offset_ms = (summary.get('hil') or {}).get('stamp_offset_ms') or 0.0
    misses = nmpc.get('deadline_misses') or 0
    if misses > limits['max_deadline_misses']:
        out.append(f'{misses} missed deadline{"s" if misses != 1 else ""} (worst sample -> '
                   f'command {_worst(st.commands.late, s0, offset_ms)})')
    outages = nmpc.get('state_timeouts') or 0
    if outages > limits['max_state_timeouts']:
        out.append(f'{outages} state timeout{"s" if outages != 1 else ""}: the controller '
                   f'sent passive commands (longest pause between states '
                   f'{_worst(st.state_gaps, t0)})')
    skipped = road.get('samples_skipped') or 0
    if skipped > limits['max_skipped_road_samples']:
        out.append(f'{skipped} road sample{"s" if skipped != 1 else ""} skipped by a late '
                   f'timer (widest gap {_worst(st.road_gaps, s0)})')
    if pauses.count:
        out.append(f'{pauses.count} pause{"s" if pauses.count != 1 else ""} between commands '
                   f'over {limits["max_command_gap_s"] * 1e3:.0f} ms (longest '
                   f'{_worst(pauses, t0)})')
    return out + map_warnings(summary, limits)


def quality_limits(overrides: Optional[Mapping[str, Any]] = None) -> Dict[str, Any]:
    """Return the thresholds: config/session.yaml's ``erva_run``, then ``overrides``."""
    return check_all(QUALITY.specs(), dict(overrides or {}), 'erva run', QUALITY.defaults())


__all__ = ['warnings', 'map_warnings', 'quality_limits']
