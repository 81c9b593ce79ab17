"""`erva bag soak`: many consecutive `erva run` sessions on a loaded machine, counted.

Each run is a real `erva run --json --record DIR` (its own processes, its own bag)
while ``busy`` processes spin (``python3 -c 'while True: pass'``, one per core by
default) at normal priority.  After each run the bag is read back with the ``mcap``
package's reader (not erva_ros's) and every topic's count is compared with what the
nodes said they published (``messages.published`` of the summary); the run's own
verdict (``recording.lost``, exit status) is kept beside it.  With an RSS trace, each
process's resident memory is sampled during the run (:mod:`erva_ros.session.bench.rss`): what a
long session grows by.
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

from mcap.reader import make_reader

from erva_ros.session.processes import ChildProcess, stop_processes
from erva_ros.session.bench.rss import RssTrace

BUSY_LOOP = 'while True: pass'


def bag_counts(bag_dir: str) -> Dict[str, int]:
    """Return the messages per topic of a bag's MCAP files (mcap's reader, no decoding).

    Every ``.mcap`` file of the directory counts: a split bag's, whether metadata.yaml
    lists them or not.
    """
    counts: Dict[str, int] = {}
    for name in sorted(f for f in os.listdir(bag_dir) if f.endswith('.mcap')):
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


def one_run(duration_s: float, record_dir: str, run_args: List[str], rss_every_s: float = 0.0,
            rss_settle_s: float = 60.0) -> Dict:
    """Run one `erva run`; return its exit status, accounting and the bag's own counts.

    ``rss_every_s`` > 0 also samples each process's VmRSS that often (``rss``: the trace
    and, per process, its growth from ``rss_settle_s`` into the run; see
    :mod:`erva_ros.session.bench.rss`).
    """
    argv = [sys.executable, '-m', 'erva_ros.cli', 'run', '--duration', str(duration_s),
            '--record', record_dir, '--json', *run_args]
    t0 = time.monotonic()
    popen = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    trace = RssTrace(popen.pid, rss_every_s).start() if rss_every_s > 0 else None
    try:
        stdout, stderr = popen.communicate()
    finally:
        if trace is not None:
            trace.stop()
    out = {'exit_status': popen.returncode, 'wall_s': round(time.monotonic() - t0, 2)}
    if trace is not None:
        out['rss'] = {'every_s': rss_every_s, 'settle_s': rss_settle_s,
                      'processes': trace.summary(rss_settle_s),
                      'trace': [{'t_s': t, **kb} for t, kb in trace.samples]}
    try:
        s = json.loads(stdout)
    except ValueError:
        out['error'] = (stderr.strip().splitlines() or ['no summary'])[-1]
        return out
    ns = s['scenario']['namespace'].rstrip('/')
    published = {}
    for topic, c in (s.get('recording') or {}).get('topics', {}).items():
        published[topic] = c['published']
    counts = bag_counts(s['bag']) if s.get('bag') else {}
    lost = {t: n - counts.get(t, 0) for t, n in published.items() if counts.get(t, 0) < n}
    files = (sum(1 for f in os.listdir(s['bag']) if f.endswith('.mcap'))
             if s.get('bag') else 0)
    out.update({'ok': s['ok'], 'errors': s['errors'], 'bag': s.get('bag'), 'bag_files': files,
                'published': sum(published.values()),
                'in_bag': sum(counts.get(t, 0) for t in published),
                'lost': sum(lost.values()), 'lost_by_topic': lost,
                'reported_lost': (s.get('recording') or {}).get('lost'),
                'commands': s['commands']['received'], 'namespace': ns})
    return out


def soak(runs: int, duration_s: float, busy: int, run_args: List[str],
         keep_bags: Optional[str] = None,
         progress: Callable[[str], None] = lambda line: None,
         rss_every_s: float = 0.0, rss_settle_s: float = 60.0) -> Dict:
    """Run ``runs`` sessions under ``busy`` loaders; return per-run results and totals.

    With ``rss_every_s`` each run has an RSS trace (:func:`one_run`), and ``rss_growth_kb``
    is each process's largest growth over the runs.
    """
    parent = keep_bags or tempfile.mkdtemp(prefix='erva_soak_')
    loaders = start_busy(busy)
    results = []
    t0 = time.monotonic()
    try:
        for i in range(runs):
            r = one_run(duration_s, parent, run_args, rss_every_s, rss_settle_s)
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
        **({'rss_growth_kb': rss_growth(results)} if rss_every_s > 0 else {}),
        'per_run': results,
    }


def rss_growth(results: List[Dict]) -> Dict[str, int]:
    """Return each process's largest RSS growth (kB) over the runs' traces."""
    out: Dict[str, int] = {}
    for r in results:
        for name, p in (r.get('rss') or {}).get('processes', {}).items():
            out[name] = max(out.get(name, p['growth_kb']), p['growth_kb'])
    return out


__all__ = ['bag_counts', 'soak', 'one_run', 'rss_growth', 'start_busy', 'stop_busy']
