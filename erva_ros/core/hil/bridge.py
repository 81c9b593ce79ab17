"""ECU bridge core (no ROS): damping commands → protected CAN frames, ECU frames → values.

:class:`BridgeCore` is what ecu_bridge_node drives; it joins four units with one job each:

* :class:`~erva_ros.core.hil.bus_link.BusLink` -- the CAN bus: open, send, loss and
  re-open every ``bus_retry_s``; nothing raises to the caller;
* :class:`~erva_ros.core.hil.command_watchdog.CommandWatchdog` -- ROS → CAN:
  :meth:`BridgeCore.submit` takes the NMPC's plan and sends points[0] at once;
  :meth:`BridgeCore.tick` (every Ts/4) follows the plan while the NMPC is late and sends
  the safe passive command c_e0 once no fresh command came for ``command_timeout_s``;
* :class:`~erva_ros.core.hil.ecu_cycles.CycleAssembler` and
  :class:`~erva_ros.core.hil.ecu_cycles.EcuHeartbeat` -- CAN → ROS:
  :meth:`BridgeCore.receive` (called in a loop by a reader thread) reads one frame,
  checks it (:mod:`erva_ros.core.hil.e2e`: length, CRC, alive counter) and returns it
  decoded as a :class:`SensorFrame` at once (no waiting for the rest of the cycle,
  which would add latency), with the ECU cycles it ended; :meth:`BridgeCore.expire`
  (call it from the receiving thread, e.g. every Ts/4) ends a cycle that lost a frame;
* :mod:`~erva_ros.core.hil.bridge_diagnostics` -- the three statuses
  (:meth:`BridgeCore.diagnostics`): command link, CAN bus, ECU heartbeat.

Their counters read as one mapping, :attr:`BridgeCore.counts`.  Thread-safe for
:meth:`submit` and :meth:`tick` called from two threads and :meth:`receive` from one of
them or a third.
"""

from collections.abc import MutableMapping
from dataclasses import dataclass
import time
from typing import Any, Callable, Dict, Iterator, Mapping, Optional, Sequence, Tuple

import can

from erva_ros.core.hil.bridge_diagnostics import (bus_status, command_status, diag_dict,
                                                  ecu_status)
from erva_ros.core.hil.settings import hardware_of
from erva_ros.core.model.params import ParamError
from erva_ros.core.reports import BridgeBusReport, BridgeCommandReport, BridgeEcuReport
from erva_ros.core.hil.bus_link import BUS_ERRORS, BusLink, is_transient, TRANSIENT_ERRNOS
from erva_ros.core.hil.codec import Command, E2EReceiver, EcuCodec
from erva_ros.core.hil.command_watchdog import CommandWatchdog
from erva_ros.core.hil.ecu_cycles import (CycleAssembler, ECU_KINDS, EcuCycle, EcuHeartbeat,
                                          SensorFrame)
from erva_ros.core.model.hardware import GeneratorHardware
from erva_ros.core.levels import ERROR, OK, STALE, WARN


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
    command_delay_s: float = 0.0      # d: the ECU applies a command for t_k at t_k + d


class CounterView(MutableMapping):
    """The units' own counters as one mapping; each name is written in the unit owning it."""

    def __init__(self, *parts: Dict[str, int]):
        self._owner = {name: part for part in parts for name in part}

    def __getitem__(self, name: str) -> int:
        return self._owner[name][name]

    def __setitem__(self, name: str, value: int) -> None:
        self._owner[name][name] = value

    def __delitem__(self, name: str) -> None:
        raise TypeError('bridge counters cannot be removed')

    def __iter__(self) -> Iterator[str]:
        return iter(self._owner)

    def __len__(self) -> int:
        return len(self._owner)


class BridgeCore:
    """The ECU bridge without ROS (see module doc)."""

    def __init__(self, codec: EcuCodec, hardware: GeneratorHardware, config: BridgeConfig,
                 bus_factory: Callable[[], can.BusABC],
                 clock: Callable[[], float] = time.monotonic):
        self.codec = codec
        self.hw = hardware
        self.cfg = config
        self.c_e_safe, _ = hardware.clamp_c_e(config.c_e_safe)
        self._clock = clock
        self.link = BusLink(bus_factory, config.bus_retry_s, config.send_timeout_s)
        self.watchdog = CommandWatchdog(codec, hardware, config.period_s,
                                        config.command_timeout_s, self.c_e_safe,
                                        self._send, config.command_delay_s)
        #: Where every frame sent and read goes too (can_trace.CanTrace), if anywhere.
        self.trace = None
        self.cycles = CycleAssembler(config.period_s)
        self.heartbeat = EcuHeartbeat(config.sensor_timeout_s)
        self._rx = E2EReceiver(codec, ECU_KINDS, config.sensor_timeout_s,
                               config.max_delta_counter)
        self._rx_bus: Optional[can.BusABC] = None
        self.counts: MutableMapping = CounterView(
            self.watchdog.counts, self.link.counts, self.cycles.counts, self.heartbeat.counts)

    @classmethod
    def from_parameters(cls, p: Mapping[str, Any], c_e0: float) -> 'BridgeCore':
        """Return the bridge of ecu_bridge_node's parameters (config/hil.yaml; ts, bus).

        ParamError (one line) for a bus spec, a DBC file or a CAN trace path
        (``can_log``) that cannot be used.
        """
        from erva_ros.core.hil.can_trace import check_path
        from erva_ros.core.hil.transport import open_bus, parse_spec
        if p.get('can_log'):
            check_path(p['can_log'])
        try:
            parse_spec(p['bus'])
            codec = EcuCodec(p['dbc_file'] or None)
        except (ValueError, FileNotFoundError) as exc:
            raise ParamError(str(exc)) from None
        ts = p['ts']
        return cls(codec, hardware_of(p), BridgeConfig(
            period_s=ts, command_timeout_s=p['command_timeout_periods'] * ts,
            sensor_timeout_s=p['sensor_timeout_periods'] * ts, c_e_safe=c_e0,
            bus_retry_s=p['bus_retry_s'], max_delta_counter=p['max_delta_counter'],
            command_delay_s=p['command_delay_s']),
            lambda: open_bus(p['bus']))

    def _now(self, now: Optional[float]) -> float:
        return self._clock() if now is None else now

    # ------------------------------------------------------------------ bus
    @property
    def bus_up(self) -> bool:
        return self.link.up

    @property
    def bus(self) -> Optional[can.BusABC]:
        """Return the CAN bus in use (None while it is lost)."""
        return self.link.bus

    @property
    def bus_error(self) -> str:
        return self.link.error

    def open(self, now: Optional[float] = None) -> bool:
        """Try to open the bus now; return True if it is up."""
        return self.link.open(self._now(now))

    def close(self) -> None:
        """Shut the bus down (node shutdown)."""
        self.link.close()

    def _send(self, msg: can.Message) -> bool:
        ok = self.link.send(msg)
        if ok and self.trace is not None:
            self.trace.sent(msg)
        return ok

    # ------------------------------------------------------------ ROS → CAN
    @property
    def command_state(self) -> str:
        """Return 'waiting' (no command yet), 'fresh' or 'timeout' (sending safe)."""
        return self.watchdog.state

    @property
    def last_command(self) -> Optional[Command]:
        return self.watchdog.last_command

    @property
    def timeouts_worst(self) -> Dict[str, float]:
        """Over all timeouts: the most plan frames before one, the largest command age."""
        return self.watchdog.timeouts_worst

    def submit(self, plan: Sequence[float], now: Optional[float] = None,
               offsets: Optional[Sequence[float]] = None,
               age_s: Optional[float] = None, stamp_ns: Optional[int] = None) -> str:
        """Take a new damping plan and send plan[0] at once (:meth:`CommandWatchdog.submit`)."""
        return self.watchdog.submit(plan, self._now(now), offsets, age_s, stamp_ns)

    def command_age(self, now: Optional[float] = None) -> float:
        """Return the time since the last accepted command (s; inf before the first)."""
        return self.watchdog.command_age(self._now(now))

    def tick(self, now: Optional[float] = None) -> None:
        """Watchdog (call every Ts/4): re-open a lost bus, follow the plan, or send safe."""
        now = self._now(now)
        self.link.retry(now)
        self.watchdog.tick(now)
        self.heartbeat.check(now)

    # ------------------------------------------------------------ CAN → ROS
    @property
    def last(self) -> Dict[Any, Any]:
        """Return the newest payload of each ECU message, by kind."""
        return self.heartbeat.last

    def receive(self, timeout: float = 0.05) -> Optional[SensorFrame]:
        """Read at most one frame (waiting up to ``timeout`` s); return it if accepted."""
        bus = self.link.bus
        if bus is None:
            time.sleep(timeout)
            return None
        if bus is not self._rx_bus:             # new or re-opened bus: new streams
            self._rx_bus = bus
            self._rx.reset()
            self.cycles.reset()
        try:
            msg = bus.recv(timeout)
        except BUS_ERRORS as exc:
            self.link.lost(bus, exc)
            return None
        if msg is None:
            return None
        if self.trace is not None:
            self.trace.received(msg)
        now = self._clock()
        kind, status, payload = self._rx.accept(msg, now)
        if payload is None:
            return None
        self.heartbeat.heard(kind, payload, now)
        rx = msg.timestamp or time.time()
        stamp, ended = self.cycles.add(kind, payload, rx, now)
        return SensorFrame(kind, payload, stamp, rx, ended)

    def expire(self, now: Optional[float] = None) -> Optional[EcuCycle]:
        """End and return the open cycle if it is older than Ts/2 (a frame was lost)."""
        return self.cycles.expire(self._now(now))

    # ------------------------------------------------------------ reporting
    def rx_counts(self) -> Dict[str, int]:
        """Return the E2E receive counters (accepted, bad_crc, repeated, skipped, ...)."""
        return self._rx.counts()

    def ecu_silent(self, now: Optional[float] = None) -> bool:
        return self.heartbeat.silent(self._now(now))

    def diagnostics(self, now: Optional[float] = None, reports: Optional[Tuple[
            BridgeCommandReport, BridgeBusReport, BridgeEcuReport]] = None
                    ) -> Tuple[BridgeCommandReport, BridgeBusReport, BridgeEcuReport]:
        """Return the bridge's three reports filled: command link, CAN bus, ECU heartbeat."""
        now = self._now(now)
        cmd, bus, ecu = reports or (BridgeCommandReport(node='ecu_bridge: command'),
                                    BridgeBusReport(node='ecu_bridge: can bus'),
                                    BridgeEcuReport(node='ecu_bridge: ecu'))
        return (command_status(self.watchdog, self.counts, self.hw.c_e_range, now, cmd),
                bus_status(self.link, self.counts, self.rx_counts(), bus),
                ecu_status(self.heartbeat, self.counts, now, ecu))


__all__ = ['BridgeConfig', 'BridgeCore', 'CounterView', 'EcuCycle',
           'SensorFrame', 'diag_dict', 'is_transient', 'TRANSIENT_ERRNOS', 'OK', 'WARN',
           'ERROR', 'STALE']
