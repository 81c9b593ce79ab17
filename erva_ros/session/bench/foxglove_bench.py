"""`erva bench --live --foxglove-ab N`: the loop's timing without and with serving Foxglove.

Runs N pairs of realtime sessions (as `erva bench --live`: no recording), alternating
A = without the Foxglove server and B = `erva run --foxglove` with a viewer connected
(:mod:`erva_ros.session.bench.foxglove_viewer` in its own process, subscribed to every channel,
reading -- or, with ``--foxglove-viewer stalled``, never reading).  The order
alternates (AB, BA, AB, ...) so a load that drifts on a shared machine hits both arms
alike.  Per arm it prints the median over the runs of each run's p50 / p99 / max and the
total sample count of: command period jitter at the plant, state-to-command latency at
the plant, sample-to-command latency and solve time; deadline misses and dropped
messages summed; the load average before and after.
"""

import dataclasses
import json
import os
import statistics
import sys
from typing import Any, Dict, List

from erva_ros.session.bench.benchmark import _run_config, bench_result
from erva_ros.session.processes import ChildProcess, module_argv
from erva_ros.session.run.orchestrator import run_session
from erva_ros.session.run.report import jsonable, print_json

#: Default length of each run of the A/B (s).
DEFAULT_AB_DURATION_S = 20.0
#: The figures compared, as named in bench_result.
FIGURES = (('period_jitter_ms', 'period jitter at plant'),
           ('state_to_command_ms', 'state -> command'),
           ('sample_to_command_ms', 'sample -> command'),
           ('solve_ms', 'solve'))
ARMS = ('without', 'with')
#: What the JSON keeps of each run.
PER_RUN = ('period_jitter_ms', 'state_to_command_ms', 'solve_ms', 'deadline_misses',
           'dropped_messages', 'viewer', 'foxglove')


def _viewer(port: int, stall: bool) -> ChildProcess:
    argv = module_argv('erva_ros.session.bench.foxglove_viewer', '--port', str(port))
    return ChildProcess('viewer', argv + (['--stall'] if stall else []), capture=True)


def _one_run(cfg, arm: str, stall: bool, log) -> Dict[str, Any]:
    viewer: List[ChildProcess] = []

    def on_line(line: str) -> None:
        log(line)
        if 'Foxglove: open ws://127.0.0.1:' in line and not viewer:
            viewer.append(_viewer(int(line.split('ws://127.0.0.1:')[1].split()[0]), stall))

    run_cfg = dataclasses.replace(cfg, foxglove='127.0.0.1:0' if arm == 'with' else None)
    result = run_session(run_cfg, log=on_line)
    report = bench_result(result.summary)
    report['exit_code'] = result.exit_code
    report['foxglove'] = result.summary.get('foxglove')
    if viewer:   # it ends when the server goes away (a stalled one: stop it)
        viewer[0].stop(grace_s=0 if stall else 10, first=None)
        lines = viewer[0].output().strip().splitlines()
        report['viewer'] = json.loads(lines[-1]) if lines else None
    return report


def _aggregate(runs: List[Dict[str, Any]]) -> Dict[str, Any]:
    out: Dict[str, Any] = {'runs': len(runs)}
    for key, _ in FIGURES:
        stats = [r.get(key) or {} for r in runs]
        out[key] = {q: (statistics.median(s[q] for s in stats if s.get(q) is not None)
                        if any(s.get(q) is not None for s in stats) else None)
                    for q in ('p50', 'p99', 'max')}
        out[key]['samples'] = sum(s.get('samples') or 0 for s in stats)
    out['deadline_misses'] = sum(r.get('deadline_misses') or 0 for r in runs)
    out['dropped_messages'] = sum(r.get('dropped_messages') or 0 for r in runs)
    out['viewer_messages'] = sum(((r.get('viewer') or {}).get('total') or 0) for r in runs)
    out['errors'] = [e for r in runs for e in r.get('errors', [])]
    return out


def _fmt(stats: Dict[str, Any]) -> str:
    if not stats.get('samples'):
        return 'n/a'
    return (f'p50 {stats["p50"]:.3f}  p99 {stats["p99"]:.3f}  max {stats["max"]:.3f} ms  '
            f'({stats["samples"]} samples)')


def run_foxglove_ab(args) -> int:
    """Run the A/B for `erva bench --live --foxglove-ab N`; return the exit status."""

    def log(line):
        print(f'erva bench: {line}', file=sys.stderr, flush=True)

    if args.duration is None:
        args.duration = DEFAULT_AB_DURATION_S
    stall = args.foxglove_viewer == 'stalled'
    cfg = _run_config(args)
    load_before = [round(v, 2) for v in os.getloadavg()]
    runs: Dict[str, List[Dict[str, Any]]] = {arm: [] for arm in ARMS}
    for pair in range(args.foxglove_ab):
        for arm in (ARMS if pair % 2 == 0 else ARMS[::-1]):
            log(f'pair {pair + 1}/{args.foxglove_ab}: {arm} the Foxglove server')
            runs[arm].append(_one_run(cfg, arm, stall, log))
    result = {'duration_s': args.duration, 'pairs': args.foxglove_ab,
              'viewer': 'stalled' if stall else 'reading',
              'cpus': os.cpu_count(), 'load_avg_before': load_before,
              'load_avg_after': [round(v, 2) for v in os.getloadavg()],
              **{arm: _aggregate(runs[arm]) for arm in ARMS},
              'per_run': {arm: [{k: r.get(k) for k in PER_RUN} for r in runs[arm]]
                          for arm in ARMS}}
    if getattr(args, 'json', False):
        print_json(jsonable(result))
    else:
        print(f'erva bench --live --foxglove-ab {args.foxglove_ab}: {args.duration:g} s per run, '
              f'{result["viewer"]} viewer, {result["cpus"]} CPUs, load average '
              f'{load_before[0]:.2f} -> {result["load_avg_after"][0]:.2f} (medians over runs '
              f'of each run\'s p50/p99/max; samples summed)')
        for arm in ARMS:
            a = result[arm]
            print(f'  {arm} Foxglove ({a["runs"]} runs'
                  + (f', viewer got {a["viewer_messages"]} messages' if arm == 'with' else '')
                  + ')')
            for key, name in FIGURES:
                print(f'    {name:<24}{_fmt(a[key])}')
            print(f'    deadline misses {a["deadline_misses"]}, dropped {a["dropped_messages"]}'
                  + ''.join(f'\n    ERROR {e}' for e in a['errors']))
    failed = any(r['exit_code'] != 0 for arm in ARMS for r in runs[arm])
    return 1 if failed else 0


__all__ = ['run_foxglove_ab', 'DEFAULT_AB_DURATION_S']
