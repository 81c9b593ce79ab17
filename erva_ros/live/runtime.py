"""The main() idiom shared by every node (ros2/examples style), with one-line start-up errors.

``rclpy.init`` parses ``--ros-args`` (``--params-file``, ``-p``, ``-r __ns:=``) as
``ros2 run`` does; the node is spun by a SingleThreadedExecutor; Ctrl-C
(KeyboardInterrupt) and SIGTERM (ExternalShutdownException) end it quietly; a bad
parameter stops it with one line on stderr and exit status 2, never a traceback.
"""

import gc
import signal
import sys
from typing import Callable, List, Optional

from erva_ros.live.realtime import set_fifo_priority
from erva_ros.params import ParamError

#: Exit status of a node stopped by a bad parameter or option.
EXIT_BAD_PARAMETER = 2


def run_node(name: str, factory: Callable[[], object], args: Optional[List[str]] = None
             ) -> int:
    """Create the node with ``factory`` and spin it until shutdown; return the exit status."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    # Installed before rclpy.init, so rclpy's own handlers (which shut the context down)
    # chain to it: a signal is then known even if it lands inside a callback.
    signalled = []

    def note(signum, frame):
        signalled.append(signum)
        if signum == signal.SIGINT:
            raise KeyboardInterrupt

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, note)
    try:
        rclpy.init(args=args)
    except Exception as exc:  # malformed --ros-args: rcl reports it, keep it to one line
        print(f'{name}: error: {str(exc).splitlines()[0]}', file=sys.stderr)
        return EXIT_BAD_PARAMETER
    node = None
    try:
        node = factory()
        # Start-up objects (CasADi functions, messages, modules) never die: move them out
        # of the collector's way so a collection during the loop scans only new objects.
        gc.collect()
        gc.freeze()
        # Last, after the start-up work: a FIFO thread building CasADi functions would
        # starve the other nodes starting on the same cores.
        priority = getattr(node, 'realtime_priority', 0)
        node.scheduling = set_fifo_priority(priority, node.get_logger().warning)
        if priority > 0 and node.scheduling.startswith('SCHED_FIFO'):
            node.get_logger().info(f'running at {node.scheduling}')
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.spin()
    except ParamError as exc:
        print(f'{name}: error: {exc}', file=sys.stderr, flush=True)
        return EXIT_BAD_PARAMETER
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if rclpy.ok() and not signalled:
            raise
        # SIGINT/SIGTERM arrived while a callback ran (a publish on the invalidated
        # context, an interrupted message conversion): part of a normal shutdown.
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


__all__ = ['EXIT_BAD_PARAMETER', 'run_node']
