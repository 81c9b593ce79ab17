"""`erva bench --live`: measure the running live system against its real-time targets.

Runs the realtime session of `erva run` (no recording: the recorder is measured by its
own benchmark) for ``--duration`` seconds (default 60) and reports, with p50 / p99 /
max and the sample count:

* command rate (Hz) and command period jitter |Δt − Ts| where the commands are used,
  at the plant (ms); also as published by nmpc_node and as a second subscriber (the
  monitor) receives them;
* state-to-command latency: the plant publishes the state of t_k -> the command
  computed from it arrives back at the plant (ms); also as the monitor sees it; and
  sample-to-command, from the sample time t_k (the road sample's stamp), which adds
  the road -> plant message and the plant's step (ms);
* solve time of the controller (ms), deadline misses, dropped and rejected messages;
* the timing model: each command acts at t_k + d; its arrival where it acts (t_k ->
  received), the late ones, the smallest d with 99.9 % on time and, in the HIL loop
  (``--ecu virtual``: the ECU, not a plant node, applies the commands), the actuation
  jitter the simulated ECU measures (actual instant − (t_k + d));

and checks them against :data:`erva_ros.session.run.report.TARGETS` (and, in the HIL loop,
:data:`HIL_TARGETS`).  The machine is named
with its core count and load average, since the figures depend on what else runs.
"""

import os
import platform
import sys
from typing import Any, Dict, List, Optional

from erva_ros.core.controllers.settings import with_linked_iteration_cap
from erva_ros.session.run.orchestrator import run_session
from erva_ros.session.run.report import jsonable, print_json, TARGETS
from erva_ros.session.run.run_config import ensure_ecu_available, RunConfig

DEFAULT_DURATION_S = 60.0
#: The HIL loop's own target: the ECU acts at t_k + d within this (p99, issue 25).
HIL_TARGETS = {'actuation_jitter_p99_ms': 0.2}


def _run_config(args):
    overrides = {k: getattr(args, k, None)
                 for k in ('cost', 'solver', 'horizon', 'max_iter', 'u_min', 'u_max')}
    overrides = with_linked_iteration_cap({k: v for k, v in overrides.items() if v is not None})
    alpha = getattr(args, 'alpha', None)
    priority = getattr(args, 'realtime_priority', None)
    live = {} if priority is None else {'realtime_priority': priority}
    if getattr(args, 'command_delay', None) is not None:
        live['command_delay_s'] = args.command_delay
    ecu = getattr(args, 'ecu', 'none') or 'none'
    if ecu != 'none':
        ensure_ecu_available(ecu)
    return RunConfig(ecu=ecu, controller=getattr(args, 'controller', None),
                     alpha1=alpha[0] if alpha else None, alpha2=alpha[1] if alpha else None,
                     seed=getattr(args, 'seed', None), mode='realtime',
                     duration_s=getattr(args, 'duration', None) or DEFAULT_DURATION_S,
                     params_file=getattr(args, 'params', None),
                     nmpc_file=getattr(args, 'settings', None),
                     record_dir=None, settings_overrides=overrides,
                     live_overrides=live)


def bench_result(summary: Dict[str, Any], busy: int = 0) -> Dict[str, Any]:
    """Return the benchmark figures of a realtime run's summary, with the targets checked."""
    cmd = summary['commands']
    nm = summary['nmpc']
    sc = summary['scenario']
    hil = 'hil' in summary
    # Where the commands are used: the plant node, or in the HIL loop the ECU (period
    # jitter of the frames it received) and the monitor (state -> command).
    jitter = (summary['plant'].get('cmd_jitter_ms', {}) if hil
              else cmd.get('period_jitter_ms', {}))
    latency = (cmd.get('monitor', {}).get('state_to_command_ms', {}) if hil
               else cmd.get('state_to_command_ms', {}))
    # (p99.9 of the arrival: where the commands act, the plant or the ECU)
    act = dict(cmd.get('actuation', {}),
               arrival_p999_ms=summary['plant'].get('arrival_p999_ms'))
    # The ECU at d = 0 applies each frame when it arrives: no instant to be late for.
    at_arrival = hil and not (act.get('command_delay_ms') or 0) > 0
    if at_arrival:
        act.update(late=None, late_pct=None)
    measured = {
        'command_rate_hz': cmd.get('rate_hz'),
        'period_jitter_p99_ms': jitter.get('p99'),
        'latency_p99_ms': latency.get('p99'),
        'deadline_misses': nm.get('deadline_misses'),
        'dropped_messages': summary['messages']['dropped_total'],
        'late_commands_pct': act.get('late_pct'),
    }
    rate_ok = (measured['command_rate_hz'] is not None
               and abs(measured['command_rate_hz'] - 1.0 / sc['ts']) <= 0.01 / sc['ts'])
    met = {
        'command_rate_hz': rate_ok,
        'period_jitter_p99_ms': _le(measured['period_jitter_p99_ms'],
                                    TARGETS['period_jitter_p99_ms']),
        'latency_p99_ms': _le(measured['latency_p99_ms'], TARGETS['latency_p99_ms']),
        'deadline_misses': measured['deadline_misses'] == 0,
        'dropped_messages': measured['dropped_messages'] == 0,
        'late_commands_pct': (measured['late_commands_pct'] is not None
                              and measured['late_commands_pct'] < TARGETS['late_commands_pct']),
    }
    targets = dict(TARGETS)
    if at_arrival:
        del targets['late_commands_pct'], measured['late_commands_pct']
        del met['late_commands_pct']
    elif hil:
        actuation_p99 = (act.get('actuation_jitter_ms') or {}).get('p99')
        measured['actuation_jitter_p99_ms'] = actuation_p99
        met['actuation_jitter_p99_ms'] = _le(actuation_p99,
                                             HIL_TARGETS['actuation_jitter_p99_ms'])
        targets.update(HIL_TARGETS)
    load = os.getloadavg() if hasattr(os, 'getloadavg') else (float('nan'),) * 3
    return {
        'mode': 'live', 'loop': 'hil' if hil else 'full state',
        'controller': sc['controller'], 'duration_s': sc['duration_s'],
        'ts': sc['ts'], 'samples': summary['metrics'].get('samples', 0),
        'comfort': {k: summary['metrics'].get(k) for k in ('acc_2norm', 'acc_rms', 'power_w')},
        'command_rate_hz': measured['command_rate_hz'],
        'period_jitter_ms': jitter,
        'state_to_command_ms': latency,
        'sample_to_command_ms': cmd.get('sample_to_command_ms', {}),
        'actuation': act,
        'nmpc_publish_jitter_ms': nm.get('cmd_jitter_ms'),
        'monitor': cmd.get('monitor', {}),
        'solve_ms': nm.get('solve_ms'),
        'deadline_misses': measured['deadline_misses'],
        'controller_fallbacks': {'plan': nm.get('controller_fallback_plan'),
                                 'passive': nm.get('controller_fallback_passive')},
        'missed_samples': nm.get('missed_samples'),
        'plant_u_from': {k: summary['plant'].get(f'u_from_{k}')
                         for k in ('command', 'plan', 'passive')},
        'dropped_messages': measured['dropped_messages'],
        'rejected_messages': summary['messages']['rejected_total'],
        'targets': {k: {'target': targets[k], 'measured': measured[k], 'met': bool(met[k])}
                    for k in targets},
        'all_targets_met': all(met.values()),
        'machine': {'cpus': os.cpu_count(), 'load_avg_1_5_15': [round(v, 2) for v in load],
                    'python': platform.python_version(), 'platform': platform.platform()},
        'busy_processes': busy,
        'errors': summary['errors'],
    }


def _le(value, limit) -> bool:
    return value is not None and value == value and value <= limit


def _fmt(stats, p999: Optional[float] = None) -> str:
    if not stats or not stats.get('samples'):
        return 'n/a'
    tail = '' if p999 is None or p999 != p999 else f'  p99.9 {p999:.3f}'
    return (f'p50 {stats["p50"]:.3f}  p99 {stats["p99"]:.3f}{tail}  max {stats["max"]:.3f} ms  '
            f'({stats["samples"]} samples)')


def _actuation(act: Dict[str, Any], where: str) -> List[str]:
    """Return the timing model's lines: d, late commands, arrival, the d they needed."""
    if not act or act.get('command_delay_ms') is None:
        return []
    need = act.get('smallest_delay_ms')
    jitter = act.get('actuation_jitter_ms')
    pct = act.get('late_pct')
    need = 'n/a' if need is None else f'{need:g} ms'
    arrival = (f'    sample -> command {where:<10} '
               + _fmt(act['arrival_ms'], act.get('arrival_p999_ms')))
    if act['late'] is None:      # the ECU at d = 0
        return ['  commands act at arrival (d = 0: no fixed instant, no late rule); smallest '
                f'd with 99.9 % on time: {need}', arrival]
    return [f'  commands act at t_k + d = {act["command_delay_ms"]:g} ms: late {act["late"]} '
            + ('' if pct is None else f'({pct:.3g} %)') + f'; smallest d with 99.9 % on '
            f'time: {need}', arrival,
            '    actuation - (t_k + d)       '
            + (_fmt(jitter) if jitter else '0 (simulated actuator: exact)')]


def format_bench(r: Dict[str, Any]) -> str:
    """Return the human-readable benchmark report."""
    rate = r['command_rate_hz']
    hil = r.get('loop') == 'hil'
    where = 'at the ECU' if hil else 'at the plant'
    lines = [
        f'erva bench --live{" --ecu virtual" if hil else ""}: {r["controller"]}, '
        f'{r["duration_s"]:g} s realtime at '
        f'Ts = {r["ts"]:g} s, {r["machine"]["cpus"]} CPUs, load average '
        f'{r["machine"]["load_avg_1_5_15"][0]:.2f}'
        + (f', {r["busy_processes"]} busy processes' if r['busy_processes'] else '')
        + ' (machine shared: figures vary)',
        f'  comfort                 acc 2-norm {r["comfort"]["acc_2norm"]:.4g} m/s², power '
        f'{r["comfort"]["power_w"]:.4g} W' if r['comfort']['acc_2norm'] is not None else
        '  comfort                 n/a',
        f'  command rate            {rate:.3f} Hz' if rate else '  command rate            n/a',
        f'  period jitter {where:<10} {_fmt(r["period_jitter_ms"])}',
        f'    as published (NMPC)   {_fmt(r["nmpc_publish_jitter_ms"])}',
        f'    at a 2nd subscriber   {_fmt(r["monitor"].get("period_jitter_ms"))}',
        f'  state -> command        {_fmt(r["state_to_command_ms"])}'
        + (' (at the monitor)' if hil else ''),
        f'    at a 2nd subscriber   {_fmt(r["monitor"].get("state_to_command_ms"))}',
        f'  sample -> command       {_fmt(r["sample_to_command_ms"])}',
        *_actuation(r['actuation'], where),
        f'  solve                   {_fmt(r["solve_ms"])}',
        f'  deadline misses {r["deadline_misses"]}, missed samples {r["missed_samples"]}, '
        f'dropped {r["dropped_messages"]}, rejected {r["rejected_messages"]}',
        '  targets:',
    ]
    for k, t in r['targets'].items():
        m = t['measured']
        m = 'n/a' if m is None else (f'{m:.3f}' if isinstance(m, float) else m)
        lines.append(f'    {k:<22} target {t["target"]:<6} measured {m:<10} '
                     f'{"met" if t["met"] else "NOT MET"}')
    for e in r['errors']:
        lines.append(f'  ERROR {e}')
    return '\n'.join(lines)


def run_live_bench(args) -> int:
    """Run the live benchmark for `erva bench --live`; return the exit status."""
    result = run_session(_run_config(args),
                         log=lambda line: print(f'erva bench: {line}', file=sys.stderr,
                                                flush=True))
    report = bench_result(result.summary, getattr(args, 'busy', 0))
    if getattr(args, 'json', False):
        print_json(jsonable(report))
    else:
        print(format_bench(report), flush=True)
    return result.exit_code


__all__ = ['DEFAULT_DURATION_S', 'HIL_TARGETS', 'bench_result', 'format_bench', 'run_live_bench']
