"""What ecu_bridge_node does, without ROS: commands in, the CAN thread, the latencies.

:class:`BridgeLoop` joins :class:`~erva_ros.core.hil.bridge.BridgeCore` (watchdog, bus,
cycles), :class:`~erva_ros.core.hil.messages.EcuMessages` and the bridge's latency
figures.  The node hands it its publish functions and drives it: :meth:`take_command`
for each ``damping_cmd`` (in the subscription's thread), :meth:`start` the CAN thread
(ECU frames → messages as they arrive, the watchdog every Ts/4), :meth:`fill` before
each status.  With ``can_log`` every raw frame also goes to a CAN trace
(:mod:`erva_ros.core.hil.can_trace`), finished by :meth:`close`.

:attr:`BridgeLoop.active` follows the node's lifecycle state.  While it is false no
command is taken and **nothing goes out on CAN** (no watchdog, no safe frame): the ECU
then goes passive by its own rule (docs/hil.md §8: the plan runs out, or its receive
timeout).  The ECU's frames are still read, so their E2E counters stay in step, but
nothing is published.
"""

import threading
import time
from typing import Callable, Dict, Iterable, List, Optional, Tuple

from erva_ros.core import contract
from erva_ros.core.hil.bridge import BridgeCore, EcuCycle, SensorFrame
from erva_ros.core.hil.can_trace import CanTrace
from erva_ros.core.hil.latency import LatencyStats
from erva_ros.core.hil.messages import EcuMessages
from erva_ros.core.levels import ERROR
from erva_ros.core.model.params import ERVAParams
from erva_ros.core.reports import Timing
from erva_ros.core.settings.loop import command_delay_ns

#: Commands beyond this magnitude (Ns/m) are absurd (a unit error), not just out of range:
#: refused; those in it are clamped to the generator's range (counted).
ABSURD_C_E = 1e6
#: The latencies: DDS / kernel receive time -> done, and inside it the node's own
#: processing (callback entry -> done): the rest is waiting to be scheduled.
LATENCIES = ('ros_to_can', 'sample_to_can', 'ros_to_can_proc', 'can_to_ros',
             'can_to_ros_proc')


class BridgeLoop:
    """The bridge between ``damping_cmd`` / ``ecu/*`` and the CAN bus (module doc)."""

    def __init__(self, p, params: ERVAParams, publish: Callable[[str, bytes], None],
                 publish_cycle: Callable[[bytes], None],
                 on_change: Callable[[], None] = lambda: None):
        self.p = p
        self.core = BridgeCore.from_parameters(p, params.c_e0)
        if p.get('can_log'):                # every raw frame, both directions
            self.core.trace = CanTrace(p['can_log'])
        self.hw = self.core.hw
        self.delay_ns = command_delay_ns(p['command_delay_s'])
        self.messages = EcuMessages(self.hw, params.l)
        self.lat = {k: LatencyStats() for k in LATENCIES}
        self.malformed = 0                # damping_cmd messages that did not decode
        self.active = False
        self._publish, self._publish_cycle, self._on_change = publish, publish_cycle, on_change
        self._last_state: Optional[Tuple] = None
        self._last_levels: Optional[List] = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='can', daemon=True)

    # -- ROS -> CAN --------------------------------------------------------------------
    def take_command(self, data: bytes, rx_ns: int) -> Optional[str]:
        """Send one ``damping_cmd`` (CDR) on; return why it was refused, if it was.

        Malformed or absurd: counted (``messages_rejected``); made for another d than
        the loop's: counted and the reason returned (the node logs it).  The stamp is the
        sample the command was computed for (synchronised clocks across hosts): a command
        delivered late is refused, not applied; its cycle tells the ECU when it acts.
        """
        if not self.active:
            return None
        t0 = time.perf_counter()
        try:
            cmd = contract.decode_command(data)
            if not all(abs(v) <= ABSURD_C_E for v in cmd.plan):   # also NaN
                raise contract.MessageRejected('absurd c_e')
        except contract.MessageRejected:
            self.malformed += 1
            self.core.watchdog.reject()
            return None
        try:   # the ECU applies it at t_k + d: the d the OCP planned with must be ours
            contract.check_command_delay(cmd, self.delay_ns)
        except contract.MessageRejected as exc:
            self.core.watchdog.reject(wrong_delay=True)
            return str(exc)
        result = self.core.submit(cmd.plan, offsets=cmd.offsets_s,
                                  age_s=(rx_ns - cmd.stamp_ns) * 1e-9, stamp_ns=cmd.stamp_ns)
        if result in ('sent', 'clamped'):
            done = time.time_ns()
            self.lat['ros_to_can'].add((done - rx_ns) * 1e-9)
            self.lat['sample_to_can'].add((done - cmd.stamp_ns) * 1e-9)
            self.lat['ros_to_can_proc'].add(time.perf_counter() - t0)
        return None

    # -- the CAN thread ----------------------------------------------------------------
    def start(self) -> None:
        """Start the CAN thread (once)."""
        if not self._thread.is_alive() and not self._stop.is_set():
            self._thread.start()

    def close(self) -> None:
        """Stop the CAN thread and shut the bus down."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)
        self.core.close()
        if self.core.trace is not None:     # after the bus: nothing more comes
            self.core.trace.close()

    def _run(self) -> None:
        """Publish each ECU frame as it arrives; run the watchdog every Ts/4."""
        period, next_tick = self.p['ts'] / 4, time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_tick:
                if self.active:
                    self._tick()
                next_tick = max(next_tick + period, now)
                continue
            f = self.core.receive(timeout=next_tick - now)
            if f is not None and self.active:
                self._frame(f)

    def _tick(self) -> None:
        self.core.tick()
        cyc = self.core.expire()                # a cycle that lost a frame: publish it
        if cyc is not None:
            self._cycle(cyc)
        # An ERROR (or its end) is published at once, not at the next period.
        state = (self.core.command_state, self.core.bus_up, self.core.ecu_silent())
        if state != self._last_state:
            self._last_state = state
            self._on_change()

    def _frame(self, f: SensorFrame) -> None:
        """Publish one ECU frame at once, stamped with its ECU cycle's stamp."""
        t0 = time.perf_counter()
        done = None
        for cyc in f.cycles:                    # an older, incomplete cycle: first
            if cyc.stamp == f.stamp:
                done = cyc
            else:
                self._cycle(cyc)
        for topic, data in self.messages.frame(f):
            self._publish(topic, data)
        if done is not None:                    # the cycle this frame completed: last
            self._cycle(done)
        self.lat['can_to_ros'].add(time.time() - f.rx_time)
        self.lat['can_to_ros_proc'].add(time.perf_counter() - t0)

    def _cycle(self, cyc: EcuCycle) -> None:
        """Publish one ECU cycle on ``ecu/measurements`` (NaN: that frame was lost)."""
        self._publish_cycle(self.messages.cycle(cyc))

    # -- report ------------------------------------------------------------------------
    def fill(self, reports) -> List[str]:
        """Fill the three reports; return the ERROR lines that are new since the last call."""
        cmd, _, ecu = self.core.diagnostics(reports=reports)
        t: Dict[str, Timing] = {k: Timing.of(v.summary()) for k, v in self.lat.items()}
        cmd.ros_to_can_ms, cmd.sample_to_can_ms = t['ros_to_can'], t['sample_to_can']
        cmd.ros_to_can_proc_ms = t['ros_to_can_proc']
        cmd.messages_rejected = self.malformed
        ecu.can_to_ros_ms, ecu.can_to_ros_proc_ms = t['can_to_ros'], t['can_to_ros_proc']
        levels = [(r.level, r.message.split(':')[0]) for r in reports]
        if levels == self._last_levels:
            return []
        self._last_levels = levels
        return _errors(reports)


def _errors(reports: Iterable) -> List[str]:
    return [f'{r.node}: {r.message}' for r in reports if r.level >= ERROR]


__all__ = ['ABSURD_C_E', 'BridgeLoop', 'LATENCIES']
