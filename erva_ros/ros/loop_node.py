"""The skeleton every erva node is built on: written once, so a node file holds only its wiring.

:class:`LoopNode` is a ROS 2 managed (lifecycle) node that owns what each node needs
besides its own core:

* its parameters, declared from its schema (:data:`erva_ros.core.settings.schemas.SCHEMAS`,
  the node's name is the key) with descriptors: ``self.p`` (a bad value stops the node
  at start-up with one line); the live ones (dynamic, docs/live.md) are checked by
  :meth:`on_parameters` when set, and ``self.p`` follows them;
* its typed report (:mod:`erva_ros.core.reports`) and the :class:`StatusReporter` that
  publishes it on ``/diagnostics`` in every lifecycle state: ``self.report``,
  ``self.status``;
* counted lifecycle publishers (``published`` per topic in the report: the session's
  loss accounting; they publish only while the node is active), raw subscriptions whose
  callbacks get the CDR bytes and the middleware's reception time (dropped unless
  active) and loop timers (idle unless active);
* the steady clock, the input rejections (counted, logged at a limited rate), its
  real-time priority (applied at the first activation) and the one shutdown protocol
  (:meth:`stop`).

Lifecycle (rclpy.lifecycle, the services ``ros2 lifecycle`` uses): the node starts
*unconfigured*; ``configure`` builds its core, publishers, subscriptions and timers
(:meth:`configure`), ``activate`` lets it act, ``deactivate`` stops it acting (no
command, no sample goes out; inputs are dropped), ``cleanup`` takes back what configure
built.  With the parameter ``autostart`` (default true) the node configures and
activates itself at start-up, as `ros2 run` users expect; `erva run` and the launch
file's ``autostart:=false`` drive the transitions instead (docs/live.md).

Hooks a node may override: :meth:`on_parameters`, :meth:`configure`, :meth:`activate`,
:meth:`deactivate`,
:meth:`refresh_report` (bring the report's figures up to date before a status goes
out), :meth:`started` (once active at its priority, e.g. start threads) and :meth:`stop`
(the shutdown protocol; the recorder finishes its bag there).
"""

import gc
import time
from typing import Callable, List, Optional, Type

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn

from erva_ros.core import topics
from erva_ros.core.levels import ERROR
from erva_ros.core.loop.status import StatusReporter
from erva_ros.core.model.params import ParamError
from erva_ros.core.loop.validation import Rejections, StampWindow
from erva_ros.core.settings.schemas import SCHEMAS
from erva_ros.core.reports import NodeReport
from erva_ros.core.startup import process_age_s
from erva_ros.ros import qos as ros_qos
from erva_ros.ros.parameters import declare_node_parameters, on_set_callback
from erva_ros.ros.realtime import set_fifo_priority

#: The spin loop and the acknowledgement wait wake at least this often (s).
SLICE_S = 0.1


class CountedPublisher:
    """A (lifecycle) publisher that counts what it published, for the loss accounting."""

    def __init__(self, publisher):
        self.publisher = publisher
        self.topic = publisher.topic_name
        self.count = 0

    def publish(self, msg) -> None:
        """Publish ``msg`` (a message or its CDR bytes) and count it (only while active)."""
        if not getattr(self.publisher, 'is_activated', True):
            return
        self.publisher.publish(msg)
        self.count += 1

    def get_subscription_count(self) -> int:
        """Return the subscriptions this writer has matched."""
        return self.publisher.get_subscription_count()


class LoopNode(LifecycleNode):
    """An erva node: parameters, report, status, lifecycle, publishers, shutdown (module doc)."""

    #: The node's report type.
    REPORT: Type[NodeReport] = NodeReport

    #: The node's name (the key of its schema).
    NAME = ''

    def __init__(self, name: str = '', hardware_id: str = '', namespace: Optional[str] = None):
        name = name or self.NAME
        super().__init__(name, **({'namespace': namespace} if namespace else {}))
        self._refuse_unavailable_transitions()
        self.p = declare_node_parameters(self, name)
        if SCHEMAS[name].live():     # after declaring: rclpy calls these on every set
            self.add_on_set_parameters_callback(on_set_callback(SCHEMAS[name],
                                                                self.on_parameters))
            self.add_post_set_parameters_callback(self._parameters_set)
        self.autostart = self.p.get('autostart', True)
        self.active = False
        self.configured = False
        self.config_error: Optional[ParamError] = None
        self._built: List = []            # (destroy, entity) of what configure made
        self._prioritised = False
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.scheduling = 'off'
        self.report = self.REPORT(node=self.get_fully_qualified_name(), hardware_id=hardware_id,
                                  session=self.p.get('session_id', ''))
        # A status goes out whenever a reader of it or of a counted publisher matches:
        # `erva run` learns that the node is up, and that its writers have their
        # readers, as soon as discovery says so, not at the next period.
        self.pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                              ros_qos.diagnostics_qos(),
                                              event_callbacks=self._matched_events())
        self.status = StatusReporter(self.report, self.pub_diag.publish, self.now_ns,
                                     self._refresh)
        self.rejections = Rejections(self.get_logger().warning, time.monotonic,
                                     self.p.get('reject_log_period_s', 1.0))
        #: SCHED_FIFO priority run_node gives the node's threads once it is built: the
        #: loop's in real time; 0 in lock-step, which runs flat out and would starve the
        #: other processes at real-time priority.
        self.realtime_priority = (self.p.get('realtime_priority', 0)
                                  if self.p.get('mode', 'realtime') == 'realtime' else 0)
        self.report.lifecycle = 'unconfigured'
        self.report.message = 'unconfigured'
        self._status_timer = None
        if 'diagnostics_period_s' in self.p:    # seen in every state; configure may refine it
            self.status_timer()

    def _refuse_unavailable_transitions(self) -> None:
        """Answer a change_state request the current state has no transition for with failure.

        rclpy's own service raises in the executor for one (RCLError: "Transition is not
        registered"), which ends the node: a stray ``ros2 lifecycle set`` -- or another
        session's request to a node of the same name -- would kill it.  rclcpp answers
        success = false; so does this.
        """
        service = getattr(self, '_service_change_state', None)
        if service is None:
            return
        answer = service.callback

        def change_state(request, response):
            available = {t[0] for t in self._state_machine.available_transitions}
            if not request.transition.label and request.transition.id not in available:
                self.get_logger().warning(
                    f'refused lifecycle transition {request.transition.id}: not available '
                    f'in state {self._state_machine.current_state[1]}')
                response.success = False
                return response
            return answer(request, response)
        service.callback = change_state

    # -- building blocks ---------------------------------------------------------------
    def now_ns(self) -> int:
        """Return the node's clock (ns): wall time, or simulated time under use_sim_time."""
        return self.get_clock().now().nanoseconds

    def publisher(self, msg_type, topic: str, qos=None) -> CountedPublisher:
        """Return a counted lifecycle publisher of a loop topic (history: ``publisher_history_s``).

        It publishes only while the node is active; configure makes it, cleanup takes it back.
        """
        if qos is None:
            qos = ros_qos.publisher_qos(self.p['publisher_history_s'], self.p['ts'])
        raw = self.create_lifecycle_publisher(msg_type, topic, qos,
                                              event_callbacks=self._matched_events())
        if self.active:               # made while active (a legacy node): enabled too
            raw.on_activate(None)
        pub = CountedPublisher(raw)
        self.status.publishers.append(pub)
        self._built.append((self._destroy_publisher, pub))
        return pub

    def _matched_events(self) -> PublisherEventCallbacks:
        """Return event callbacks that publish the status when a reader matches."""
        def on_matched(info) -> None:
            if info.current_count_change > 0 and hasattr(self, 'status'):
                self.status.publish()
        return PublisherEventCallbacks(matched=on_matched)

    def subscribe(self, msg_type, topic: str, callback: Callable[[bytes, int], None],
                  qos=None):
        """Subscribe raw: ``callback(data, rx_ns)`` with the middleware's reception time.

        Messages that arrive while the node is not active are dropped.
        """
        def on_message(data: bytes, info) -> None:
            if self.active:
                callback(data, info.get('received_timestamp') or time.time_ns())
        sub = self.create_subscription(msg_type, topic, on_message,
                                       qos or ros_qos.control_qos(), raw=True)
        self._built.append((self.destroy_subscription, sub))
        return sub

    def timer(self, period_s: float, callback: Callable[[], None], clock=None):
        """Return a loop timer: it calls ``callback`` only while the node is active."""
        def on_timer() -> None:
            if self.active:
                callback()
        t = self.create_timer(period_s, on_timer, **({'clock': clock} if clock else {}))
        self._built.append((self.destroy_timer, t))
        return t

    def status_timer(self, busy_window_s: float = 0.0, period_s: Optional[float] = None):
        """Publish the status every ``diagnostics_period_s`` (see StatusReporter.on_timer).

        In every lifecycle state; one such timer per node (a second call replaces it).
        """
        period = period_s or self.p['diagnostics_period_s']
        if self._status_timer is not None:
            self.destroy_timer(self._status_timer)

        def on_timer() -> None:     # before configure: no core to ask yet
            if self.configured:
                self.on_status_timer(busy_window_s)
            else:
                self.status.on_timer(busy_window_s)
        self._status_timer = self.create_timer(period, on_timer, clock=self.steady)
        return self._status_timer

    def destroy_node(self) -> None:
        """Destroy the node, and the lifecycle state machine that holds its handle.

        rclpy's LifecycleNode never frees its state machine, which keeps the rcl node
        alive: the participant then would not leave the graph before the process ends
        (peers see it go only when its lease runs out, 20 s).
        """
        super().destroy_node()
        self._state_machine.destroy_when_not_in_use()

    def _destroy_publisher(self, pub: CountedPublisher) -> None:
        self.status.publishers.remove(pub)
        self.destroy_lifecycle_publisher(pub.publisher)

    # -- lifecycle ---------------------------------------------------------------------
    def on_configure(self, state) -> TransitionCallbackReturn:
        """Build the node's core, publishers, subscriptions and timers (:meth:`configure`)."""
        self.report.startup.setdefault('configuring', process_age_s())
        try:
            self.configure()
        except ParamError as exc:       # one line; the node stays unconfigured
            self.config_error = exc
            self.get_logger().error(f'configure failed: {exc}')
            self._take_back()
            self.status.set(ERROR, f'configure failed: {exc}')
            return TransitionCallbackReturn.FAILURE
        # What configure built lives as long as the node: out of the collector's way, so
        # a collection during the loop scans only new objects.
        gc.collect()
        gc.freeze()
        self.configured = True
        self.report.startup['configured'] = process_age_s()
        self._state('inactive')
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state) -> TransitionCallbackReturn:
        """Enable the publishers, then let the node act (:meth:`activate`)."""
        result = super().on_activate(state)
        if not self._prioritised:   # after the build: a FIFO thread building CasADi
            self._prioritised = True    # functions would starve the other nodes
            self.prioritise()
        self.active = True
        self.activate()
        self.report.startup.setdefault('activated', process_age_s())
        self._state('active')
        return result

    def on_deactivate(self, state) -> TransitionCallbackReturn:
        """Stop acting (:meth:`deactivate`): inputs dropped, nothing published."""
        self.deactivate()
        self.active = False
        result = super().on_deactivate(state)
        self._state('inactive')
        return result

    def on_cleanup(self, state) -> TransitionCallbackReturn:
        """Take back what configure built."""
        self._take_back()
        self.configured = False
        self._state('unconfigured')
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state) -> TransitionCallbackReturn:
        """Stop acting; the process ends with :meth:`stop` (run_node)."""
        if self.active:
            self.on_deactivate(state)
        return TransitionCallbackReturn.SUCCESS

    def _take_back(self) -> None:
        for destroy, entity in reversed(self._built):
            destroy(entity)
        self._built.clear()

    def _state(self, label: str) -> None:
        self.report.lifecycle = label
        self.status.publish()

    def prioritise(self) -> None:
        """Give the node's threads ``realtime_priority`` (SCHED_FIFO), then :meth:`started`."""
        self.scheduling = set_fifo_priority(self.realtime_priority, self.get_logger().warning)
        if self.realtime_priority > 0 and self.scheduling.startswith('SCHED_FIFO'):
            self.get_logger().info(f'running at {self.scheduling}')
        self.started()

    def start_up(self) -> None:
        """``autostart``: configure and activate now; raise a configure error (ParamError)."""
        self.trigger_configure()
        if self.config_error is not None:
            raise self.config_error
        self.trigger_activate()

    def on_status_timer(self, busy_window_s: float) -> None:
        """Publish the status when due (a node may check its health here first)."""
        self.status.on_timer(busy_window_s)

    def stamp_window(self, lockstep: bool = False) -> StampWindow:
        """Return the node's input stamp window (``max_stamp_lead_s``, ``max_stamp_age_s``).

        In lock-step the node's clock is /clock, which may reach a node after the sample
        it stamps: two periods more lead are allowed there.
        """
        lead = self.p['max_stamp_lead_s'] + (2 * self.p['ts'] if lockstep else 0.0)
        return StampWindow(int(round(lead * 1e9)), int(round(self.p['max_stamp_age_s'] * 1e9)))

    def reject(self, topic: str, why: str) -> None:
        """Count and (at a limited rate) log a rejected input message."""
        self.rejections.reject(topic, why)

    def rejected(self, topic: str) -> int:
        """Return how many messages of ``topic`` were rejected."""
        return self.rejections.counts.get(topic, 0)

    def _parameters_set(self, parameters) -> None:
        """Follow live parameters rclpy set (and announced on /parameter_events) in ``self.p``."""
        for p in parameters:
            self.p[p.name] = p.value
        self.parameters_set([p.name for p in parameters])

    # -- hooks -------------------------------------------------------------------------
    def on_parameters(self, values) -> None:
        """Check live parameters about to be set, each checked by its spec already.

        Raise ParamError to refuse them all (the reason goes back to the requester).
        """

    def parameters_set(self, names) -> None:
        """React after live parameters ``names`` were set (``self.p`` has their values)."""

    def configure(self) -> None:
        """Build the core, publishers, subscriptions and timers (raise ParamError if bad)."""

    def activate(self) -> None:
        """Start acting (publishers are enabled, inputs flow from now on)."""

    def deactivate(self) -> None:
        """Stop acting (publishers are disabled and inputs dropped right after)."""

    def _refresh(self) -> None:
        self.report.scheduling = self.scheduling
        if self.configured:
            self.refresh_report()

    def refresh_report(self) -> None:
        """Bring the report's figures up to date (called before each status goes out)."""

    def started(self) -> None:
        """Start what runs once the node is built, first active and at its priority."""

    def stop(self, stopping: Callable[[], bool], limit_s: float) -> int:
        """Stop: publish the final status, then wait until all of it is delivered.

        Publishes the report with ``final`` set (its final counts), then waits, bounded
        by ``limit_s`` and in short slices (``stopping()`` true: a second signal, stop
        waiting), until every subscriber acknowledged what this node's counted
        publishers and status wrote.  Returns the process's exit status.
        """
        self.status.publish(final=True)
        self.acked = wait_for_acks([p.publisher for p in self.status.publishers]
                                   + [self.pub_diag], stopping, limit_s)
        return 0


def wait_for_acks(publishers: List, stopping: Callable[[], bool], limit_s: float) -> bool:
    """Return True once every subscriber of ``publishers`` acknowledged all they wrote.

    False after ``limit_s`` or once ``stopping()`` (a second signal) is true.
    """
    deadline = time.monotonic() + limit_s
    for pub in publishers:
        while not stopping():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            if pub.wait_for_all_acked(Duration(nanoseconds=int(min(left, SLICE_S) * 1e9))):
                break
        else:
            return False
    return True


__all__ = ['SLICE_S', 'CountedPublisher', 'LoopNode', 'wait_for_acks']
