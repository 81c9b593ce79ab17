"""Shared fixtures: an isolated ROS 2 environment per test run, and the erva CLI runner."""

import os
import subprocess
import sys

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _domain_id() -> int:
    """Return this test process's DDS domain: its own, so parallel runs never cross.

    ERVA_TEST_DOMAIN_ID=D[,D2,...] gives the domains: D to the run (or to pytest-xdist's
    worker gw0), D2 to worker gw1, and so on.  Otherwise, and for workers beyond the list,
    one in 1..101 (clear of the default 0; Fast DDS allows up to 232 on localhost) from
    the pid of the run -- the workers' parent -- plus the worker's number, so the
    workers of one run never share one.
    """
    worker = os.environ.get('PYTEST_XDIST_WORKER')          # gw0, gw1, ... under xdist
    k = int(worker[2:]) if worker else 0
    given = [d for d in os.environ.get('ERVA_TEST_DOMAIN_ID', '').split(',') if d.strip()]
    if k < len(given):
        return int(given[k])
    return 1 + ((os.getppid() if worker else os.getpid()) + k) % 101


ROS_DOMAIN_ID = _domain_id()
#: The domain of a test without the ``ros`` marker: erva refuses it, with one line, before
#: it starts DDS (Fast DDS could not create a participant there: its ports would pass
#: 65535).  So a test that starts an erva process or node without the marker fails, and
#: ``-m "not ros"`` never starts DDS unseen.  An rclpy node the test creates itself is
#: refused by _refuse_nodes_without_the_marker.
NO_DDS_DOMAIN = 233


def ros_env(extra=None):
    """Environment for child processes: local-only discovery, this run's domain."""
    env = dict(os.environ)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['ROS_DOMAIN_ID'] = os.environ['ROS_DOMAIN_ID']     # this test's: pytest_runtest_setup
    env['PYTHONUNBUFFERED'] = '1'
    env['MPLBACKEND'] = 'Agg'
    env.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    pp = env.get('PYTHONPATH', '')
    env['PYTHONPATH'] = REPO + (os.pathsep + pp if pp else '')
    if extra:
        env.update(extra)
    return env


# This process too (tests that create rclpy nodes in-process).
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ['ROS_DOMAIN_ID'] = str(ROS_DOMAIN_ID)
os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)
os.environ.setdefault('MPLBACKEND', 'Agg')


def _refuse_nodes_without_the_marker():
    """Make an rclpy node created in this process raise while a test without ``ros`` runs.

    (Fast DDS would end the process in NO_DDS_DOMAIN, taking the worker with it.)
    """
    try:
        from rclpy.node import Node
    except ImportError:         # the runtime install without the ROS wheels: no nodes
        return
    init = Node.__init__

    def guarded(self, *args, **kwargs):
        if os.environ.get('ROS_DOMAIN_ID') == str(NO_DDS_DOMAIN):
            raise RuntimeError('this test creates an rclpy node: mark it @pytest.mark.ros '
                               '(docs/tests.md)')
        init(self, *args, **kwargs)
    Node.__init__ = guarded


_refuse_nodes_without_the_marker()


def pytest_runtest_setup(item):
    """Give the test its domain: the run's with the ``ros`` marker, else NO_DDS_DOMAIN.

    Set before the test's fixtures (a module's too), for this process and, by ros_env,
    every process a test starts.
    """
    ros = item.get_closest_marker('ros') is not None
    os.environ['ROS_DOMAIN_ID'] = str(ROS_DOMAIN_ID if ros else NO_DDS_DOMAIN)


def pytest_collection_modifyitems(config, items):
    """Put the files with slow tests first (stable otherwise).

    With two workers the suite ends when the last file does: a minute-long test must not
    start last.  (pytest-xdist's loadfile hands out files in the order of their first test.)
    """
    items.sort(key=lambda item: item.get_closest_marker('slow') is None)


def fifo_permitted(priority: int = 20) -> bool:
    """Return whether this kernel lets a process take SCHED_FIFO (asked, not assumed)."""
    probe = f'import os; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param({priority}))'
    return subprocess.run([sys.executable, '-c', probe], capture_output=True).returncode == 0


def run_erva(*args, timeout=300, env=None, check=False):
    """Run ``erva ARGS`` as a user would (python -m erva_ros.cli), capture output."""
    proc = subprocess.run([sys.executable, '-m', 'erva_ros.cli', *map(str, args)],
                          capture_output=True, text=True, timeout=timeout,
                          env=ros_env(env), cwd=REPO)
    if check and proc.returncode != 0:
        raise AssertionError(f'erva {" ".join(map(str, args))} failed ({proc.returncode}):\n'
                             f'{proc.stdout}\n{proc.stderr}')
    return proc


@pytest.fixture
def erva():
    return run_erva


@pytest.fixture(scope='session')
def repo_root():
    return REPO


@pytest.fixture(scope='session', autouse=True)
def compiled_functions():
    """Compile the shipped configurations' functions once, before any test starts a node.

    On an empty cache (ERVA_CACHE_DIR, a fresh machine) a node compiling its solver
    itself took up to a minute, beyond other nodes' start-up timeouts; `erva compile`
    does it up front (both xdist workers call it: the second waits for the first's
    libraries, and on a warm cache it returns at once).  A failed compile is not a test
    failure (codegen: auto runs the functions uncompiled): its line is shown.
    """
    proc = run_erva('compile', '--json', timeout=1800)
    if proc.returncode != 0:
        import warnings
        warnings.warn(f'erva compile failed ({proc.returncode}): '
                      f'{(proc.stderr or proc.stdout).strip()[-500:]}')


def shipped_delay_s() -> float:
    """Return the shipped command delay d (config/live.yaml), which `erva run` applies."""
    from erva_ros.core.settings.schemas import LIVE
    return float(LIVE.defaults()['command_delay_s'])


def sim_delay_args():
    """Return `erva sim`'s options for `erva run`'s default loop: d acts and is modelled."""
    d = repr(shipped_delay_s())
    return ['--actuation-delay', d, '--command-delay', d]


@pytest.fixture(scope='session')
def pg_server(tmp_path_factory):
    """Return the URI of a PostgreSQL server for the map tests (test/map_server.py).

    .ci/run's ($ERVA_TEST_PG: must answer), else a throw-away one started here, else the
    PostgreSQL cases skip with the reason.
    """
    from map_server import session_server
    yield from session_server(tmp_path_factory)
