"""The main() idiom shared by every node (ros2/examples style), with one-line start-up errors.

``rclpy.init`` parses ``--ros-args`` (``--params-file``, ``-p``, ``-r __ns:=``) as
``ros2 run`` does; the node is spun by a SingleThreadedExecutor; a bad parameter stops
it with one line on stderr and exit status 2, never a traceback.

Shutdown (SIGINT/SIGTERM, Ctrl-C) ends the node *cleanly* for the session's records:
rclpy's own signal handlers would shut the context down at once, so a publisher
leaving with samples a subscriber (the recorder) has not acknowledged yet would take
them with it.  Instead the signal stops the spin loop, then the node publishes a last
status (its final counts, :meth:`~erva_ros.ros.loop_node.LoopNode.stop`) and waits,
bounded by ``SHUTDOWN_ACK_S``, until every subscriber has acknowledged everything its
counted publishers and its status wrote (``Publisher.wait_for_all_acked``).  A second
signal skips the wait.  Then the node, the context and the DDS participant are torn down
(peers see it leave at once) and the process ends with ``os._exit``: the interpreter's
own exit would only join middleware threads (0.4-0.9 s of timed sleeps).  A phase slower
than ``SLOW_STOP_S`` says so on stderr.  Whatever hangs on the way out, the process is
gone ``SHUTDOWN_ACK_S + SHUTDOWN_GRACE_S`` (9 s) after the first signal, before a
supervisor's SIGKILL (10 s, :func:`erva_ros.session.processes.stop_processes`): the kernel
ends it with SIGALRM, after every thread's stack is written to stderr (faulthandler; also
on SIGUSR1, without stopping), so a hang in a middleware thread (eProsima/Fast-DDS#2398:
a thread spinning after its peer died) is both ended and located.
"""

import faulthandler
import os
import signal
import sys
import time
from typing import List, Optional, Type

from erva_ros.core.model.params import ParamError
from erva_ros.core.startup import process_age_s
from erva_ros.ros.context import check_domain_id

#: Exit status of a node stopped by a bad parameter or option.
EXIT_BAD_PARAMETER = 2
#: How long (s) a stopping node waits for its subscribers to acknowledge what it published.
SHUTDOWN_ACK_S = 4.0
#: After the acknowledgement wait, how long (s) tearing the node down may take at most.
SHUTDOWN_GRACE_S = 5.0
#: A stop phase longer than this (s) is reported on stderr.
SLOW_STOP_S = 1.0
#: The spin loop wakes at least this often to see a stop request (s).
SPIN_TIMEOUT_S = 0.1


def run_node(node_class: Type, args: Optional[List[str]] = None) -> int:
    """Create a :class:`~erva_ros.ros.loop_node.LoopNode` ``node_class``; spin it until shutdown.

    Returns the exit status of a start-up failure (:data:`EXIT_BAD_PARAMETER`); a node
    that ran ends the process itself, with the status its :meth:`stop` returns.
    """
    imported = process_age_s()      # the interpreter and the node's imports
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    name = node_class.NAME
    signalled: List[float] = []      # when each stop signal came (monotonic s)

    def note(signum, frame):
        if not signalled:
            signal.alarm(int(SHUTDOWN_ACK_S + SHUTDOWN_GRACE_S))   # the last resort
        signalled.append(time.monotonic())

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, note)
    # Where a node hangs, from C as well: every thread's stack on stderr (its log under
    # `erva run`) when the last resort fires, and on SIGUSR1 (a supervisor's last word
    # before SIGKILL, or `kill -USR1 <pid>` by hand) without stopping the node.
    faulthandler.register(signal.SIGALRM, chain=True)
    faulthandler.register(signal.SIGUSR1)
    try:
        check_domain_id()
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # bad domain, malformed --ros-args: one line
        print(f'{name}: error: {str(exc).splitlines()[0]}', file=sys.stderr)
        return EXIT_BAD_PARAMETER
    initialised = process_age_s()
    node = None
    code = 0
    try:
        node = node_class()
        node.report.startup.update(imported=imported, initialised=initialised,
                                   constructed=process_age_s())
        if node.autostart:      # else `erva run` or `ros2 lifecycle set` drive it
            node.start_up()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while not signalled and rclpy.ok():
            executor.spin_once(timeout_sec=SPIN_TIMEOUT_S)
        stop_t0 = time.monotonic()
        # The wait counts from the signal (a long callback may have delayed this point),
        # so it ends before a supervisor's SIGTERM; a little is always left for it.
        since = stop_t0 - signalled[0] if signalled else 0.0
        before = len(signalled)
        code = node.stop(lambda: len(signalled) > before, max(0.5, SHUTDOWN_ACK_S - since))
        acked = getattr(node, 'acked', True)
        if not acked or time.monotonic() - stop_t0 > SLOW_STOP_S:
            _stop_note(name, f'final samples {"" if acked else "not all "}acknowledged '
                             f'after {time.monotonic() - stop_t0:.2f} s')
    except ParamError as exc:
        print(f'{name}: error: {exc}', file=sys.stderr, flush=True)
        return EXIT_BAD_PARAMETER
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        t0 = time.monotonic()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()                     # (also finishes rcl's logging)
        # The participant leaves here, its peers told at once, not in the interpreter's exit.
        rclpy.get_default_context().destroy()
        if time.monotonic() - t0 > SLOW_STOP_S:
            _stop_note(name, f'tearing down took {time.monotonic() - t0:.2f} s')
    # Nothing is left to do, but the interpreter's exit would still join the middleware's
    # threads (0.4-0.9 s measured, timed sleeps in static destructors): end here.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def _stop_note(name: str, what: str) -> None:
    """Say on stderr (the node's log under `erva run`) that stopping was slow, and where."""
    print(f'{name}: slow stop: {what}', file=sys.stderr, flush=True)


__all__ = ['EXIT_BAD_PARAMETER', 'SHUTDOWN_ACK_S', 'SHUTDOWN_GRACE_S', 'run_node']
