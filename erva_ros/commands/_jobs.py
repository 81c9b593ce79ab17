"""Independent jobs of a study (``erva table``, ``erva pareto``): local processes or Dask.

Without ``--scheduler`` the jobs run in ``--jobs`` local worker processes (default: one
per CPU core).  With ``--scheduler ADDRESS`` they run on an existing Dask distributed
cluster (optional extra ``erva_ros[dask]``; every worker needs erva_ros installed).
Each job is a pure function of its arguments -- no wall-clock budget, no state carried
between jobs -- so the numbers do not depend on where or in which order jobs run.
"""

import os
from typing import Callable, List, Optional, Sequence

from erva_ros.commands._common import positive_int
from erva_ros.core.errors import CLIError


def default_jobs() -> int:
    """Return the default number of local worker processes (CPU cores available)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:        # not on Linux
        return max(1, os.cpu_count() or 1)


def add_jobs_options(parser, unit: str) -> None:
    """Add --jobs and --scheduler; ``unit`` names what one job computes."""
    parser.add_argument('--jobs', type=positive_int, default=None, metavar='N',
                        help=f'local worker processes, one {unit} each (default: one per '
                             f'CPU core, here {default_jobs()})')
    parser.add_argument('--scheduler', metavar='ADDRESS', default=None,
                        help='run the jobs on an existing Dask distributed cluster, e.g. '
                             'tcp://10.0.0.5:8786 (needs the extra erva_ros[dask] here and '
                             'erva_ros on every worker); same numbers as a local run')


def run_jobs(fn: Callable, jobs: Sequence, n_jobs: Optional[int] = None,
             scheduler: Optional[str] = None,
             progress: Optional[Callable[[int, int], None]] = None) -> List:
    """Return ``[fn(job) for job in jobs]``, computed locally in parallel or on Dask."""
    if scheduler:
        return _run_dask(fn, jobs, scheduler, progress)
    n_jobs = min(n_jobs or default_jobs(), len(jobs))
    results = []
    if progress:
        progress(0, len(jobs))
    if n_jobs > 1:
        import multiprocessing
        with multiprocessing.get_context('fork').Pool(n_jobs) as pool:
            for i, r in enumerate(pool.imap(fn, jobs), 1):
                results.append(r)
                if progress:
                    progress(i, len(jobs))
        return results
    for i, job in enumerate(jobs, 1):
        results.append(fn(job))
        if progress:
            progress(i, len(jobs))
    return results


def _run_dask(fn, jobs, address, progress):
    try:
        from distributed import as_completed, Client
    except ImportError:
        raise CLIError('--scheduler needs Dask: pip install "erva_ros[dask]"') from None
    try:
        client = Client(address, timeout='10s')
    except (OSError, TimeoutError, ValueError) as exc:
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise CLIError(f'--scheduler: cannot connect to {address!r}: {first}') from None
    try:
        futures = client.map(fn, list(jobs), pure=False)
        if progress:
            progress(0, len(futures))
        index = {f.key: i for i, f in enumerate(futures)}
        results = [None] * len(futures)
        for done, fut in enumerate(as_completed(futures), 1):
            results[index[fut.key]] = fut.result()
            if progress:
                progress(done, len(futures))
        return results
    finally:
        client.close()
