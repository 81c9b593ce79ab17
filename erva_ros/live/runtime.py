"""The main() idiom shared by every node (ros2/examples style), with one-line start-up errors.

``rclpy.init`` parses ``--ros-args`` (``--params-file``, ``-p``, ``-r __ns:=``) as
``ros2 run`` does; the node is spun by a SingleThreadedExecutor; Ctrl-C
(KeyboardInterrupt) and SIGTERM (ExternalShutdownException) end it quietly; a bad
parameter stops it with one line on stderr and exit status 2, never a traceback.
"""

import gc
import sys
from typing import Callable, List, Optional

from erva_ros.params import ParamError

#: Exit status of a node stopped by a bad parameter or option.
EXIT_BAD_PARAMETER = 2


def run_node(name: str, factory: Callable[[], object], args: Optional[List[str]] = None
             ) -> int:
    """Create the node with ``factory`` and spin it until shutdown; return the exit status."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

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
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.spin()
    except ParamError as exc:
        print(f'{name}: error: {exc}', file=sys.stderr, flush=True)
        return EXIT_BAD_PARAMETER
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if rclpy.ok():
            raise
        # SIGINT/SIGTERM shut the context down while a callback was publishing: the
        # callback's "context is invalid" error is part of a normal shutdown.
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


__all__ = ['EXIT_BAD_PARAMETER', 'run_node']
