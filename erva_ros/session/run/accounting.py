"""Message accounting of an `erva run` session: who must be matched, and was anything lost.

A writer delivers only to the readers it has matched, and a reliable writer repairs a
reader's gaps only from its own history.  So a session records everything exactly when

1. the loop starts only after every loop writer has matched every subscriber it will
   have -- the other loop nodes, the session monitor and the recorder (each node's
   report has ``subscribers`` per topic, the recorder's ``publishers`` per topic);
2. the writers keep enough history to repair a stalled recorder
   (``publisher_history_s``; :func:`erva_ros.ros.qos.publisher_qos`);
3. at the end the nodes stay up until the recorder holds what they published
   (each report's ``published`` against the recorder's ``count``), and each node,
   when stopped, waits until its subscribers acknowledged its samples
   (:meth:`erva_ros.ros.loop_node.LoopNode.stop`).

:func:`check_bag` then compares, per topic, what the nodes published with what the bag
file holds -- read back from disk, not the recorder's word for it -- and, for
``/diagnostics``, that every node's status sequence numbers are there without a gap.
"""

from typing import Any, Dict, Iterable, List, Mapping, Optional, Sequence, Tuple

from erva_ros.core import topics
from erva_ros.core.bag.reader import open_bag
from erva_ros.core.contract import decode_diagnostics
from erva_ros.core.hil import topics as hil
from erva_ros.core.reports import NMPCReport, NodeReport, RecorderReport, report_from_status
from erva_ros.core.wire import header_stamp_ns

#: Subscribers of each loop topic among the loop's own nodes (observers come on top).
LOOP_SUBSCRIBERS = {
    topics.STATE: 1,            # nmpc_node
    topics.SPRUNG_ACCEL: 0,
    topics.GENERATOR: 0,
    topics.ROAD_HEIGHT: 1,      # plant_sim_node
    topics.ROAD_PREVIEW: 1,     # nmpc_node
    topics.DAMPING_CMD: 1,      # plant_sim_node
    topics.DIAGNOSTICS: 0,
}


def hil_loop_subscribers(road_estimated: bool = False) -> Dict[str, int]:
    """Return LOOP_SUBSCRIBERS of the HIL loop (the ECU simulator, bridge and estimator).

    ``road_estimated``: the estimator reads no road; the map preview its road/estimate.
    """
    road = {topics.ROAD_ESTIMATE: 1, topics.ROAD_ALIGNMENT: 0} if road_estimated else {}
    return {
        **road,
        topics.STATE: 1,            # nmpc_node (from the estimator)
        topics.ROAD_HEIGHT: 1 if road_estimated else 2,   # the ECU simulator, the estimator
        topics.ROAD_PREVIEW: 1,     # nmpc_node
        topics.DAMPING_CMD: 1,      # ecu_bridge_node
        topics.SPRUNG_ACCEL: 0,     # the ECU simulator's ground truth
        topics.GENERATOR: 0,
        topics.DIAGNOSTICS: 0,
        hil.ECU_MEASUREMENTS: 1,    # state_estimator_node
        hil.ECU_DAMPING_APPLIED: 0, hil.ECU_SPRUNG_ACCEL: 0, hil.ECU_SUSPENSION: 0,
        hil.ECU_GENERATOR: 0, hil.TRUE_STATE: 0,
    }


def qualify(topic: str, namespace: str) -> str:
    """Return ``topic`` resolved against ``namespace`` (absolute names stay)."""
    return topic if topic.startswith('/') else f'{namespace.rstrip("/")}/{topic}'


def expected_subscribers(loop: Mapping[str, int], observers: Iterable[Iterable[str]],
                         namespace: str) -> Dict[str, int]:
    """Return, per fully qualified topic, how many subscribers its writer must match.

    ``loop`` counts the loop's own subscribers per topic; each of ``observers`` (the
    monitor, the recorder, ...) is the list of topics that observer subscribes to.
    """
    out = {qualify(t, namespace): n for t, n in loop.items()}
    for watched in observers:
        for t in watched:
            name = qualify(t, namespace)
            if name in out:
                out[name] += 1
    return out


def unmatched(reports: Mapping[str, NodeReport], nodes: Sequence[str],
              expected: Mapping[str, int], later: Mapping[str, int]) -> List[str]:
    """Return what is not matched yet (empty once the loop may start).

    ``reports`` are the session's newest reports by node name; every one of ``nodes``
    must have reported, and each writer's ``subscribers`` must reach ``expected`` minus
    ``later`` (subscribers that come only after the check, e.g. the monitor's gate
    subscription).
    """
    missing = [f'{n}: no status yet' for n in nodes
               if not any(name == n or name.startswith(n + ':') for name in reports)]
    for name, report in reports.items():
        for topic, count in report.subscribers.items():
            need = expected.get(topic)
            if need is None:
                continue
            need -= later.get(topic, 0)
            if count < need:
                missing.append(f'{name}: {topic} has {count} of {need} subscribers')
    return missing


def rejections_cost(rejected_total: int, nmpc: Optional[NMPCReport],
                    foreign_total: int = 0) -> Optional[str]:
    """Return why rejected inputs cost the loop samples of control (None if they did not).

    Samples whose state never became the controller's: those it missed (a busy
    controller's superseded states are load, not rejection) and those it gave the passive
    command for want of a state -- every state refused, as after a wrong first stamp.
    Rejected messages of other publishers (``foreign_total``: stamped outside the session
    or repeating a stamp) are extra messages, not the loop's samples: refusing them takes
    no sample away, so only the session's own rejected messages count.
    """
    if nmpc is None:
        return None
    unseen = nmpc.missed_samples - nmpc.superseded_states + nmpc.safe_commands
    if rejected_total > foreign_total and unseen > 0:
        return (f'{unseen} samples went without a command of their own while '
                f'{rejected_total} input messages were rejected')
    return None


def recorder_unmatched(recorder: Optional[RecorderReport], record: Mapping[str, int]
                       ) -> List[str]:
    """Return the recorded topics whose writers the recorder has not all matched yet.

    ``record`` maps each fully qualified recorded topic to its number of writers.
    """
    got = {} if recorder is None else recorder.publishers
    return [f'recorder: {topic} matched {got.get(topic, 0)} of {need} publishers'
            for topic, need in record.items() if got.get(topic, 0) < need]


def published_counts(reports: Iterable[NodeReport], final_only: bool = False
                     ) -> Dict[str, Optional[int]]:
    """Return, per topic, the messages the nodes say they published.

    ``final_only``: a topic of a node whose final report did not come (the node was
    killed, or is still running) is unknown (None), never a count that may be short.
    """
    out: Dict[str, Optional[int]] = {}
    for r in reports:
        for topic, n in r.published.items():
            if final_only and not r.final:
                out[topic] = None
            elif out.get(topic, 0) is not None:
                out[topic] = out.get(topic, 0) + n
    return out


def recorder_behind(recorder: Optional[RecorderReport], published: Mapping[str, Optional[int]]
                    ) -> Dict[str, Tuple[int, int]]:
    """Return {topic: (recorded, published)} for topics the recorder has not caught up on."""
    counts = {} if recorder is None else recorder.count
    return {topic: (counts.get(topic, 0), n) for topic, n in published.items()
            if n is not None and counts.get(topic, 0) < n}


def check_bag(bag_path: str, published: Mapping[str, Optional[int]],
              status_seqs: Mapping[str, int], window_ns: Optional[Tuple[int, int]] = None,
              session: str = '') -> Dict:
    """Compare the bag (all its files) with what was published; return the per-topic accounting.

    ``published`` maps topics to the nodes' final counts (None: unknown, the node's
    final report is missing); ``status_seqs`` maps each node's status name to the highest
    ``status_seq`` the session saw from it: the bag must hold every status from its
    first recorded one up to that.  Messages stamped outside ``window_ns`` (the
    session's time span) are counted as foreign, not as the loop's; so are statuses of
    another session (``session``: this one's id).  Returns ``{'topics': {topic:
    {published, recorded, lost, foreign}}, 'lost': total, 'unknown': [topics],
    'diagnostics_missing': {status name: [seq, ...]}, 'foreign_statuses': n, 'in_bag':
    {messages, topics, other_topics: {topic: messages}}}`` (``in_bag``: the whole bag, as
    `erva bag info` counts; ``other_topics``: those not checked against a publisher).
    """
    bag = open_bag(bag_path)
    recorded = {t: 0 for t in published}
    foreign = {t: 0 for t in published}
    seen: Dict[str, set] = {}
    foreign_statuses = 0
    for msg in bag.messages():
        if msg.topic == topics.DIAGNOSTICS:
            for status in decode_diagnostics(msg.data)[1]:
                report = report_from_status(status)
                if session and report.session != session:
                    foreign_statuses += 1
                elif report.status_seq:
                    seen.setdefault(status.name, set()).add(report.status_seq)
        if msg.topic not in recorded:
            continue
        stamp = header_stamp_ns(msg.data)
        if window_ns is not None and not window_ns[0] <= stamp <= window_ns[1]:
            foreign[msg.topic] += 1
        else:
            recorded[msg.topic] += 1
    # What the bag holds in all, as `erva bag info` counts it: the loop's topics checked
    # above, and the others (/diagnostics, /parameter_events) by their counts.
    in_bag = {'messages': bag.message_count, 'topics': len(bag.topics),
              'other_topics': {t: info.count for t, info in sorted(bag.topics.items())
                               if t not in published}}
    out = {'topics': {}, 'lost': 0, 'unknown': [], 'diagnostics_missing': {},
           'foreign_statuses': foreign_statuses, 'in_bag': in_bag}
    for topic, n in published.items():
        lost = None if n is None else max(0, n - recorded[topic])
        out['topics'][topic] = {'published': n, 'recorded': recorded[topic], 'lost': lost,
                                'foreign': foreign[topic]}
        if lost is None:
            out['unknown'].append(topic)
        else:
            out['lost'] += lost
    for name, last in status_seqs.items():
        got = seen.get(name, set())
        first = min(got) if got else last + 1
        gaps = sorted(set(range(first, last + 1)) - got)
        if not got or gaps:
            out['diagnostics_missing'][name] = gaps if got else 'none recorded'
    return out


def recorder_report(reports: Mapping[str, NodeReport]) -> Optional[RecorderReport]:
    """Return the recorder's newest report (None before its first)."""
    return next((r for r in reports.values() if isinstance(r, RecorderReport)), None)


def node_reports(reports: Mapping[str, NodeReport]) -> List[NodeReport]:
    """Return the newest report of every node but the recorder."""
    return [r for r in reports.values() if not isinstance(r, RecorderReport)]


def check_recording(bag_dir: str, reports: Mapping[str, NodeReport], window: Tuple[int, int],
                    session: str = '') -> Tuple[Dict[str, Any], List[str]]:
    """Compare the bag with what every node published; return (report, one error per loss).

    ``window`` is the span of the session's stamps (ns): others are not the loop's.  A
    node whose final report is missing (it was killed) has published an unknown number:
    its topics are reported as such, not as a loss or as more recorded than published.
    """
    errors: List[str] = []
    recorder = recorder_report(reports)
    report: Dict[str, Any] = {'lost_in_transport': 0 if recorder is None
                              else recorder.lost_in_transport}
    published = published_counts(node_reports(reports), final_only=True)
    seqs = {r.node: r.status_seq for r in reports.values() if r.status_seq}
    try:
        report.update(check_bag(bag_dir, published, seqs, window, session))
    except Exception as exc:    # BagError, CdrError: the file itself is the problem
        report['error'] = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        return report, [f'the bag cannot be checked: {report["error"]}']
    if recorder is not None and recorder.error:
        # One cause, one line: the losses per topic and the missing statuses follow from it.
        kept = sum(c['recorded'] for c in report['topics'].values())
        report['failed'] = recorder.error
        return report, [f'recording failed: {recorder.error}; the loop ran on, the bag keeps '
                        f'the {kept} messages written before ("erva bag repair {bag_dir} '
                        '--out DIR" completes it elsewhere)']
    for topic, c in report['topics'].items():
        if c['lost']:
            errors.append(f'the bag lost {c["lost"]} of {c["published"]} messages on {topic}')
    for name, gaps in report['diagnostics_missing'].items():
        errors.append(f'the bag lacks /diagnostics statuses of {name}: {gaps}')
    if report['lost_in_transport']:
        errors.append(f'the middleware reported {report["lost_in_transport"]} '
                      f'messages lost before the recorder took them')
    return report, errors


__all__ = ['LOOP_SUBSCRIBERS', 'hil_loop_subscribers', 'qualify', 'expected_subscribers',
           'unmatched', 'rejections_cost', 'recorder_unmatched', 'published_counts',
           'recorder_behind', 'check_bag', 'recorder_report', 'node_reports',
           'check_recording']
