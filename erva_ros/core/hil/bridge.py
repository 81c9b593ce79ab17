"""ECU bridge core (no ROS): damping commands → protected CAN frames, ECU frames → values.

ROS → CAN.  :meth:`BridgeCore.submit` takes the NMPC's plan (``damping_cmd``
points: c_e now, then at t0 + k·Ts, Ns/m), rejects non-finite or empty plans,
clamps every value to the hardware range (:class:`~erva_ros.core.hil.hardware.GeneratorHardware`)
and sends points[0] at once as duty D = c_e / c_e,full.  :meth:`BridgeCore.tick`
(called every Ts/4) is the watchdog that keeps the ECU fed at the command period Ts:

* a command is *fresh* for ``command_timeout_s`` (default 3·Ts) after it arrived;
* if no frame went out for 1.5·Ts while the command is fresh (the NMPC is late), the
  plan's point for the elapsed time is sent (the NMPC's own plan, not a guess);
* once the command is stale, the **safe passive command** (c_e0, CMD_MODE = SAFE_PASSIVE)
  is sent every Ts and the command state is ERROR until a fresh command arrives;
  :attr:`BridgeCore.timeouts_worst` keeps the most plan frames that went out before
  a timeout, and the largest command age at which one was declared;
* a command that is already older than ``command_timeout_s`` when it arrives is
  refused (``commands_stale``);
* before the first command the bridge sends the safe command too (state WARN).

CAN → ROS.  :meth:`BridgeCore.receive` (called in a loop by a reader thread) reads
one frame, checks it (:mod:`erva_ros.core.hil.e2e`: length, CRC, alive counter) and
returns it decoded as a :class:`SensorFrame` at once (no waiting for the rest of the
cycle, which would add latency).  Frames of one ECU cycle (status, chassis,
generator, in any order) share one stamp: the receive time of the cycle's first
frame; a cycle ends when all three arrived, when a kind repeats or after Ts/2.  A
rejected frame is dropped and counted, and so is a cycle that misses a frame.
Each ended cycle is also handed out whole, once, as an :class:`EcuCycle` (what a
node publishes as ``ecu/measurements``): with the frame that completes it
(``SensorFrame.cycles``) or, for a cycle that misses a frame, with the next cycle's
first frame or from :meth:`BridgeCore.expire` (call it from the receiving thread,
e.g. every Ts/4) once it is Ts/2 old, whichever comes first.

Bus loss.  An error of ``send``/``recv`` (interface down, socket closed) closes the
bus, is counted and reported (state ERROR), and :meth:`tick` re-opens it through
``bus_factory``, at most once every ``bus_retry_s``, until it works; nothing raises to
the caller.  A full transmit queue (ENOBUFS / EAGAIN: no ECU acknowledging, a busy
bus) only drops that frame (``send_errors``): the bus is still there.
"""

from dataclasses import dataclass, field
import errno
import math
import threading
import time
from typing import Any, Callable, Dict, List, Optional, Sequence

import can

from erva_ros.core.hil.codec import Command, CommandMode, E2EReceiver, EcuCodec, EcuMode, Kind
from erva_ros.core.hil.hardware import GeneratorHardware
from erva_ros.core.levels import ERROR, OK, WARN

#: Send errors that mean "queue full", not "interface gone" (SocketCAN gives ENOBUFS when
#: no node acknowledges; python-can's virtual bus when a receiver's queue stays full).
TRANSIENT_ERRNOS = frozenset({errno.ENOBUFS, errno.EAGAIN})
_TRANSIENT_TEXT = ('buffer full', 'one or more recipients')


def is_transient(exc: BaseException) -> bool:
    """Return True if a send error leaves the bus usable (the frame alone is lost)."""
    code = getattr(exc, 'error_code', None) or getattr(exc, 'errno', None)
    return code in TRANSIENT_ERRNOS or any(t in str(exc).lower() for t in _TRANSIENT_TEXT)


@dataclass(frozen=True)
class BridgeConfig:
    """Timing and safety settings of the bridge (SI units)."""

    period_s: float = 0.02            # command period Ts (50 Hz)
    command_timeout_s: float = 0.06   # fresh-command timeout (default 3 periods)
    sensor_timeout_s: float = 0.06    # ECU silent after this long without a valid frame
    c_e_safe: float = 10000.0         # Ns/m, safe passive command (paper c_e0)
    bus_retry_s: float = 0.5          # s between attempts to re-open a lost bus
    max_delta_counter: int = 1        # alive-counter step accepted (1: no frame may be lost)
    send_timeout_s: float = 0.005     # s a send may block (full TX queue)


@dataclass
class EcuCycle:
    """One ended ECU cycle: the payloads that arrived (a lost frame's kind is absent)."""

    stamp: float                       # CAN receive time of its first frame (epoch s)
    payloads: Dict[Kind, Any]          # Status, Chassis, Generator by kind
    rx_time: float                     # CAN receive time of its last frame (epoch s)

    @property
    def complete(self) -> bool:
        return len(self.payloads) == len(ECU_KINDS)


@dataclass
class SensorFrame:
    """One accepted ECU frame, decoded; times are CAN receive times (epoch s)."""

    kind: Kind
    payload: Any                       # Status, Chassis or Generator
    stamp: float                       # first frame of this ECU cycle: the cycle's stamp
    rx_time: float                     # this frame
    cycles: tuple = ()                 # EcuCycles this frame ended (oldest first)


@dataclass
class _Cycle:
    stamp: float
    started: float = 0.0               # on the core's clock (for expire)
    rx_time: float = 0.0
    payloads: Dict[Kind, Any] = field(default_factory=dict)

    @property
    def kinds(self):
        return self.payloads.keys()


@dataclass
class DiagStatus:
    """A ROS-free diagnostic_msgs/DiagnosticStatus."""

    level: int
    name: str
    message: str
    values: Dict[str, str] = field(default_factory=dict)


ECU_KINDS = (Kind.STATUS, Kind.CHASSIS, Kind.GENERATOR)
COUNTER_NAMES = (
    'commands_received', 'commands_rejected', 'commands_stale', 'commands_clamped',
    'frames_sent',
    'safe_frames_sent', 'plan_frames_sent', 'command_timeouts', 'frames_not_sent',
    'send_errors', 'bus_losses', 'bus_open_attempts', 'bus_open_failures', 'reconnects',
    'ecu_cycles', 'incomplete_cycles', 'ecu_silences')


class BridgeCore:
    """The ECU bridge without ROS.

    Thread-safe for :meth:`submit` and :meth:`tick` called from two threads (they share
    the command state under a lock) and :meth:`receive` from one of them or a third.
    """

    def __init__(self, codec: EcuCodec, hardware: GeneratorHardware, config: BridgeConfig,
                 bus_factory: Callable[[], can.BusABC],
                 clock: Callable[[], float] = time.monotonic):
        self.codec = codec
        self.hw = hardware
        self.cfg = config
        self.c_e_safe, _ = hardware.clamp_c_e(config.c_e_safe)
        self._factory = bus_factory
        self._clock = clock
        self._lock = threading.Lock()           # the bus object
        self._cmd_lock = threading.RLock()      # plan, send times, E2E sender
        self.counts: Dict[str, int] = dict.fromkeys(COUNTER_NAMES, 0)
        # bus
        self._bus: Optional[can.BusABC] = None
        self._ever_open = False
        self._last_attempt = -math.inf
        self.bus_error = ''
        # ROS → CAN
        self._tx = codec.sender(Kind.COMMAND)
        self._plan: Optional[List[float]] = None
        self._offsets: List[float] = []
        self._plan_time = -math.inf
        self._last_send = -math.inf
        self.command_state = 'waiting'          # waiting | fresh | timeout
        self.last_command: Optional[Command] = None
        self._plan_frames = 0                   # plan frames since the last command
        #: Over all timeouts: the most plan frames sent after the last command, and the
        #: largest command age (s) at which the timeout was declared.
        self.timeouts_worst: Dict[str, float] = {'plan_frames': 0, 'command_age_s': 0.0}
        # CAN → ROS
        self._rx = E2EReceiver(codec, ECU_KINDS, config.sensor_timeout_s,
                               config.max_delta_counter)
        self._rx_bus: Optional[can.BusABC] = None
        self._cycle: Optional[_Cycle] = None
        self._last_sensor = -math.inf
        self._ecu_silent = True
        self.last: Dict[Kind, Any] = {}          # newest payload of each ECU message

    # ------------------------------------------------------------------ bus
    @property
    def bus_up(self) -> bool:
        return self._bus is not None

    @property
    def bus(self) -> Optional[can.BusABC]:
        """Return the CAN bus in use (None while it is lost)."""
        return self._bus

    def open(self, now: Optional[float] = None) -> bool:
        """Try to open the bus now; return True if it is up."""
        now = self._clock() if now is None else now
        if self._bus is not None:
            return True
        self.counts['bus_open_attempts'] += 1
        self._last_attempt = now
        try:
            bus = self._factory()
        except Exception as exc:  # any open failure is reported and retried, never raised
            self.counts['bus_open_failures'] += 1
            self.bus_error = f'cannot open bus: {exc}'
            return False
        with self._lock:
            self._bus = bus
            if self._ever_open:
                self.counts['reconnects'] += 1
            self._ever_open = True
            self.bus_error = ''
        return True

    def _lost(self, bus: can.BusABC, exc: BaseException) -> None:
        with self._lock:
            if self._bus is not bus:
                return                  # the other thread already handled it
            self._bus = None
            self.counts['bus_losses'] += 1
            self.bus_error = f'bus lost: {exc}'
        try:
            bus.shutdown()
        except Exception:  # a dead interface may fail to close; it is dropped anyway
            pass

    def close(self) -> None:
        """Shut the bus down (node shutdown)."""
        with self._lock:
            bus, self._bus = self._bus, None
        if bus is not None:
            bus.shutdown()

    def _send(self, msg: can.Message) -> bool:
        bus = self._bus
        if bus is None:
            self.counts['frames_not_sent'] += 1
            return False
        try:
            bus.send(msg, timeout=self.cfg.send_timeout_s)
        except (can.CanError, OSError, ValueError) as exc:
            self.counts['send_errors'] += 1
            if is_transient(exc):
                self.bus_error = f'send failed, frame dropped: {exc}'
            else:
                self._lost(bus, exc)
            return False
        if self.bus_error.startswith('send failed'):
            self.bus_error = ''
        return True

    # ------------------------------------------------------------ ROS → CAN
    def submit(self, plan: Sequence[float], now: Optional[float] = None,
               offsets: Optional[Sequence[float]] = None,
               age_s: Optional[float] = None) -> str:
        """Take a new damping plan (Ns/m; plan[0] = now) and send plan[0] at once.

        ``offsets`` are the plan points' times after the command (s, the messages'
        time_from_start; default k·Ts).  ``age_s`` is how old the command was when it
        arrived (its sample instant to its arrival, s; None: unknown).  Returns 'sent',
        'clamped' (sent after clamping), 'not_sent' (bus down), 'rejected' (empty or
        non-finite: ignored, the previous command ages on) or 'stale' (older than
        ``command_timeout_s``: ignored and counted as well).
        """
        values = [float(v) for v in plan]
        if not values or not all(math.isfinite(v) for v in values):
            self.counts['commands_rejected'] += 1
            return 'rejected'
        if age_s is not None and not age_s <= self.cfg.command_timeout_s:
            self.counts['commands_stale'] += 1
            return 'stale'
        if offsets is None or len(offsets) != len(values):
            offsets = [k * self.cfg.period_s for k in range(len(values))]
        clamped = [self.hw.clamp_c_e(v) for v in values]
        with self._cmd_lock:
            now = self._clock() if now is None else now
            self._plan = [v for v, _ in clamped]
            self._offsets = [float(o) for o in offsets]
            self._plan_time = now
            self.counts['commands_received'] += 1
            self._plan_frames = 0
            if clamped[0][1]:
                self.counts['commands_clamped'] += 1
            self.command_state = 'fresh'
            sent = self._send_c_e(self._plan[0], CommandMode.CONTROLLED, now)
        if not sent:
            return 'not_sent'
        return 'clamped' if clamped[0][1] else 'sent'

    def _send_c_e(self, c_e: float, mode: CommandMode, now: float) -> bool:
        duty, _ = self.hw.clamp_duty(self.hw.duty_from_c_e(c_e))
        cmd = Command(duty=duty, c_e=c_e, mode=mode)
        ok = self._send(self.codec.encode(Kind.COMMAND, cmd, self._tx))
        if ok:
            self.last_command = cmd
            self._last_send = now
            self.counts['frames_sent'] += 1
            if mode is CommandMode.SAFE_PASSIVE:
                self.counts['safe_frames_sent'] += 1
        return ok

    def command_age(self, now: Optional[float] = None) -> float:
        """Return the time since the last accepted command (s; inf before the first)."""
        return (self._clock() if now is None else now) - self._plan_time

    def tick(self, now: Optional[float] = None) -> None:
        """Watchdog (call every Ts/4): re-open a lost bus, follow the plan, or send safe."""
        with self._cmd_lock:
            self._tick(self._clock() if now is None else now)

    def _tick(self, now: float) -> None:
        # Re-open at most every bus_retry_s: an interface that opens but fails on send
        # (SocketCAN on a link that is down) must not be hammered every tick.
        if self._bus is None and now - self._last_attempt >= self.cfg.bus_retry_s:
            self.open(now)
        period = self.cfg.period_s
        since_send = now - self._last_send
        if self.command_age(now) > self.cfg.command_timeout_s:
            if self.command_state == 'fresh':
                self.command_state = 'timeout'
                self.counts['command_timeouts'] += 1
                # What the NMPC's last plan covered before going safe (docs/hil.md).
                worst = self.timeouts_worst
                worst['plan_frames'] = max(worst['plan_frames'], self._plan_frames)
                worst['command_age_s'] = max(worst['command_age_s'], self.command_age(now))
                since_send = math.inf           # go safe now, not at the next period
            if since_send >= period * 0.95:
                self._send_c_e(self.c_e_safe, CommandMode.SAFE_PASSIVE, now)
        elif since_send >= 1.5 * period:
            age = self.command_age(now) + 1e-9
            k = 0                               # the plan point due now
            for i, offset in enumerate(self._offsets):
                if offset <= age:
                    k = i
            if self._send_c_e(self._plan[k], CommandMode.CONTROLLED, now):
                self.counts['plan_frames_sent'] += 1
                self._plan_frames += 1
        if now - self._last_sensor > self.cfg.sensor_timeout_s and not self._ecu_silent:
            self._ecu_silent = True
            self.counts['ecu_silences'] += 1

    # ------------------------------------------------------------ CAN → ROS
    def receive(self, timeout: float = 0.05) -> Optional[SensorFrame]:
        """Read at most one frame (waiting up to ``timeout`` s); return it if accepted."""
        bus = self._bus
        if bus is None:
            time.sleep(timeout)
            return None
        if bus is not self._rx_bus:             # new or re-opened bus: new streams
            self._rx_bus = bus
            self._rx.reset()
            self._cycle = None
        try:
            msg = bus.recv(timeout)
        except (can.CanError, OSError, ValueError) as exc:
            self._lost(bus, exc)
            return None
        if msg is None:
            return None
        now = self._clock()
        kind, status, payload = self._rx.accept(msg, now)
        if payload is None:
            return None
        self._last_sensor = now
        self._ecu_silent = False
        rx = msg.timestamp or time.time()
        cyc = self._cycle
        ended = []
        if cyc is None or kind in cyc.kinds or rx - cyc.stamp > 0.5 * self.cfg.period_s:
            if cyc is not None:
                ended.append(self._close_cycle(cyc))
            cyc = self._cycle = _Cycle(rx, now)
        cyc.payloads[kind] = payload
        cyc.rx_time = rx
        if len(cyc.kinds) == len(ECU_KINDS):
            ended.append(self._close_cycle(cyc))
            self._cycle = None
        self.last[kind] = payload
        return SensorFrame(kind, payload, cyc.stamp, rx, tuple(ended))

    def expire(self, now: Optional[float] = None) -> Optional[EcuCycle]:
        """End and return the open cycle if it is older than Ts/2 (a frame was lost)."""
        cyc = self._cycle
        now = self._clock() if now is None else now
        if cyc is None or now - cyc.started <= 0.5 * self.cfg.period_s:
            return None
        self._cycle = None
        return self._close_cycle(cyc)

    def _close_cycle(self, cyc: _Cycle) -> EcuCycle:
        self.counts['ecu_cycles'] += 1
        if len(cyc.kinds) < len(ECU_KINDS):
            self.counts['incomplete_cycles'] += 1
        return EcuCycle(cyc.stamp, dict(cyc.payloads), cyc.rx_time)

    # ------------------------------------------------------------ reporting
    def rx_counts(self) -> Dict[str, int]:
        """Return the E2E receive counters (accepted, bad_crc, repeated, skipped, ...)."""
        return self._rx.counts()

    def ecu_silent(self, now: Optional[float] = None) -> bool:
        now = self._clock() if now is None else now
        return now - self._last_sensor > self.cfg.sensor_timeout_s

    def diagnostics(self, now: Optional[float] = None, prefix: str = 'ecu_bridge') -> List[
            DiagStatus]:
        """Return the bridge's three statuses: command link, CAN bus, ECU heartbeat."""
        now = self._clock() if now is None else now
        c = self.counts
        cmd = self.last_command
        cmd_values = {k: str(c[k]) for k in (
            'commands_received', 'commands_rejected', 'commands_stale', 'commands_clamped',
            'command_timeouts', 'frames_sent', 'safe_frames_sent', 'plan_frames_sent',
            'frames_not_sent')}
        worst = self.timeouts_worst
        cmd_values['timeout_plan_frames_max'] = str(worst['plan_frames'])
        cmd_values['timeout_age_ms_max'] = f'{worst["command_age_s"] * 1e3:.2f}'
        cmd_values.update({
            'command_age_s': f'{self.command_age(now):.4f}',
            'sent_c_e_ns_per_m': f'{cmd.c_e:.1f}' if cmd else '',
            'sent_duty': f'{cmd.duty:.4f}' if cmd else '',
            'sent_mode': cmd.mode.name if cmd else '',
            'hardware_c_e_range_ns_per_m': '{:.1f}..{:.1f}'.format(*self.hw.c_e_range)})
        if self.command_state == 'timeout':
            cmd_diag = DiagStatus(ERROR, f'{prefix}: command', 'no fresh damping command for '
                                  f'{self.command_age(now):.3f} s > '
                                  f'{self.cfg.command_timeout_s:.3f} s: sending safe passive '
                                  f'c_e = {self.c_e_safe:.0f} Ns/m', cmd_values)
        elif self.command_state == 'waiting':
            cmd_diag = DiagStatus(WARN, f'{prefix}: command', 'waiting for the first damping '
                                  'command: sending safe passive', cmd_values)
        else:
            cmd_diag = DiagStatus(OK, f'{prefix}: command', 'forwarding damping commands',
                                  cmd_values)
        rx = self.rx_counts()
        bus_values = {k: str(v) for k, v in rx.items()}
        bus_values.update({k: str(c[k]) for k in (
            'send_errors', 'bus_losses', 'bus_open_attempts', 'bus_open_failures',
            'reconnects')})
        bus_values['error'] = self.bus_error
        if self._bus is None:
            bus_diag = DiagStatus(ERROR, f'{prefix}: can bus',
                                  self.bus_error or 'bus not open', bus_values)
        else:
            rejected = sum(rx[k] for k in ('wrong_length', 'bad_crc', 'repeated', 'skipped',
                                           'bad_counter'))
            msg = 'bus up' + (f', {rejected} frames rejected' if rejected else '')
            bus_diag = DiagStatus(WARN if rejected else OK, f'{prefix}: can bus', msg,
                                  bus_values)
        ecu_diag = self._ecu_diag(now, prefix)
        return [cmd_diag, bus_diag, ecu_diag]

    def _ecu_diag(self, now: float, prefix: str) -> DiagStatus:
        st = self.last.get(Kind.STATUS)
        gen = self.last.get(Kind.GENERATOR)
        values = {k: str(self.counts[k]) for k in ('ecu_cycles', 'incomplete_cycles',
                                                   'ecu_silences')}
        if st is not None:
            values.update({'ecu_mode': st.mode.name, 'c_e_applied_ns_per_m': f'{st.c_e_applied:g}',
                           'c_e_mean_ns_per_m': f'{st.c_e_mean:g}',
                           'ecu_cmd_rejected_mod256': str(st.cmd_rejected),
                           'ecu_cmd_timeouts_mod256': str(st.cmd_timeouts)})
        if gen is not None:
            values.update({'generator_speed_rad_s': f'{gen.speed:g}',
                           'generator_current_a': f'{gen.current:g}',
                           'generator_voltage_v': f'{gen.voltage:g}'})
        name = f'{prefix}: ecu'
        if self._last_sensor == -math.inf:
            return DiagStatus(ERROR, name, 'ECU silent: no valid frame received yet', values)
        if self.ecu_silent(now):
            return DiagStatus(ERROR, name, 'ECU silent: no valid frame for '
                              f'{now - self._last_sensor:.3f} s', values)
        if st is None:
            return DiagStatus(WARN, name, 'ECU sends sensors but no status yet', values)
        if st.mode is EcuMode.FAULT:
            return DiagStatus(ERROR, name, 'ECU reports FAULT', values)
        if st.mode is not EcuMode.CONTROLLED:
            return DiagStatus(WARN, name, f'ECU in {st.mode.name} (passive damping)', values)
        return DiagStatus(OK, name, 'ECU controlled', values)


def diag_dict(statuses: Sequence[DiagStatus]) -> Dict[str, Any]:
    """Return statuses as plain data (for JSON output and tests)."""
    return {s.name: {'level': s.level, 'message': s.message, 'values': dict(s.values)}
            for s in statuses}
