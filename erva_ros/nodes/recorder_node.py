"""recorder_node: record the session's topics into a rosbag2-compatible MCAP bag.

Subscribes (QoS ``ros_qos.control_qos``: reliable, volatile, keep-last 10) to every
topic of the live contract -- the ``/erva`` topics resolved against this node's
namespace, ``/diagnostics`` and ``/clock`` -- and writes each message's CDR bytes as
received (raw subscription, no re-serialisation) with the times rosbag2 Jazzy records:
log time = reception time (the middleware's ``received_timestamp``; node time under
``use_sim_time``), publish time = the publisher's ``source_timestamp``.  A topic's
channel is created when its first publisher is discovered (or its first message
arrives), with the QoS its publishers offer and their RIHS01 type hash, as
``ros2 bag record`` does.

Parameters (read at start-up):

==================  ============  =========================================================
``bag_dir``         string        bag directory to create (must not exist), e.g.
                                  ``bags/20261122T101500Z_paper``
``topics``          string[]      topics to record; relative names resolve against the
                                  node namespace (default: the whole contract)
``session_metadata`` string       JSON object stored as the ``erva_session`` MCAP record;
                                  version, git commit, host and start time are added
``chunk_size``      int (B)       close a chunk at this size (default 786432, libmcap's)
``flush_period_s``  double (s)    close and hand the chunk to the OS at least this often:
                                  at most this much is lost if the process is killed
``compression``     string        MCAP chunk compression: none (rosbag2 default), zstd, lz4
``fsync``           bool          also fsync at each flush (survives power loss)
``diagnostics_period_s`` double   period of the recorder's own /diagnostics status
``realtime_priority`` int         SCHED_FIFO priority of every thread of the recorder
                                  (its DDS receive threads too); 0 = normal scheduling.
                                  `erva run` sets it below the loop's, so the record of a
                                  real-time loop is not starved by other work on the
                                  machine while the loop still goes first
``nice``            int           CPU niceness added to this process with normal
                                  scheduling (default 10)
==================  ============  =========================================================

What survives a recorder stall: the loop's publishers keep ``publisher_history_s``
(10 s) of samples for reliable repair, and each subscription here keeps
``RECORDER_DEPTH`` samples, so a recorder stopped for seconds (SIGSTOP, a slow disk)
receives everything once it runs again.  The status on ``/diagnostics`` (every
``diagnostics_period_s``) reports per topic ``count:<topic>`` (messages written) and
``publishers:<topic>`` (writers this subscription has matched: `erva run` starts the
loop only when every one is), and ``lost_in_transport`` (samples the middleware
reports lost before the recorder took them).

SIGINT/SIGTERM: pending messages are taken, the file is finished (summary, indexes,
metadata.yaml) and the node exits 0.  A bag that cannot be written (directory exists
or is not writable, disk full) is reported as one log line and an ERROR status on
``/diagnostics``; the node keeps running without recording and exits 1.  Being its
own process, the recorder cannot stall or stop the control loop.
"""

import faulthandler
import functools
import json
import os
import signal
import sys
import threading
import time
from typing import Dict, List, Optional

import rclpy
from rclpy.exceptions import NameValidationException, ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType)

from diagnostic_msgs.msg import DiagnosticArray

from erva_ros.core import topics as contract
from erva_ros.ros import diagnostics as diag, qos as ros_qos
from erva_ros.core.bag import BagError
from erva_ros.core.bag.qos import profile_to_dict
from erva_ros.ros.bag_messages import message_class
from erva_ros.core.bag.session import session_metadata
from erva_ros.core.bag.writer import BagWriter, COMPRESSIONS, DEFAULT_CHUNK_SIZE
from erva_ros.ros.realtime import MAX_PRIORITY, set_fifo_priority

#: Default topics: relative names resolve against the node namespace (default /erva).
DEFAULT_TOPICS = [contract.STATE, contract.SPRUNG_ACCEL, contract.GENERATOR,
                  contract.ROAD_HEIGHT, contract.ROAD_PREVIEW, contract.DAMPING_CMD,
                  contract.DIAGNOSTICS, contract.CLOCK]
#: Type of each contract topic by its name as written in topics.py.
CONTRACT_TYPES = {name: contract.TOPIC_TYPES[f'{contract.NAMESPACE}/{name}']
                  for name in DEFAULT_TOPICS if not name.startswith('/')}
CONTRACT_TYPES.update({name: contract.TOPIC_TYPES[name]
                       for name in DEFAULT_TOPICS if name.startswith('/')})
DISCOVERY_PERIOD_S = 0.1   # rosbag2's default topic polling interval
#: Reader history of every recorded topic: a stall of the recorder (seconds of 50 Hz topics)
#: must not overflow it.
RECORDER_DEPTH = 1000


def _range(lo, hi, integer=False):
    if integer:
        return {'integer_range': [IntegerRange(from_value=lo, to_value=hi, step=1)]}
    return {'floating_point_range': [FloatingPointRange(from_value=lo, to_value=hi)]}


#: Parameters: name -> (default, type, description, range); see the module doc.
PARAMETERS = {
    'bag_dir': ('', ParameterType.PARAMETER_STRING,
                'bag directory to create (must not exist)', {}),
    'topics': (list(DEFAULT_TOPICS), ParameterType.PARAMETER_STRING_ARRAY,
               'topics to record; relative names resolve against the node namespace', {}),
    'session_metadata': ('{}', ParameterType.PARAMETER_STRING,
                         'JSON object stored as the erva_session MCAP metadata record', {}),
    'chunk_size': (DEFAULT_CHUNK_SIZE, ParameterType.PARAMETER_INTEGER,
                   'close an MCAP chunk at this size (bytes)',
                   _range(1024, 64 * 1024 * 1024, integer=True)),
    'flush_period_s': (0.5, ParameterType.PARAMETER_DOUBLE,
                       'close the chunk and hand it to the OS at least this often (s)',
                       _range(0.01, 60.0)),
    'compression': ('none', ParameterType.PARAMETER_STRING,
                    'MCAP chunk compression: ' + ', '.join(COMPRESSIONS), {}),
    'fsync': (False, ParameterType.PARAMETER_BOOL, 'fsync the file at every flush', {}),
    'diagnostics_period_s': (1.0, ParameterType.PARAMETER_DOUBLE,
                             'period of the recorder status on /diagnostics (s)',
                             _range(0.1, 60.0)),
    'nice': (10, ParameterType.PARAMETER_INTEGER,
             'CPU niceness added to the recorder process with normal scheduling',
             _range(0, 19, integer=True)),
    'realtime_priority': (0, ParameterType.PARAMETER_INTEGER,
                          'SCHED_FIFO priority of the recorder\'s threads (0: normal '
                          'scheduling); below the loop\'s', _range(0, MAX_PRIORITY, integer=True)),
}


class RecorderNode(Node):
    """Record topics into one bag; see the module doc for parameters and behaviour."""

    def __init__(self):
        super().__init__('recorder', namespace=contract.NAMESPACE)
        p = {name: self.declare_parameter(name, default, ParameterDescriptor(
                 name=name, type=ptype, description=doc, read_only=True, **rng)).value
             for name, (default, ptype, doc, rng) in PARAMETERS.items()}
        if not p['bag_dir']:
            raise ValueError('parameter bag_dir is required (the bag directory to create)')
        if p['compression'] not in COMPRESSIONS:
            raise ValueError(f'parameter compression={p["compression"]!r}: choose from '
                             f'{", ".join(COMPRESSIONS)}')
        if p['nice'] and not p['realtime_priority']:
            os.nice(p['nice'])
        #: Applied once the node exists (main): its DDS threads are running by then.
        self.realtime_priority = p['realtime_priority']
        self.bag_dir = p['bag_dir']
        session = self._session(p['session_metadata'])
        self._use_sim_time = bool(self.get_parameter('use_sim_time').value)

        self.error: Optional[str] = None
        self.received = 0
        self.lost = 0            # taken but not written (after a write error)
        self.lost_in_transport = 0
        self.writer: Optional[BagWriter] = None
        self._subs: Dict[str, object] = {}
        self._pending: Dict[str, Optional[str]] = {}   # topic -> type (None: from graph)
        self._status_pub = self.create_publisher(DiagnosticArray, contract.DIAGNOSTICS,
                                                 ros_qos.diagnostics_qos())
        self._status_seq = 0
        # Timers on the steady clock: under use_sim_time, /clock may not run yet (lock-step
        # waits for the recorder's status before it starts the clock).
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        try:
            self.writer = BagWriter(self.bag_dir, chunk_size=p['chunk_size'],
                                    compression=p['compression'],
                                    flush_period_s=p['flush_period_s'], fsync=p['fsync'],
                                    session=session, custom_data=session)
        except BagError as exc:
            self._fail(str(exc))
        if self.writer is not None:
            self._start(p['topics'], p['flush_period_s'])
        self.create_timer(p['diagnostics_period_s'], self._publish_status, clock=self._steady)

    def _start(self, requested: List[str], flush_period_s: float) -> None:
        """Subscribe to the requested topics whose type is known; discover the others."""
        for name in requested:
            topic = self.resolve_topic_name(name)
            self._pending[topic] = CONTRACT_TYPES.get(name) or contract.TOPIC_TYPES.get(topic)
            if self._pending[topic] is not None:
                self._subscribe(topic, self._pending[topic])
        self._discovery_timer = self.create_timer(DISCOVERY_PERIOD_S, self._discover,
                                                  clock=self._steady)
        self.create_timer(flush_period_s, self._flush, clock=self._steady)
        self.get_logger().info(f'recording {len(self._pending)} topics to '
                               f'{self.writer.file_path}')

    # -- session metadata --------------------------------------------------------------
    def _session(self, text: str) -> Dict[str, str]:
        try:
            given = json.loads(text) if text.strip() else {}
        except ValueError as exc:
            raise ValueError(f'parameter session_metadata is not JSON ({exc})') from None
        if not isinstance(given, dict):
            raise ValueError('parameter session_metadata must be a JSON object')
        base = session_metadata(str(given.get('scenario', '')),
                                extra={'recorder': self.get_fully_qualified_name(),
                                       'bag_dir': self.bag_dir})
        for key in ('parameters', 'controller', 'seed', 'command'):
            base.pop(key, None)  # only the caller knows these
        base.update({str(k): v if isinstance(v, str) else json.dumps(v, sort_keys=True)
                     for k, v in given.items()})
        return base

    # -- subscriptions -----------------------------------------------------------------------
    def _subscribe(self, topic: str, type_name: str) -> None:
        cls = message_class(type_name)
        events = SubscriptionEventCallbacks(message_lost=self._on_lost)
        self._subs[topic] = self.create_subscription(
            cls, topic, functools.partial(self._on_message, topic, type_name),
            ros_qos.control_qos(RECORDER_DEPTH), raw=True, event_callbacks=events)

    def _on_lost(self, info) -> None:
        """Count messages the middleware reports lost before this node took them."""
        self.lost_in_transport += int(info.total_count_change)

    def _discover(self) -> None:
        """Create channels as publishers appear; subscribe to topics typed by the graph."""
        if self.writer is None or self.error:
            return
        missing = [t for t in self._pending if not self.writer.has_topic(t)]
        if not missing:
            self._discovery_timer.cancel()
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
        offered = [profile_to_dict(i.qos_profile) for i in infos]
        hashes = {str(i.topic_type_hash) for i in infos if i.topic_type_hash.version > 0}
        type_hash = hashes.pop() if len(hashes) == 1 else None  # None: the share .json one
        try:
            self.writer.add_topic(topic, type_name, offered, type_hash)
        except BagError as exc:
            self._fail(str(exc))

    def _on_message(self, topic: str, type_name: str, data: bytes, info: dict) -> None:
        self.received += 1
        if self.error or self.writer is None:
            self.lost += 1
            return
        if self._use_sim_time:
            log_time = self.get_clock().now().nanoseconds
        else:
            log_time = info.get('received_timestamp') or time.time_ns()
        publish_time = info.get('source_timestamp') or log_time
        try:
            if not self.writer.has_topic(topic):
                self._create_channel(topic, type_name)
            self.writer.write(topic, data, log_time, publish_time,
                              info.get('publication_sequence_number') or 0)
        except BagError as exc:
            self.lost += 1
            self._fail(str(exc))

    def _flush(self) -> None:
        if self.writer is not None and not self.error:
            try:
                self.writer.maybe_flush()
            except BagError as exc:
                self._fail(str(exc))

    # -- health --------------------------------------------------------------------------
    def _fail(self, message: str) -> None:
        if self.error is None:
            self.error = message
            self.get_logger().error(f'recording failed: {message}; the control loop is not '
                                    'affected (the recorder is a separate process)')
            self._publish_status()

    def _publish_status(self) -> None:
        values: Dict[str, object] = {'bag_dir': self.bag_dir, 'received': self.received,
                                     'lost': self.lost,
                                     'lost_in_transport': self.lost_in_transport}
        if self.writer is not None:
            counts = self.writer.counts
            values.update({'written': self.writer.message_count,
                           'bytes': self.writer.bytes_written, 'flushes': self.writer.flushes,
                           'topics': len(counts)})
            # Per topic, so `erva run` can wait until the bag holds what was published,
            # and start the loop only when every writer is matched.
            values.update({f'count:{topic}': n for topic, n in sorted(counts.items())})
            values.update({f'publishers:{topic}': sub.get_publisher_count()
                           for topic, sub in sorted(self._subs.items())})
        self._status_seq += 1
        values.update({'status_seq': self._status_seq,
                       'subscribers:' + contract.DIAGNOSTICS:
                           self._status_pub.get_subscription_count(),
                       'scheduling': getattr(self, 'scheduling', 'off')})
        level, message = ((diag.ERROR, self.error) if self.error
                          else (diag.OK, f'recording to {self.bag_dir}'))
        status = diag.status_msg(f'{self.get_name()}: bag recorder', level, message, values,
                                 'erva')
        self._status_pub.publish(diag.array_msg(self.get_clock().now().nanoseconds, [status]))

    # -- shutdown --------------------------------------------------------------------------
    def drain(self, executor, quiet_spins: int = 3, limit_s: float = 5.0) -> None:
        """Take messages already delivered to this process before the file is closed.

        Timers first stop (a status or a flush now would only come between the messages).
        The drain ends once ``quiet_spins`` waits of 50 ms in a row took nothing: counted,
        not timed, so a recorder starved by other work still takes everything queued when
        it runs again; or after ``limit_s`` (publishers that never stop).
        """
        for timer in list(self.timers):
            timer.cancel()
        end = time.monotonic() + limit_s
        quiet = 0
        while quiet < quiet_spins and time.monotonic() < end:
            before = self.received
            executor.spin_once(timeout_sec=0.05)
            quiet = quiet + 1 if self.received == before else 0

    def finish(self) -> int:
        """Close the bag (summary, indexes, metadata.yaml); return the exit code."""
        if self.writer is not None and not self.error:
            try:
                meta = self.writer.close()
                lost = (f'; the middleware reported {self.lost_in_transport} messages lost'
                        if self.lost_in_transport else '')
                self.get_logger().info(f'wrote {meta["message_count"]} messages to '
                                       f'{self.writer.bag_dir}{lost}')
            except BagError as exc:
                self._fail(str(exc))
        return 1 if self.error else 0


def main(args=None) -> int:
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    faulthandler.register(signal.SIGUSR1)    # stacks on demand, as every node (ros/runtime)
    node = None
    rc = 0
    try:
        try:
            node = RecorderNode()
        except (ValueError, ParameterException, NameValidationException) as exc:
            print(f'recorder_node: error: {exc}', file=sys.stderr)
            return 2
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        node.scheduling = set_fifo_priority(node.realtime_priority, node.get_logger().warning)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
        node.drain(executor)
        rc = node.finish()
    except (KeyboardInterrupt, ExternalShutdownException):
        rc = node.finish() if node is not None else 0
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return rc


if __name__ == '__main__':
    sys.exit(main())
