"""Compile what an `erva run` session's nodes will load, before any of them starts.

A node that compiled its CasADi functions itself at start-up (up to a minute on an empty
cache) used up the other nodes' start-up timeouts.  :func:`warm_session` builds the
session's cores from the same effective values its params file gives the nodes
(:func:`erva_ros.core.loop.warmup.session_targets`) and compiles what is missing, with one
progress line per core; on a warm cache it costs milliseconds and starts nothing.
"""

from typing import Callable, Optional

from erva_ros.core.loop.warmup import ensure_compiled, session_targets, WarmResult
from erva_ros.session.run.session_file import Session


def warm_session(session: Session, log: Callable[[str], None],
                 hil_file: Optional[str] = None) -> WarmResult:
    """Compile the functions ``session``'s nodes will load; ParamError if that must fail.

    ``hil_file`` is the HIL loop's parameter file (default config/hil.yaml, as
    :func:`erva_ros.session.hil.hil_processes.hil_process_specs`).
    """
    return ensure_compiled(session_targets(session.erva, session.settings, session.live,
                                           session.ecu, hil_file, session.road_estimated), log)


__all__ = ['warm_session']
