"""`erva run --foxglove`: the session's Foxglove server process (nodes/foxglove_node.py).

:func:`check_address` validates ``[HOST:]PORT`` and binds it once, so a port in use or
an address of no interface here fails with one line before any process starts.
:func:`start_process` starts foxglove_node first of all the session's processes and
waits until it listens, so a viewer can connect before the loop runs and the node
subscribes before the time master starts (it counts as one more subscriber, like the
recorder).  It is stopped with the recorder, after the loop's nodes.
"""

import json
import os
import time
from typing import Any, Callable, Dict, List, Tuple

from erva_ros.core.reports import FoxgloveReport
from erva_ros.core.topics import clock_remap
from erva_ros.core.errors import CLIError
from erva_ros.ros import foxglove_server as fg
from erva_ros.session.processes import ChildProcess, node_argv, stop_processes
from erva_ros.session.run.recording import session_topics

#: The process name in `erva run`'s summary and logs.
PROCESS = 'foxglove_server'
#: Its node module (erva_ros.nodes.<name>).
PROCESS_NODE = 'foxglove_node'
#: The log line of foxglove_node once it listens (followed by the URL).
READY = 'serving ws://'
#: Longest wait for the server to listen (a cold start on a busy machine takes seconds).
START_TIMEOUT_S = 60.0


def check_address(text: str) -> Tuple[str, int]:
    """Return (host, port) of ``--foxglove [HOST:]PORT``; raise CLIError (one line) if unusable.

    Without HOST the server listens on loopback only; another address is used only when
    named.  The address is bound once here (and released), so a port in use is reported
    before anything starts.
    """
    missing = fg.sdk_missing()
    if missing:
        raise CLIError(f'--foxglove: {missing}')
    try:
        host, port = fg.parse_address(text)
        fg.check_bindable(host, port)
    except ValueError as exc:
        raise CLIError(f'--foxglove: {exc}') from None
    return host, port


def server_argv(host: str, port: int, namespace: str, topics: List[str],
                session: Dict[str, str], use_sim_time: bool, session_id: str = '') -> List[str]:
    """Return the command line of foxglove_node for one session."""
    return node_argv(PROCESS_NODE, namespace, parameters={
        'host': json.dumps(host), 'port': int(port), 'topics': json.dumps(list(topics)),
        'session_id': json.dumps(session_id),
        # A double-quoted YAML scalar, so rcl keeps the JSON a string.
        'session_metadata': json.dumps(json.dumps(session, sort_keys=True)),
        **({'use_sim_time': True} if use_sim_time else {})})


def start_process(cfg, session, env: Dict[str, str], log: Callable[[str], None],
                  description: Dict[str, str]):
    """Start foxglove_node for ``session`` and wait until it listens; return its process.

    Raises CLIError (exit 2) when it cannot listen (say, the port was taken since
    :func:`check_address`), after stopping it.
    """
    host, port = fg.parse_address(cfg.foxglove)
    argv = server_argv(host, port, cfg.namespace, session_topics(session), description,
                       use_sim_time=not session.realtime, session_id=session.session_id)
    argv += clock_remap(cfg.namespace)
    proc = ChildProcess(PROCESS, argv, env, os.path.join(session.directory, f'{PROCESS}.log'))
    deadline = time.monotonic() + START_TIMEOUT_S
    while True:
        lines = proc.tail(50).splitlines()
        ready = next((line for line in lines if READY in line), None)
        if ready is not None:
            served = 'ws://' + ready.split(READY, 1)[1].split()[0]
            log(f'Foxglove: open {served} (Open connection > Foxglove WebSocket; '
                f'layout config/foxglove_layout.json)')
            return proc
        if proc.poll() is not None or time.monotonic() > deadline:
            why = (lines[-1] if lines else 'no output') if proc.poll() is not None else (
                f'not listening after {START_TIMEOUT_S:g} s')
            stop_processes([proc])
            raise CLIError(f'--foxglove: the Foxglove server did not start: '
                           f'{why.split("error: ", 1)[-1]}')
        time.sleep(0.05)


def summary(reports: Dict[str, Any]) -> Dict[str, Any]:
    """Return the server's counters for `erva run`'s summary from the session's reports."""
    r = next((r for r in reports.values() if isinstance(r, FoxgloveReport)), None)
    if r is None:
        return {'status': 'no status received'}
    return {'url': r.url, 'received': r.received, 'forwarded': r.forwarded,
            'clients_seen': r.clients_seen, 'overflow_events': r.overflow_events,
            'offered': dict(r.offered)}


__all__ = ['PROCESS', 'check_address', 'server_argv', 'start_process',
           'summary']
