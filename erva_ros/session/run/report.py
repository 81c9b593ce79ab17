"""Text and JSON forms of a live run's summary (`erva run`, `erva bench --live`)."""

import json
import math
import sys
from typing import Any, Dict, List

from erva_ros.session.run.segments import lines as segment_lines

#: Targets of the live system (issue 4), checked by `erva bench --live`.
TARGETS = {
    'command_rate_hz': 50.0,          # = 1 / Ts, within 1 %
    'period_jitter_p99_ms': 2.0,
    'latency_p99_ms': 5.0,
    'deadline_misses': 0,
    'dropped_messages': 0,
    'late_commands_pct': 0.1,         # commands after their instant t_k + d, below
}


def jsonable(obj: Any) -> Any:
    """Return ``obj`` with NaN/inf replaced by None and numpy scalars by Python numbers."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if hasattr(obj, 'item') and not isinstance(obj, (str, bytes)):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _ms(stats: Dict[str, Any]) -> str:
    if not stats or not stats.get('samples'):
        return 'n/a'
    return (f'p50 {stats["p50"]:.2f} / p99 {stats["p99"]:.2f} / max {stats["max"]:.2f} ms '
            f'({stats["samples"]} samples)')


def _p(stats: Dict[str, Any]) -> str:
    if not stats or not stats.get('samples'):
        return 'n/a'
    return f'{stats["p50"]:.2f} / {stats["p99"]:.2f}'


def print_json(obj: Any) -> None:
    """Print ``obj`` as indented JSON on stdout (NaN refused: use :func:`jsonable` first)."""
    json.dump(obj, sys.stdout, indent=2, allow_nan=False)
    sys.stdout.write('\n')
    sys.stdout.flush()


def _actuation_lines(act: Dict[str, Any]):
    """Return the timing model's lines: commands act at t_k + d; late; the d they need."""
    pct = act.get('late_pct')
    need = act.get('smallest_delay_ms')
    lines = [f'  timing    commands act at t_k + d, d = {act["command_delay_ms"]:g} ms: late '
             f'{act.get("late")}' + ('' if pct is None else f' ({pct:.2g} %)')
             + ('' if need is None else
                f'; the smallest d with 99.9 % on time was {need:g} ms'),
             f'            sample time -> command where it acts {_ms(act.get("arrival_ms"))}']
    jitter = act.get('actuation_jitter_ms')
    lines.append('            actuation instant - (t_k + d) '
                 + (_ms(jitter) if jitter else '0 (simulated actuator: exact)'))
    return lines


def _map_line(m: Dict[str, Any]) -> str:
    """Return the summary line of the map preview (docs/road.md)."""
    return (f'  map       {m["samples"]} previews, {m["fallback_points"]} of {m["points"]} '
            f'points no-preview (before start {m["before_start_points"]}, beyond end '
            f'{m["beyond_end_points"]}, gap {m["gap_points"]}, unmatched '
            f'{m["unmatched_points"]}); {m["alignments"]} alignments, '
            f'{m["alignments_refused"]} refused, offset '
            + ('none' if m['offset_m'] is None else f'{m["offset_m"]:+.3f} m'))


def format_summary(s: Dict[str, Any]) -> str:
    """Return the human-readable summary of one run."""
    sc = s['scenario']
    m = s['metrics']
    cmd = s['commands']
    nm = s['nmpc']
    pl = s['plant']
    msg = s['messages']
    lines: List[str] = [
        f'erva run: {sc["controller"]} (alpha1 = {sc["weights"][0]:g}, alpha2 = '
        f'{sc["weights"][1]:g}), {sc["road"]} road seed {sc["seed"]}, {sc["model"]} model, '
        f'{sc["mode"]}, {sc["duration_s"]:g} s at Ts = {sc["ts"]:g} s',
    ]
    if m.get('samples'):
        lines.append(f'  comfort   chassis acceleration 2-norm {m["acc_2norm"]:.4g} m/s², '
                     f'RMS {m["acc_rms"]:.4g} m/s² ({m["samples"]} samples)'
                     + (f', continuous RMS {m["acc_rms_continuous"]:.4g} m/s²'
                        if m.get('acc_rms_continuous') else ''))
        lines.append(f'  energy    average harvested power {m["power_w"]:.4g} W '
                     f'({m["harvested_j"]:.4g} J)')
    if m.get('realtime_factor'):
        lines.append(f'  pace      {m["realtime_factor"]:.2f}x real time')
    rate = (f'{cmd["rate_hz"]:.2f} Hz' if cmd.get('rate_hz') else
            'n/a (lock-step)' if sc['mode'] == 'lockstep' else 'n/a')
    lines.append(f'  commands  {cmd["received"]} received, rate {rate}')
    if 'period_jitter_ms' in cmd:
        lines.append(f'  jitter    command period |Δt - Ts| at the plant '
                     f'{_ms(cmd["period_jitter_ms"])}')
        lines.append(f'  latency   state -> command at the plant '
                     f'{_ms(cmd["state_to_command_ms"])}')
        lines.append(f'            sample time -> command {_ms(cmd["sample_to_command_ms"])}')
    elif 'monitor' in cmd:      # HIL: no plant node; as the monitor receives them
        lines.append(f'  jitter    command period |Δt - Ts| at the monitor '
                     f'{_ms(cmd["monitor"]["period_jitter_ms"])}')
        lines.append(f'  latency   state -> command at the monitor '
                     f'{_ms(cmd["monitor"]["state_to_command_ms"])}')
        lines.append(f'            sample time -> command {_ms(cmd["sample_to_command_ms"])}')
    act = cmd.get('actuation')
    if act and act.get('command_delay_ms') is not None:
        lines.extend(_actuation_lines(act))
    lines.append(f'  solve     {_ms(nm.get("solve_ms"))}')
    lines.append(f'  deadlines {nm.get("deadline_misses")} missed; controller fallbacks: plan '
                 f'{nm.get("controller_fallback_plan")}, passive '
                 f'{nm.get("controller_fallback_passive")}; state timeouts '
                 f'{nm.get("state_timeouts")}')
    lines.extend(segment_lines(s.get('tuning')))     # the segments by parameter set, if any
    if 'hil' in s:
        lines.extend(_hil_lines(s['hil']))
    else:
        lines.append(f'  plant     u from command {pl.get("u_from_command")}, from plan '
                     f'{pl.get("u_from_plan")}, passive {pl.get("u_from_passive")}; '
                     f'late commands {pl.get("late_commands")}')
    skipped = (s.get('road') or {}).get('samples_skipped')
    if skipped:     # the real-time road timer fell behind: the plant stepped across the gap
        gaps = pl.get('road_gaps')      # HIL: no plant node, the ECU counts no gaps
        bridged = '' if gaps is None else \
            f', {gaps} gap{"" if gaps == 1 else "s"} bridged by the plant'
        lines.append(f'  road      {skipped} sample{"" if skipped == 1 else "s"} skipped '
                     f'(timer behind){bridged}')
    if (s.get('road') or {}).get('map'):
        lines.append(_map_line(s['road']['map']))
    lines.append(f'  messages  dropped {msg["dropped_total"]}, rejected {msg["rejected_total"]}')
    if s.get("scheduling"):     # what realtime_priority got each node (ros/realtime.py)
        kinds = sorted(set(s['scheduling'].values()))
        lines.append(f'  sched     {"; ".join(kinds)} '
                     f'({len(s["scheduling"])} node{"s" if len(s["scheduling"]) > 1 else ""})')
    if s.get('bag'):
        lines.append(f'  bag       {s["bag"]}')
        lines.extend(_recording_lines(s.get('recording') or {}))
    for w in s.get('warnings') or []:
        lines.append(f'  WARN      {w}')
    if s['errors']:
        for e in s['errors']:
            lines.append(f'  ERROR     {e}')
    else:
        warned = len(s.get('warnings') or [])
        lines.append(f'  ok        all nodes ran and stopped cleanly ({s["wall_time_s"]:.1f} s '
                     'wall)' + (f', with {warned} warning{"s" if warned > 1 else ""} '
                                '(--strict fails such a run)' if warned else ''))
    return '\n'.join(lines)


def _recording_lines(r: Dict[str, Any]) -> List[str]:
    if 'topics' not in r:
        return []
    known = {t: c for t, c in r['topics'].items() if c['published'] is not None}
    pub = sum(c['published'] for c in known.values())
    rec = sum(c['recorded'] for c in known.values())
    foreign = sum(c['foreign'] for c in r['topics'].values())
    line = (f'  recorded  {rec} of {pub} published messages on {len(known)} topics, '
            f'{r["lost"]} lost')
    unknown = sorted(set(r['topics']) - set(known))
    if unknown:     # a node stopped without its final report (killed): its count is unknown
        line += (f'; {sum(r["topics"][t]["recorded"] for t in unknown)} recorded on '
                 f'{", ".join(unknown)}, published unknown (no final report)')
    if foreign:
        line += f'; {foreign} foreign (stamped outside the session)'
    if r.get('lost_in_transport'):
        line += f'; the middleware reported {r["lost_in_transport"]} lost in transport'
    bag = r.get('in_bag')
    if not bag:
        return [line]
    # The count `erva bag info` gives: the loop's topics, /diagnostics and anything else.
    others = ' and '.join(f'{n} on {t}' for t, n in bag['other_topics'].items())
    return [line, f'            the bag holds {bag["messages"]} messages on {bag["topics"]} '
                  f'topics as erva bag info counts them' + (f', {others} included' if others
                                                            else '')]


def _hil_lines(h: Dict[str, Any]) -> List[str]:
    br, ecu, est, lat = h['bridge'], h['ecu'], h['estimator'], h['latency_ms']
    nis = est.get('nis_mean')
    drops = '/'.join(str(br.get(f'dropped_{k}')) for k in ('crc', 'counter', 'length'))
    ecu_drops = '/'.join(str(ecu.get(f'dropped_{k}')) for k in ('crc', 'counter', 'length'))
    lines = [f'  bridge    E2E drops crc/counter/length {drops}, command timeouts '
             f'{br.get("command_timeouts")}, bus errors {br.get("bus_errors")}; ECU drops '
             f'{ecu_drops}, overruns {ecu.get("overruns")}',
             f'            ROS -> CAN {_ms(lat["bridge_ros_to_can"])}',
             f'            CAN -> ROS {_ms(lat["bridge_can_to_ros"])}',
             f'  estimator {_ms(lat["estimator"])}; NIS mean '
             f'{nis if nis is None else format(nis, ".2f")}']
    chain = h.get('chain_ms') or {}
    if chain:       # each stage as time since the sample instant t_k (hil_summary.CHAIN)
        lines.append(f'  chain     from the sample t_k, p50 / p99 ms: sensors on CAN '
                     f'{_p(chain.get("sensors_on_can"))}, at the estimator '
                     f'{_p(chain.get("measurements_at_estimator"))}, state published '
                     f'{_p(chain.get("state_published"))},')
        offset = h.get('stamp_offset_ms', 0.0)
        stamps = ('' if offset == 0 else '; the state\'s stamps: not paired with t_k'
                  if offset is None else f'; the state\'s stamps: t_k + {offset:.2f} ms')
        lines.append(f'            command on CAN {_p(chain.get("command_on_can"))}, applied '
                     f'by the ECU {_p(chain.get("command_applied"))}{stamps}')
    err = est.get('error') or {}
    if err.get('matched'):
        rel = ', '.join(f'{k} {v:.0%}' for k, v in err['relative_rms'].items()
                        if v is not None)
        hidden = err.get('not_observable')
        lines.append(f'            error RMS / its RMS vs the ECU\'s truth: {rel} '
                     f'({err["matched"]} samples'
                     + (f'; {", ".join(hidden)} not observable with the road estimated)'
                        if hidden else ')'))
    return lines


__all__ = ['TARGETS', 'jsonable', 'print_json', 'format_summary']
