"""`erva bag soak`: many consecutive `erva run` sessions on a loaded machine, counted.

Each run is a real `erva run --json --record DIR` (its own processes, its own bag)
while ``busy`` processes spin (``python3 -c 'while True: pass'``, one per core by
default) at normal priority.  After each run the bag is read back with the ``mcap``
package's reader (not erva_ros's) and every topic's count is compared with what the
nodes said they published (``messages.published`` of the summary); the run's own
verdict (``recording.lost``, exit status) is kept beside it.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from typing import Callable, Dict, List, Optional

from erva_ros.session.processes import ChildProcess, stop_processes

BUSY_LOOP = 'while True: pass'


def bag_counts(bag_dir: str) -> Dict[str, int]:
    """Return the messages per topic of a bag's MCAP file (mcap's reader, no decoding)."""
    from mcap.reader import make_reader
    (name,) = [f for f in os.listdir(bag_dir) if f.endswith('.mcap')]
    counts: Dict[str, int] = {}
    with open(os.path.join(bag_dir, name), 'rb') as fh:
        for _, channel, _ in make_reader(fh).iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    return counts


def start_busy(n: int) -> List[ChildProcess]:
    """Start ``n`` busy-looping Python processes (normal priority)."""
    return [ChildProcess(f'busy{i}', [sys.executable, '-c', BUSY_LOOP]) for i in range(n)]


def stop_busy(procs: List[ChildProcess]) -> None:
    """Stop the busy loops (:func:`start_busy`)."""
    stop_processes(procs, grace_s=1.0, first=signal.SIGKILL)


def one_run(duration_s: float, record_dir: str, run_args: List[str]) -> Dict:
    """Run one `erva run`; return its exit status, accounting and the bag's own counts."""
    argv = [sys.executable, '-m', 'erva_ros.cli', 'run', '--duration', str(duration_s),
            '--record', record_dir, '--json', *run_args]
    t0 = time.monotonic()
    proc = subprocess.run(argv, capture_output=True, text=True)
    out = {'exit_status': proc.returncode, 'wall_s': round(time.monotonic() - t0, 2)}
    try:
        s = json.loads(proc.stdout)
    except ValueError:
        out['error'] = (proc.stderr.strip().splitlines() or ['no summary'])[-1]
        return out
    ns = s['scenario']['namespace'].rstrip('/')
    published = {}
    for topic, c in (s.get('recording') or {}).get('topics', {}).items():
        published[topic] = c['published']
    counts = bag_counts(s['bag']) if s.get('bag') else {}
    lost = {t: n - counts.get(t, 0) for t, n in published.items() if counts.get(t, 0) < n}
    out.update({'ok': s['ok'], 'errors': s['errors'], 'bag': s.get('bag'),
                'published': sum(published.values()),
                'in_bag': sum(counts.get(t, 0) for t in published),
                'lost': sum(lost.values()), 'lost_by_topic': lost,
                'reported_lost': (s.get('recording') or {}).get('lost'),
                'commands': s['commands']['received'], 'namespace': ns})
    return out


def soak(runs: int, duration_s: float, busy: int, run_args: List[str],
         keep_bags: Optional[str] = None,
         progress: Callable[[str], None] = lambda line: None) -> Dict:
    """Run ``runs`` sessions under ``busy`` loaders; return per-run results and totals."""
    parent = keep_bags or tempfile.mkdtemp(prefix='erva_soak_')
    loaders = start_busy(busy)
    results = []
    t0 = time.monotonic()
    try:
        for i in range(runs):
            r = one_run(duration_s, parent, run_args)
            results.append(r)
            progress(f'run {i + 1}/{runs}: exit {r["exit_status"]}, published '
                     f'{r.get("published")}, in the bag {r.get("in_bag")}, lost '
                     f'{r.get("lost")} ({r["wall_s"]:.1f} s)'
                     + (f'; {r["errors"][0]}' if r.get('errors') else ''))
            if keep_bags is None and r.get('bag'):
                shutil.rmtree(r['bag'], ignore_errors=True)
    finally:
        stop_busy(loaders)
        if keep_bags is None:
            shutil.rmtree(parent, ignore_errors=True)
    return {
        'runs': runs, 'duration_s': duration_s, 'busy_processes': busy,
        'cores': os.cpu_count(), 'run_args': run_args,
        'published': sum(r.get('published') or 0 for r in results),
        'in_bags': sum(r.get('in_bag') or 0 for r in results),
        'lost': sum(r.get('lost') or 0 for r in results),
        'runs_with_loss': sum(1 for r in results if r.get('lost')),
        'runs_failed': sum(1 for r in results if r['exit_status'] != 0),
        'wall_s': round(time.monotonic() - t0, 1),
        'per_run': results,
    }


__all__ = ['bag_counts', 'soak', 'one_run', 'start_busy', 'stop_busy']
