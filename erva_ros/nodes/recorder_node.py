"""recorder_node: record the session's topics into a rosbag2-compatible MCAP bag.

Subscribes (reliable, keep-last ``RECORDER_DEPTH``) to every topic of ``topics`` and
writes each message's CDR bytes as received (:class:`erva_ros.core.bag.recording.Recording`)
with rosbag2 Jazzy's times: log time = reception time (node time under
``use_sim_time``), publish time = the publisher's ``source_timestamp``.  A topic's
channel is created when its first publisher is discovered (or its first message
arrives), with the QoS its publishers offer and their type hash, as ``ros2 bag record``
does.  The bag is split into ``<bag>_<i>.mcap`` files every ``max_bag_duration_s`` (300 s)
or ``max_bag_size_bytes``, as ``ros2 bag record --max-bag-duration/--max-bag-size``: the
writer's memory stays bounded in a session of any length (docs/recording.md).
Parameters: config/session.yaml (``bag_dir`` is required).  The loop's
publishers keep ``publisher_history_s`` of samples and each subscription here
``RECORDER_DEPTH``: a recorder stalled for seconds still gets everything.

SIGINT/SIGTERM: pending messages are taken, the file is finished and the node exits 0.
A bag that cannot be written is one log line and an ERROR status; the node goes on
without recording and exits 1.  Being its own process, it cannot stall the loop.
"""

import functools
import os
import time
from typing import Dict, Optional

from rclpy.event_handler import SubscriptionEventCallbacks

from erva_ros.core import topics as contract
from erva_ros.core.bag import BagError
from erva_ros.core.bag.qos import profile_to_dict
from erva_ros.core.bag.recording import Recording
from erva_ros.core.bag.session import recorder_session
from erva_ros.core.levels import ERROR, OK
from erva_ros.core.model.params import ParamError
from erva_ros.core.reports import RecorderReport
from erva_ros.ros import qos as ros_qos
from erva_ros.ros.bag_messages import message_class
from erva_ros.ros.loop_node import LoopNode
from erva_ros.ros.runtime import run_node

#: How the bag is split: stored in each file's session record.
SPLIT_PARAMETERS = ('max_bag_duration_s', 'max_bag_size_bytes')
DISCOVERY_PERIOD_S = 0.1   # rosbag2's default topic polling interval
#: How long a channel's creation waits for the graph to list the writer of its first message.
GRAPH_WAIT_S = 1.0
#: Reader history of every recorded topic: a stall of the recorder (seconds of 50 Hz topics)
#: must not overflow it.
RECORDER_DEPTH = 1000


class RecorderNode(LoopNode):
    """Record topics into one bag; see the module doc."""

    NAME = 'recorder'
    REPORT = RecorderReport

    def __init__(self):
        super().__init__(self.NAME, 'bag recorder', namespace=contract.NAMESPACE)
        self.report.node += ': bag recorder'     # its own statuses in the bag: findable
        p = self.p
        if not p['bag_dir']:
            raise ParamError('parameter bag_dir is required (the bag directory to create)')
        if p['nice'] and not p['realtime_priority']:
            os.nice(p['nice'])
        self.bag_dir = self.report.bag_dir = p['bag_dir']
        self._use_sim_time = bool(self.get_parameter('use_sim_time').value)
        self._subs: Dict[str, object] = {}
        self._pending: Dict[str, Optional[str]] = {}   # topic -> type (None: from the graph)
        session = recorder_session(p['session_metadata'], self.get_fully_qualified_name(),
                                   self.bag_dir, {k: p[k] for k in SPLIT_PARAMETERS})
        self.bag = Recording(p, session, self.report, self._failed)
        if self.bag.ok:
            self.status.set(OK, f'recording to {self.bag_dir}')
        self.writer = self.bag.writer
        if self.bag.ok:
            for name in p['topics']:
                topic = self.resolve_topic_name(name)
                self._pending[topic] = contract.type_of(name, self.get_namespace())
                if self._pending[topic] is not None:
                    self._subscribe(topic, self._pending[topic])
            self._discovery = self.create_timer(DISCOVERY_PERIOD_S, self._discover,
                                                clock=self.steady)
            self.create_timer(p['flush_period_s'], self.bag.flush, clock=self.steady)
            self.get_logger().info(f'recording {len(self._pending)} topics to '
                                   f'{self.writer.file_path}')
        # On the steady clock: under use_sim_time, /clock may not run yet (lock-step waits
        # for the recorder's status before it starts the clock).
        self.status_timer()

    def _subscribe(self, topic: str, type_name: str) -> None:
        events = SubscriptionEventCallbacks(message_lost=self._on_lost)
        self._subs[topic] = self.create_subscription(
            message_class(type_name), topic, functools.partial(self._on_message, topic,
                                                               type_name),
            ros_qos.control_qos(RECORDER_DEPTH), raw=True, event_callbacks=events)

    def _on_lost(self, info) -> None:
        """Count messages the middleware reports lost before this node took them."""
        self.report.lost_in_transport += int(info.total_count_change)

    def _discover(self) -> None:
        """Create channels as publishers appear; subscribe to topics typed by the graph."""
        if not self.bag.ok:
            return
        missing = [t for t in self._pending if not self.writer.has_topic(t)]
        if not missing:
            self._discovery.cancel()
            return
        graph = None
        for topic in missing:
            type_name = self._pending[topic]
            if type_name is None:
                graph = dict(self.get_topic_names_and_types()) if graph is None else graph
                if topic not in graph:
                    continue
                type_name = self._pending[topic] = graph[topic][0]
                try:
                    self._subscribe(topic, type_name)
                except BagError as exc:
                    self.get_logger().warning(f'not recording {topic}: {exc}')
                    del self._pending[topic]
                    continue
            if self.get_publishers_info_by_topic(topic):
                self._create_channel(topic, type_name)

    def _create_channel(self, topic: str, type_name: str) -> None:
        infos = self.get_publishers_info_by_topic(topic)
        # A first message can come before the graph has heard of its writer (data and
        # discovery are separate; seen under load): the graph, kept by rmw's own thread,
        # is asked again for a while, so the channel gets the offered QoS.
        deadline = time.monotonic() + GRAPH_WAIT_S
        while not infos and time.monotonic() < deadline:
            time.sleep(0.005)
            infos = self.get_publishers_info_by_topic(topic)
        hashes = {str(i.topic_type_hash) for i in infos if i.topic_type_hash.version > 0}
        self.bag.add_topic(topic, type_name, [profile_to_dict(i.qos_profile) for i in infos],
                           hashes.pop() if len(hashes) == 1 else None)

    def _on_message(self, topic: str, type_name: str, data: bytes, info: dict) -> None:
        log_time = (self.now_ns() if self._use_sim_time
                    else info.get('received_timestamp') or time.time_ns())
        self.bag.write(topic, data, log_time, info.get('source_timestamp') or log_time,
                       info.get('publication_sequence_number') or 0,
                       lambda: self._create_channel(topic, type_name))

    def _failed(self, message: str) -> None:
        self.get_logger().error(f'recording failed: {message}; the control loop is not '
                                'affected (the recorder is a separate process)')
        self.status.set(ERROR, message)

    def refresh_report(self) -> None:
        if not hasattr(self, 'bag'):        # the bag failed to open: nothing to count
            return
        self.bag.fill()
        # The writers matched per topic: `erva run` starts the loop only when all are.
        self.report.publishers = {t: s.get_publisher_count() for t, s in self._subs.items()}
        self.report.subscribers[contract.DIAGNOSTICS] = self.pub_diag.get_subscription_count()

    def stop(self, stopping, limit_s: float) -> int:
        """Take what was delivered already, then finish the bag; exit 1 if it failed.

        Timers stop first (a status or a flush now would only come between the
        messages).  The drain ends once three waits of 50 ms in a row took nothing:
        counted, not timed, so a recorder starved by other work still takes everything
        queued when it runs again; or after 5 s (publishers that never stop).
        """
        for timer in list(self.timers):
            timer.cancel()
        end, quiet = time.monotonic() + 5.0, 0
        while quiet < 3 and time.monotonic() < end and not stopping():
            before = self.report.received
            self.executor.spin_once(timeout_sec=0.05)
            quiet = quiet + 1 if self.report.received == before else 0
        meta = self.bag.close()
        if meta is not None:
            lost = self.report.lost_in_transport
            self.get_logger().info(f'wrote {meta["message_count"]} messages to {self.bag_dir}'
                                   + (f'; the middleware reported {lost} messages lost'
                                      if lost else ''))
        self.status.publish(final=True)
        return 1 if self.bag.error else 0


def main(args=None) -> int:
    """Run recorder_node until shutdown."""
    return run_node(RecorderNode, args)


if __name__ == '__main__':
    import sys
    sys.exit(main())
