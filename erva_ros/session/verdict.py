"""The real-time verdict of an `erva run` session: a WARN line per way it fell short.

A run can finish, record everything and stop cleanly, and still not have been real
time: deadlines missed, the controller without a state, road samples skipped by a late
timer, a long pause between commands.  Each, above its threshold (config/session.yaml,
``erva_run``), is one warning with the count and the worst instance (when it happened,
from the first state); with ``--strict`` the warnings fail the run (exit 1).
Lock-step sessions run on simulated time: nothing here applies to them.
"""

from typing import Any, Dict, List, Mapping, Optional, Tuple


def _worst(pairs: List[Tuple[float, int]], t0: int) -> Optional[str]:
    """Return 'X ms at t = Y s' of the largest (value_s, at_ns) pair (None if none)."""
    if not pairs:
        return None
    value, at = max(pairs, key=lambda p: (p[0], -p[1]))     # the first of the worst
    return f'{value * 1e3:.0f} ms at t = {(at - t0) * 1e-9:.2f} s'


def warnings(obs, summary: Mapping[str, Any], limits: Mapping[str, Any]) -> List[str]:
    """Return the real-time warnings of a realtime session (see the module doc).

    ``obs`` is the session's Observations (decoded), ``summary`` its figures.
    """
    out: List[str] = []
    t0 = min(obs.state_rx.values()) if obs.state_rx else 0    # arrivals: from the first state's
    s0 = min(obs.states) if obs.states else 0                 # stamps: from its sample
    nmpc, road = summary.get('nmpc') or {}, summary.get('road') or {}
    late = [((rx - stamp) * 1e-9, stamp) for stamp, rx, _ in obs.commands
            if stamp in obs.states]
    misses = nmpc.get('deadline_misses') or 0
    if misses > limits['max_deadline_misses']:
        out.append(f'{misses} missed deadline{"s" if misses != 1 else ""} (worst sample -> '
                   f'command {_worst(late, s0)})')
    outages = nmpc.get('state_timeouts') or 0
    if outages > limits['max_state_timeouts']:
        rx = sorted(obs.state_rx.values())
        gaps = [((b - a) * 1e-9, a) for a, b in zip(rx, rx[1:])]
        out.append(f'{outages} state timeout{"s" if outages != 1 else ""}: the controller '
                   f'sent passive commands (longest pause between states {_worst(gaps, t0)})')
    skipped = road.get('samples_skipped') or 0
    if skipped > limits['max_skipped_road_samples']:
        stamps = sorted(obs.heights)
        gaps = [((b - a) * 1e-9, a) for a, b in zip(stamps, stamps[1:])]
        out.append(f'{skipped} road sample{"s" if skipped != 1 else ""} skipped by a late '
                   f'timer (widest gap {_worst(gaps, s0)})')
    rx = sorted(rx for stamp, rx, _ in obs.commands)
    gaps = [((b - a) * 1e-9, a) for a, b in zip(rx, rx[1:])]
    over = [g for g in gaps if g[0] > limits['max_command_gap_s']]
    if over:
        out.append(f'{len(over)} pause{"s" if len(over) != 1 else ""} between commands over '
                   f'{limits["max_command_gap_s"] * 1e3:.0f} ms (longest {_worst(over, t0)})')
    return out


def quality_limits(overrides: Optional[Mapping[str, Any]] = None) -> Dict[str, Any]:
    """Return the thresholds: config/session.yaml's ``erva_run``, then ``overrides``."""
    from erva_ros.core.node_params import QUALITY
    from erva_ros.core.specs import check_all
    return check_all(QUALITY.specs(), dict(overrides or {}), 'erva run', QUALITY.defaults())


__all__ = ['warnings', 'quality_limits']
