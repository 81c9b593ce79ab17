"""The resident memory of a session's processes over time (VmRSS from /proc), per node.

:class:`RssTrace` samples, every ``period_s``, the VmRSS of a process (an `erva run`)
and of each of its children (the nodes it started), named by what they run
(``python -m erva_ros.nodes.nmpc_node`` -> ``nmpc_node``, ``erva_ros.cli ecu-sim`` ->
``ecu_sim``).  :meth:`RssTrace.summary` gives each one's growth after a settling time
(start-up allocations, the first seconds of DDS traffic), which a week-long run on a
vehicle PC multiplies.  Linux only (no /proc: an empty trace).
"""

import os
import threading
import time
from typing import Dict, List, Optional, Tuple

#: The name of the supervising process itself in a trace.
ROOT = 'erva_run'


def vm_rss_kb(pid: int) -> Optional[int]:
    """Return a process's resident set size (kB, VmRSS of /proc/<pid>/status), None if gone."""
    try:
        with open(f'/proc/{pid}/status', encoding='ascii', errors='replace') as fh:
            for line in fh:
                if line.startswith('VmRSS:'):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None     # a zombie has no VmRSS


def children(pid: int) -> List[int]:
    """Return the pids of the children of ``pid`` (the parent field of /proc/*/stat)."""
    out: List[int] = []
    for entry in os.listdir('/proc') if os.path.isdir('/proc') else ():
        if not entry.isdigit():
            continue
        try:
            with open(f'/proc/{entry}/stat', encoding='ascii', errors='replace') as fh:
                stat = fh.read()
            # pid (comm) state ppid ...: comm may hold spaces and parentheses.
            if int(stat[stat.rindex(')') + 2:].split()[1]) == pid:
                out.append(int(entry))
        except (OSError, ValueError, IndexError):
            continue
    return out


def process_name(pid: int) -> str:
    """Return what a process runs: a ``-m`` module's last part, an erva command, or argv[0]."""
    try:
        with open(f'/proc/{pid}/cmdline', 'rb') as fh:
            argv = [a.decode(errors='replace') for a in fh.read().split(b'\0') if a]
    except OSError:
        return str(pid)
    if '-m' in argv[:-1]:
        module = argv[argv.index('-m') + 1]
        rest = argv[argv.index('-m') + 2:]
        if module == 'erva_ros.cli' and rest:
            return rest[0].replace('-', '_')
        return module.rsplit('.', 1)[-1]
    return os.path.basename(argv[0]) if argv else str(pid)


class RssTrace:
    """VmRSS of a process and its children every ``period_s`` (a thread; :meth:`stop`)."""

    def __init__(self, root_pid: int, period_s: float):
        self.root_pid = int(root_pid)
        self.period_s = float(period_s)
        #: (seconds since start, {name: kB}) per sample.
        self.samples: List[Tuple[float, Dict[str, int]]] = []
        self._stop = threading.Event()
        self._t0 = time.monotonic()
        self._names: Dict[int, str] = {}
        self._thread = threading.Thread(target=self._run, name='rss-trace', daemon=True)

    def start(self) -> 'RssTrace':
        """Start sampling (the first sample at once)."""
        self._t0 = time.monotonic()
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop sampling and wait for the thread."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def sample(self) -> Dict[str, int]:
        """Return {name: kB} now, of the root (:data:`ROOT`) and its living children."""
        out: Dict[str, int] = {}
        for pid in [self.root_pid] + children(self.root_pid):
            kb = vm_rss_kb(pid)
            if kb is None:
                continue
            if pid not in self._names:
                self._names[pid] = ROOT if pid == self.root_pid else process_name(pid)
            out[self._names[pid]] = kb
        return out

    def _run(self) -> None:
        while True:
            now = self.sample()
            if now:
                self.samples.append((round(time.monotonic() - self._t0, 2), now))
            if self._stop.wait(self.period_s):
                return

    def summary(self, settle_s: float = 60.0) -> Dict[str, Dict[str, float]]:
        """Return per process: kB at the first sample from ``settle_s`` on, at the last, growth.

        A process seen only before ``settle_s`` (a short run) counts from its first
        sample.  ``max_kb`` is over the whole trace; ``span_s`` the time the growth is over.
        """
        out: Dict[str, Dict[str, float]] = {}
        names = sorted({n for _, s in self.samples for n in s})
        for name in names:
            trace = [(t, s[name]) for t, s in self.samples if name in s]
            later = [p for p in trace if p[0] >= settle_s] or trace
            (t1, first), (t2, last) = later[0], later[-1]
            out[name] = {'first_kb': first, 'last_kb': last, 'growth_kb': last - first,
                         'max_kb': max(kb for _, kb in trace), 'from_s': t1,
                         'span_s': round(t2 - t1, 2), 'samples': len(trace)}
        return out


__all__ = ['ROOT', 'vm_rss_kb', 'children', 'process_name', 'RssTrace']
