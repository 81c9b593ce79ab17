"""The recording of an `erva run` session: the recorder process, its drain, the bag check.

* :func:`start_recorder` starts recorder_node on a new bag directory with the session's
  description, below the loop's real-time priority;
* :class:`RecorderDrain` tells when the recorder holds every message the nodes published
  (the nodes stay up until then, as long as it makes progress);
"""

import importlib.util
import os
import tempfile
import time
from typing import Callable, Dict, List, Mapping, Optional

from erva_ros.core import topics
from erva_ros.core.bag import session as bag_session
from erva_ros.core.errors import CLIError
from erva_ros.core.hil.topics import RECORD_TOPICS
from erva_ros.core.reports import NodeReport
from erva_ros.core.settings.schemas import SCHEMAS
from erva_ros.session.run import accounting
from erva_ros.session.processes import ChildProcess, module_argv
from erva_ros.session.run.session_file import Session, session_description

#: `erva run` waits for the recorder to report every message the nodes published (its
#: status comes every RECORDER_STATUS_S) before stopping them, while it makes progress,
#: giving up after this long without any (the reason goes in the summary).
RECORDER_STALL_S = 5.0
#: The recorder's status period in a session (the start gate and the drain read it).
RECORDER_STATUS_S = 0.25
#: The recorder runs at SCHED_FIFO this much below the loop's nodes: above other work on
#: the machine, so the record is not starved, below the loop, so the loop goes first.
RECORDER_PRIORITY_BELOW = 10
#: The recorder's process name in `erva run`.
PROCESS = 'recorder_node'


def record_topics(hil: bool, road_estimated: bool = False, prediction: bool = True
                  ) -> List[str]:
    """Return the topics a session records (and serves): the contract, plus the HIL topics.

    ``road_estimated`` (``--preview map:FILE``): also the road estimate and the alignment.
    Without ``prediction`` (``publish_prediction`` false) nobody writes ``prediction``,
    and the start would wait for its writer.
    """
    out = list(SCHEMAS['recorder'].defaults()['topics'])
    if not prediction:
        out.remove(topics.PREDICTION)
    if hil:
        out += RECORD_TOPICS
    if road_estimated:
        out += [topics.ROAD_ESTIMATE, topics.ROAD_ALIGNMENT]
    return out


def session_topics(session: Session) -> List[str]:
    """Return the topics ``session`` records and serves (:func:`record_topics`)."""
    return record_topics(session.hil, session.road_estimated,
                         session.live['publish_prediction'])


def recorder_available() -> bool:
    """Return True when the recorder (erva_ros.core.bag, recorder_node) is installed."""
    return all(importlib.util.find_spec(m) is not None
               for m in ('erva_ros.core.bag.session', 'erva_ros.nodes.recorder_node'))


def check_record_dir(parent: str) -> None:
    """Raise CLIError unless bags can be written under ``parent`` (created if missing).

    Refused before anything starts: a session whose record cannot be written is not
    the session the user asked for (a disk that fills up *during* the run is reported
    by the recorder and fails the run's bag check instead).
    """
    try:
        os.makedirs(parent, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=parent, prefix='.erva-write-test-'):
            pass
    except OSError as exc:
        raise CLIError(f'--record {parent}: cannot write bags there '
                       f'({exc.strerror or exc}); pick another directory or --no-record'
                       ) from None


def start_recorder(session: Session, namespace: str, bag_parent: str, env: Dict[str, str],
                   log: Callable[[str], None], parameters: Optional[Mapping] = None
                   ) -> ChildProcess:
    """Start recorder_node on a new bag under ``bag_parent``; its ``bag_dir`` and ``topics``.

    ``parameters``: recorder parameters of the command line (how the bag is split).
    """
    bag_dir = bag_session.new_bag_dir(bag_parent, session.scenario)
    record = session_topics(session)
    loop_priority = session.live['realtime_priority'] if session.realtime else 0
    argv = module_argv('erva_ros.nodes.recorder_node', *bag_session.recorder_ros_args(
        bag_dir, session_description(session), topics=record, namespace=namespace,
        use_sim_time=not session.realtime,
        parameters={'diagnostics_period_s': RECORDER_STATUS_S,
                    'session_id': session.session_id,
                    'realtime_priority': max(0, loop_priority - RECORDER_PRIORITY_BELOW)
                    if loop_priority > 1 else 0, **(parameters or {})}))
    argv += topics.clock_remap(namespace)
    proc = ChildProcess(PROCESS, argv, env, os.path.join(session.directory, f'{PROCESS}.log'))
    proc.bag_dir = bag_dir
    proc.topics = record
    log(f'recording to {bag_dir}')
    return proc


class RecorderDrain:
    """Tell when the recorder holds every message the nodes published (so far).

    A publisher that exits takes what it has not delivered with it, so the nodes stay
    up until then -- as long as the recorder makes progress; after RECORDER_STALL_S
    without any, give up and say why (:attr:`gave_up`).
    """

    def __init__(self, stall_s: float = RECORDER_STALL_S):
        self.stall_s = stall_s
        self.gave_up: Optional[str] = None
        self._total: Optional[int] = None
        self._progress = 0.0

    def caught_up(self, reports: Mapping[str, NodeReport], now: Optional[float] = None
                  ) -> bool:
        """Return True once nothing is behind, or the recorder stalled (see :attr:`gave_up`)."""
        recorder = accounting.recorder_report(reports)
        if recorder is not None and recorder.error:    # it writes nothing more: no wait
            return True
        behind = accounting.recorder_behind(
            recorder,
            accounting.published_counts(accounting.node_reports(reports)))
        if not behind:
            return True
        total = sum(got for got, _ in behind.values())
        now = time.monotonic() if now is None else now
        if total != self._total:
            self._total, self._progress = total, now
        if now - self._progress > self.stall_s:
            topic, (got, n) = next(iter(behind.items()))
            self.gave_up = (f'the recorder made no progress for {self.stall_s:g} s with '
                            f'{topic} at {got} of {n} messages; the nodes were stopped')
            return True
        return False


def record_writers(record: List[str], namespace: str, n_diagnostics: int) -> Dict[str, int]:
    """Return the writers the recorder must match per topic before the start.

    One per data topic; /diagnostics and /parameter_events: ``n_diagnostics`` (every
    node, the recorder itself and the Foxglove server: each announces its parameter
    changes, so a change made during the run is in the bag).
    """
    node_wide = (topics.DIAGNOSTICS, topics.PARAMETER_EVENTS)
    out = {accounting.qualify(t, namespace): 1 for t in record
           if t not in (topics.CLOCK, *node_wide)}
    out[topics.DIAGNOSTICS] = n_diagnostics
    if topics.PARAMETER_EVENTS in record:
        out[topics.PARAMETER_EVENTS] = n_diagnostics
    return out


__all__ = ['RECORDER_STALL_S', 'RECORDER_STATUS_S', 'RECORDER_PRIORITY_BELOW',
           'PROCESS', 'record_topics', 'session_topics', 'recorder_available',
           'check_record_dir', 'start_recorder',
           'RecorderDrain', 'record_writers']
