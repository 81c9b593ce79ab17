"""The first run on a fresh machine: an empty solver cache, both cores busy, runs at first try.

Each session gets a new, empty ERVA_CACHE_DIR while two busy loops keep both cores
occupied (the way the README's fresh-clone runs failed: nmpc_node spent ~51 s compiling,
and another node's start-up timeout ran out).  The session's functions are compiled
by `erva run` before any node starts, with a progress line; the nodes then only load
libraries, and a second run compiles nothing.
"""

import json
import subprocess
import sys

import pytest

from conftest import run_erva, shipped_delay_s

pytestmark = [pytest.mark.ros, pytest.mark.slow]

BUSY = 'while True: pass'


@pytest.fixture
def busy_cores():
    """Keep both cores busy for the test (two `python3 -c 'while True: pass'` loops)."""
    procs = [subprocess.Popen([sys.executable, '-c', BUSY]) for _ in range(2)]
    yield
    for p in procs:
        p.kill()
        p.wait()


# The shipped loop (config/live.yaml command_delay_s > 0) builds the NMPC with a delay.
_DELAYED = ', with a command delay' if shipped_delay_s() else ''


@pytest.mark.parametrize('args, compiles', [
    (('--ecu', 'virtual'), (f'compiling the NMPC (preview, erva model{_DELAYED})',
                            "compiling the simulated ECU's plant (erva model)")),
    (('--model', 'benchmark'), (f'compiling the NMPC (preview, benchmark model{_DELAYED})',
                                'compiling the plant (benchmark model)')),
])
def test_an_empty_cache_under_load_runs_at_the_first_try(tmp_path, busy_cores, args, compiles):
    cache = tmp_path / 'cache'
    proc = run_erva('run', *args, '--duration', '2', '--json', timeout=1800,
                    env={'ERVA_CACHE_DIR': str(cache)})
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout)
    assert summary['ok'] and summary['errors'] == [], summary['errors']
    # erva run compiled first, saying so, and before any node started: the nodes loaded
    # libraries only (a node that compiles says "compiling" in its own log, not here).
    err = proc.stderr
    assert all(line in err for line in compiles), err[-3000:]
    assert max(err.index(line) for line in compiles) < err.index('started ')
    assert any(cache.glob('*.so'))
    # A second run finds everything cached: no compile line at all.
    again = run_erva('run', *args, '--duration', '1', '--json', timeout=600,
                     env={'ERVA_CACHE_DIR': str(cache)})
    assert again.returncode == 0 and 'compiling' not in again.stderr, again.stderr[-2000:]
