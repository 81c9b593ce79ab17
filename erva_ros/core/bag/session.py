"""Plain-Python helpers to start a recorded session: bag names, session metadata, recorder argv.

``erva run`` (or any launcher) typically does::

    from erva_ros.core.bag import session
    bag_dir = session.new_bag_dir('bags', 'paper')          # bags/20261122T101500Z_paper
    meta = session.session_metadata('paper', parameters={...}, seed=1, controller='preview')
    argv = [sys.executable, '-m', 'erva_ros.nodes.recorder_node',
            *session.recorder_ros_args(bag_dir, meta)]

The metadata is stored in the bag as the MCAP metadata record ``erva_session`` (and in
metadata.yaml's ``custom_data``): every value a string, structured values as JSON.
"""

import datetime
import json
import os
import platform
import re
import socket
import subprocess
import sys
from typing import Any, Dict, List, Mapping, Optional, Sequence

from erva_ros import __version__
from erva_ros.core.model.params import ParamError
from erva_ros.core.redact import redact_text

_UNSAFE = re.compile(r'[^A-Za-z0-9_.-]+')


def utc_stamp(now: Optional[datetime.datetime] = None) -> str:
    """Return the compact UTC time used in bag names, e.g. 20261122T101500Z."""
    now = now or datetime.datetime.now(datetime.timezone.utc)
    return now.astimezone(datetime.timezone.utc).strftime('%Y%m%dT%H%M%SZ')


def new_bag_dir(parent: str, scenario: str,
                now: Optional[datetime.datetime] = None) -> str:
    """Return a new, not yet existing ``parent/<UTC time>_<scenario>`` bag directory path.

    The directory is not created (the recorder creates it and refuses an existing one);
    a clash within the same second gets a ``_2``, ``_3`` ... suffix.
    """
    name = f'{utc_stamp(now)}_{_UNSAFE.sub("-", scenario).strip("-") or "session"}'
    path = os.path.join(parent, name)
    n = 2
    while os.path.exists(path):
        path = os.path.join(parent, f'{name}_{n}')
        n += 1
    return path


def git_commit(repo: Optional[str] = None) -> str:
    """Return the git commit of the source tree (with '-dirty' if modified), or ''."""
    repo = repo or os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    try:
        head = subprocess.run(['git', '-C', repo, 'rev-parse', 'HEAD'], capture_output=True,
                              text=True, timeout=5)
        if head.returncode != 0:
            return ''
        dirty = subprocess.run(['git', '-C', repo, 'status', '--porcelain',
                                '--untracked-files=no'], capture_output=True, text=True,
                               timeout=5)
        return head.stdout.strip() + ('-dirty' if dirty.stdout.strip() else '')
    except (OSError, subprocess.SubprocessError):
        return ''


def _text(value: Any) -> str:
    return value if isinstance(value, str) else json.dumps(value, sort_keys=True, default=str)


def session_metadata(scenario: str, parameters: Optional[Mapping[str, Any]] = None,
                     seed: Optional[int] = None, controller: Optional[str] = None,
                     extra: Optional[Mapping[str, Any]] = None,
                     start_time: Optional[datetime.datetime] = None) -> Dict[str, str]:
    """Return what reproduces a session, as the string map stored in the bag.

    Keys: scenario, controller, seed, parameters (JSON), erva_ros_version, git_commit,
    host, platform, python, start_time (UTC ISO 8601), command (argv) and ``extra``.
    """
    start = (start_time or datetime.datetime.now(datetime.timezone.utc)).astimezone(
        datetime.timezone.utc)
    meta: Dict[str, Any] = {
        'scenario': scenario,
        'controller': controller if controller is not None else '',
        'seed': '' if seed is None else seed,
        'parameters': dict(parameters or {}),
        'erva_ros_version': __version__,
        'git_commit': git_commit(),
        'host': socket.gethostname(),
        'platform': platform.platform(),
        'python': platform.python_version(),
        'start_time': start.isoformat(timespec='milliseconds').replace('+00:00', 'Z'),
        'command': command_line(),
    }
    meta.update(extra or {})
    return {str(k): _text(v) for k, v in meta.items()}


def stored_parameters(session: Mapping[str, str]) -> Dict[str, Any]:
    """Return the ``parameters`` a session record stores (erva, controller, live), {} if none."""
    try:
        params = json.loads(session.get('parameters', '') or '{}')
    except ValueError:
        return {}
    return params if isinstance(params, dict) else {}


def recorder_session(text: str, recorder: str, bag_dir: str,
                     extra: Optional[Mapping[str, Any]] = None) -> Dict[str, str]:
    """Return the session record of a recorder given ``session_metadata`` = ``text`` (JSON).

    The recorder adds what it knows (version, git commit, host, start time, itself, the
    bag and ``extra``, e.g. how it splits the bag); the caller's JSON object wins for the
    keys only it knows.  ParamError (one line) if ``text`` is not a JSON object.
    """
    try:
        given = json.loads(text) if text.strip() else {}
    except ValueError as exc:
        raise ParamError(f'parameter session_metadata is not JSON ({exc})') from None
    if not isinstance(given, dict):
        raise ParamError('parameter session_metadata must be a JSON object')
    base = session_metadata(str(given.get('scenario', '')),
                            extra={'recorder': recorder, 'bag_dir': bag_dir, **(extra or {})})
    for key in ('parameters', 'controller', 'seed', 'command'):
        base.pop(key, None)  # only the caller knows these
    base.update({str(k): v if isinstance(v, str) else json.dumps(v, sort_keys=True)
                 for k, v in given.items()})
    return base


def command_line(argv: Optional[Sequence[str]] = None) -> str:
    """Return the command that made the session, without this machine's paths or secrets.

    ``python -m erva_ros.<module>`` shows as that; a console script (``erva``) by its name;
    a map server's URI without its password (core/roadmap/location.py).
    """
    argv = list(sys.argv if argv is None else argv)
    if not argv:
        return ''
    head = os.path.abspath(argv[0])
    package = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    if head.endswith('.py') and head.startswith(package + os.sep):
        module = os.path.relpath(head[:-3], os.path.dirname(package)).replace(os.sep, '.')
        first = ['python', '-m', module]
    else:
        first = [os.path.basename(argv[0])]
    return redact_text(' '.join(first + argv[1:]))


def recorder_ros_args(bag_dir: str, metadata: Optional[Mapping[str, Any]] = None,
                      topics: Optional[Sequence[str]] = None, namespace: Optional[str] = None,
                      node_name: Optional[str] = None, flush_period_s: Optional[float] = None,
                      use_sim_time: bool = False,
                      parameters: Optional[Mapping[str, Any]] = None) -> List[str]:
    """Return the ``--ros-args ...`` that start recorder_node on ``bag_dir``.

    The JSON metadata goes in as a double-quoted YAML scalar, so rcl keeps it a string;
    ``parameters`` are further numeric or boolean recorder parameters.
    """
    args = ['--ros-args']
    if node_name:
        args += ['-r', f'__node:={node_name}']
    if namespace:
        args += ['-r', f'__ns:={namespace}']
    args += ['-p', f'bag_dir:={json.dumps(os.fspath(bag_dir))}']
    if metadata:
        text = json.dumps({str(k): _text(v) for k, v in metadata.items()}, sort_keys=True)
        args += ['-p', f'session_metadata:={json.dumps(text)}']
    if topics:
        args += ['-p', f'topics:={json.dumps(list(topics))}']
    if flush_period_s is not None:
        args += ['-p', f'flush_period_s:={float(flush_period_s)!r}']
    if use_sim_time:
        args += ['-p', 'use_sim_time:=true']
    for key, value in (parameters or {}).items():
        args += ['-p', f'{key}:={json.dumps(value)}']
    return args


__all__ = ['new_bag_dir', 'session_metadata', 'stored_parameters', 'recorder_session',
           'recorder_ros_args', 'git_commit', 'utc_stamp']
