"""Child processes of the session tools: how they are described, started and stopped.

One home for what `erva run`, `erva run --ecu virtual`, the benchmarks and the soak
test do with processes:

* :class:`ProcessSpec` -- a name, an argv and an environment (what to start);
* :func:`child_env` -- the environment every child gets (local-only discovery,
  unbuffered output, the caller's ROS_DOMAIN_ID);
* :func:`module_argv` / :func:`node_argv` -- ``python -m <module>`` command lines, a
  node's with its namespace and params files;
* :class:`ChildProcess` -- one started process in its own process group, ended by the
  kernel when its parent dies (at once; the recorder after closing its bag), its output
  in a log file, captured, or discarded;
* :func:`stop_processes` -- SIGINT, then SIGTERM, then SIGKILL after a grace period
  each (SIGUSR1 just before SIGKILL: a hung node writes its stacks), every process reaped.
"""

import ctypes
from dataclasses import dataclass, field
import functools
import os
import re
import signal
import subprocess
import sys
import time
from typing import Dict, Iterable, List, Mapping, Optional, Sequence

from erva_ros.core.settings.files import shipped_config

#: A log line that says something failed: an ERROR/FATAL log line (rclpy's format), an
#: exception's last line, or a command's one-line ``prog: error: ...``.
_ERROR_LINE = re.compile(r'^\s*\[(ERROR|FATAL)\]|^\s*[\w.]*(Error|Exception|Interrupt)\b: |'
                         r'^\s*[\w. -]+: (error|internal error): ')
#: Grace period (s) between SIGINT, SIGTERM and SIGKILL when stopping a process.
STOP_GRACE_S = 5.0
#: How long (s) a hung process gets to write its stacks (SIGUSR1) before SIGKILL.
DUMP_WAIT_S = 0.5
_SIGINT = signal.SIGINT     # (ChildProcess.signal hides the module in the class body)


@dataclass
class ProcessSpec:
    """One process to start: a name, its argv and its environment."""

    name: str
    argv: List[str]
    env: Dict[str, str] = field(default_factory=dict)


def child_env(base: Optional[Mapping[str, str]] = None, force_local: bool = False
              ) -> Dict[str, str]:
    """Return the environment of a child process (``base``: default os.environ).

    Discovery stays on this machine unless the caller set otherwise (``force_local``:
    always), output is unbuffered, so a log shows what happened up to a crash, without
    an AMENT_PREFIX_PATH the packages are looked up in this interpreter's prefix, and
    without a Fast DDS profile file of the caller's, config/fastdds_session.xml (faster
    announcements: nodes are heard as they start, final samples acknowledged at once).
    """
    env = dict(os.environ if base is None else base)
    if force_local:
        env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    else:
        env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    env['PYTHONUNBUFFERED'] = '1'
    use_session_profile(env)
    return env


def use_session_profile(env: Dict[str, str]) -> None:
    """Give ``env`` config/fastdds_session.xml unless it names a Fast DDS profile file.

    (Also for the session process itself, before its first DDS participant: it must hear
    its nodes as soon as they start.)
    """
    if not any(env.get(k) for k in PROFILE_VARIABLES):
        env[PROFILE_VARIABLES[0]] = session_profile()


#: Where Fast DDS finds an XML profile file (the name Fast DDS 2.x reads; its newer name).
PROFILE_VARIABLES = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')


def session_profile() -> str:
    """Return config/fastdds_session.xml: faster announcements (the file says which, why)."""
    return shipped_config('fastdds_session.xml')


def module_argv(module: str, *args: str) -> List[str]:
    """Return the command line of ``python -m module args...`` with this interpreter."""
    return [sys.executable, '-m', module, *args]


def node_argv(node: str, namespace: str, params_files: Sequence[str] = (),
              parameters: Optional[Mapping[str, object]] = None) -> List[str]:
    """Return the command line of ``erva_ros.nodes.<node>`` in ``namespace``.

    ``params_files`` are passed as ``--params-file`` in order, ``parameters`` as
    ``-p name:=value`` after them (booleans written as YAML true/false).
    """
    argv = module_argv(f'erva_ros.nodes.{node}', '--ros-args', '-r', f'__ns:={namespace}')
    for path in params_files:
        argv += ['--params-file', path]
    return argv + ros_params(parameters)


def ros_params(parameters: Optional[Mapping[str, object]]) -> List[str]:
    """Return ``-p name:=value`` arguments (booleans written as YAML true/false)."""
    argv: List[str] = []
    for name, value in (parameters or {}).items():
        text = ('true' if value else 'false') if isinstance(value, bool) else str(value)
        argv += ['-p', f'{name}:={text}']
    return argv


#: Children that the kernel asks to finish when their parent dies (SIGTERM): the recorder
#: closes its bag with everything it received.  Any other child is SIGKILLed at once: a
#: loop node stopping cleanly would wait for acknowledgements from peers that are gone
#: (a SCHED_FIFO plant_sim_node ran on for up to 10 s after `erva run` was killed).
FINISH_ON_PARENT_DEATH = ('recorder_node',)


def parent_death_signal(name: str) -> int:
    """Return the signal child ``name`` gets when its parent dies (FINISH_ON_PARENT_DEATH)."""
    return signal.SIGTERM if name in FINISH_ON_PARENT_DEATH else signal.SIGKILL


def _die_with_parent(sig: int, parent: int) -> None:
    """Ask the kernel to send ``sig`` to this child when its parent dies (Linux prctl)."""
    try:
        libc = ctypes.CDLL('libc.so.6', use_errno=True)
        libc.prctl(1, int(sig))         # PR_SET_PDEATHSIG
        if os.getppid() != parent:      # the parent died before the prctl: go now
            os.kill(os.getpid(), int(sig))
    except OSError:
        pass


class ChildProcess:
    """One child process in its own process group (signals reach what it started too).

    Its output goes to ``log_path`` (stdout and stderr), or is captured
    (``capture=True``: text, read while waiting, see :meth:`output`), or is discarded.
    When this process dies the kernel ends it (:func:`parent_death_signal`, or
    ``on_parent_death``), so no child outlives its parent.
    """

    def __init__(self, name: str, argv: Sequence[str], env: Optional[Mapping[str, str]] = None,
                 log_path: Optional[str] = None, capture: bool = False,
                 on_parent_death: Optional[int] = None):
        self.name = name
        self.log_path = log_path
        self._log = open(log_path, 'w', encoding='utf-8') if log_path else None
        out = (self._log if self._log else subprocess.PIPE if capture
               else subprocess.DEVNULL)
        self.popen = subprocess.Popen(list(argv), stdout=out,
                                      stderr=subprocess.STDOUT if self._log else out,
                                      stdin=subprocess.DEVNULL,
                                      env=None if env is None else dict(env),
                                      text=capture or None, start_new_session=True,
                                      preexec_fn=functools.partial(
                                          _die_with_parent,
                                          on_parent_death or parent_death_signal(name),
                                          os.getpid()))
        self.pid = self.popen.pid
        self.captured = capture
        self.stopped_by_us = False
        self._out: Optional[str] = ''
        self._err: Optional[str] = ''

    @classmethod
    def start(cls, spec: ProcessSpec, log_dir: str) -> 'ChildProcess':
        """Start ``spec`` with its output in ``log_dir/<name>.log``."""
        return cls(spec.name, spec.argv, spec.env or None,
                   os.path.join(log_dir, f'{spec.name}.log'))

    def poll(self) -> Optional[int]:
        """Return the exit status, or None while running."""
        return self.popen.poll()

    def signal(self, sig: int) -> None:
        """Send ``sig`` to the process group (the process and anything it started)."""
        try:
            os.killpg(self.pid, sig)
        except ProcessLookupError:
            pass

    def wait(self, timeout_s: float) -> Optional[int]:
        """Wait up to ``timeout_s`` for the exit (reading captured output); return the status."""
        try:
            if self.captured:
                # After a timeout, communicate() goes on where it stopped; once done it
                # returns everything (again on a later call).
                self._out, self._err = self.popen.communicate(timeout=timeout_s)
            else:
                self.popen.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            pass
        return self.popen.poll()

    def stop(self, grace_s: float = STOP_GRACE_S, first: Optional[int] = _SIGINT
             ) -> Optional[int]:
        """Stop this process (:func:`stop_processes`); ``first=None`` lets it end by itself."""
        stop_processes([self], grace_s, first)
        return self.popen.returncode

    def output(self) -> str:
        """Return the captured stdout once the process ended (captured processes)."""
        return self._out or ''

    def errors(self) -> str:
        """Return the captured stderr once the process ended."""
        return self._err or ''

    def tail(self, lines: int = 5) -> str:
        """Return the last lines of the process's log file ('' without one)."""
        if self._log is None:
            return ''
        if not self._log.closed:
            self._log.flush()
        try:
            with open(self.log_path, encoding='utf-8', errors='replace') as fh:
                return ''.join(fh.readlines()[-lines:]).rstrip()
        except OSError:
            return ''

    def cause(self, lines: int = 20) -> str:
        """Return why the process ended, as far as known ('' if not).

        Killed: 'killed by SIGKILL' (a signal from outside; its log says nothing about
        it).  Otherwise the last error among the log's last ``lines`` lines: an ERROR or
        FATAL log line, an exception's line, a command's ``prog: error: ...``.  Never any
        other log line: the last line of a log says what the process was doing, not why
        it ended.
        """
        status = self.popen.poll()
        if status is not None and status < 0:
            try:
                return f'killed by {signal.Signals(-status).name}'
            except ValueError:
                return f'killed by signal {-status}'
        errors = [line for line in self.tail(lines).splitlines() if _ERROR_LINE.search(line)]
        return errors[-1].strip() if errors else ''

    def close(self) -> None:
        """Close the log file."""
        if self._log is not None:
            self._log.close()


def stop_processes(procs: Iterable[ChildProcess], grace_s: float = STOP_GRACE_S,
                   first: Optional[int] = signal.SIGINT) -> None:
    """Stop processes with ``first`` (SIGINT), then SIGTERM, then SIGKILL; reap them all.

    Each signal goes to every process still running, and the next follows after
    ``grace_s``.  ``first=None`` gives them ``grace_s`` to end by themselves before SIGTERM.
    """
    procs = list(procs)
    for sig in (first, signal.SIGTERM, signal.SIGKILL):
        alive = [p for p in procs if p.poll() is None]
        if not alive:
            break
        if sig == signal.SIGKILL and first != signal.SIGKILL:
            # A node that is still here is hung: ask for its threads' stacks in its log
            # first (erva_ros.ros.runtime registers SIGUSR1 for that).
            for p in alive:
                p.signal(signal.SIGUSR1)
            time.sleep(DUMP_WAIT_S)
        for p in alive:
            if sig is not None:
                p.stopped_by_us = True
                p.signal(sig)
        deadline = time.monotonic() + grace_s
        for p in alive:
            p.wait(max(0.0, deadline - time.monotonic()))
    for p in procs:
        p.wait(max(grace_s, 1.0))    # reap (a killed process's output is complete then)
        p.close()


__all__ = ['STOP_GRACE_S', 'FINISH_ON_PARENT_DEATH', 'ProcessSpec', 'child_env',
           'use_session_profile', 'module_argv',
           'node_argv', 'ros_params', 'parent_death_signal', 'ChildProcess', 'stop_processes']
