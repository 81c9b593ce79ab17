"""The ECU's frames on the bridge (no ROS): assembled into cycles, and its heartbeat.

The ECU sends three frames per cycle (status, chassis, generator) at its sample
instant.  :class:`CycleAssembler` groups the accepted frames into cycles: the frames of
one cycle, in any order, share one stamp, the receive time of its first frame; a cycle
ends when all three arrived, when a kind repeats or after Ts/2.  Each ended cycle is
handed out whole, once, as an :class:`EcuCycle`: with the frame that completes it or,
for a cycle that misses a frame (``incomplete_cycles``), with the next cycle's first
frame or from :meth:`CycleAssembler.expire` once it is Ts/2 old, whichever comes first.

:class:`EcuHeartbeat` keeps the newest payload of each kind and tells when the ECU
went silent (no valid frame for ``timeout_s``; each silence counted once).
"""

from dataclasses import dataclass, field
import math
from typing import Any, Dict, Optional, Tuple

from erva_ros.core.hil.codec import Kind

ECU_KINDS = (Kind.STATUS, Kind.CHASSIS, Kind.GENERATOR)


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
    started: float = 0.0               # on the caller's clock (for expire)
    rx_time: float = 0.0
    payloads: Dict[Kind, Any] = field(default_factory=dict)


class CycleAssembler:
    """Accepted ECU frames → ECU cycles (see module doc); one receiving thread."""

    COUNTER_NAMES = ('ecu_cycles', 'incomplete_cycles')

    def __init__(self, period_s: float):
        self.period_s = float(period_s)
        self._cycle: Optional[_Cycle] = None
        self.counts: Dict[str, int] = dict.fromkeys(self.COUNTER_NAMES, 0)

    def reset(self) -> None:
        """Forget the open cycle (a new or re-opened bus: new streams)."""
        self._cycle = None

    def add(self, kind: Kind, payload: Any, rx: float, now: float) -> Tuple[float, tuple]:
        """Take a frame; return its cycle's stamp and the cycles it ended (oldest first).

        ``rx`` is its receive time (epoch s), ``now`` the caller's clock, the one
        :meth:`expire` is called with.
        """
        cyc = self._cycle
        ended = []
        if cyc is None or kind in cyc.payloads or rx - cyc.stamp > 0.5 * self.period_s:
            if cyc is not None:
                ended.append(self._close(cyc))
            cyc = self._cycle = _Cycle(rx, now)
        cyc.payloads[kind] = payload
        cyc.rx_time = rx
        if len(cyc.payloads) == len(ECU_KINDS):
            ended.append(self._close(cyc))
            self._cycle = None
        return cyc.stamp, tuple(ended)

    def expire(self, now: float) -> Optional[EcuCycle]:
        """End and return the open cycle if it is older than Ts/2 (a frame was lost)."""
        cyc = self._cycle
        if cyc is None or now - cyc.started <= 0.5 * self.period_s:
            return None
        self._cycle = None
        return self._close(cyc)

    def _close(self, cyc: _Cycle) -> EcuCycle:
        self.counts['ecu_cycles'] += 1
        if len(cyc.payloads) < len(ECU_KINDS):
            self.counts['incomplete_cycles'] += 1
        return EcuCycle(cyc.stamp, dict(cyc.payloads), cyc.rx_time)


class EcuHeartbeat:
    """When the ECU was last heard, what it said last, and its silences."""

    COUNTER_NAMES = ('ecu_silences',)

    def __init__(self, timeout_s: float):
        self.timeout_s = float(timeout_s)
        self.last_heard = -math.inf             # on the caller's clock
        self._silent = True
        self.last: Dict[Kind, Any] = {}          # newest payload of each ECU message
        self.counts: Dict[str, int] = dict.fromkeys(self.COUNTER_NAMES, 0)

    def heard(self, kind: Kind, payload: Any, now: float) -> None:
        """Take a valid frame received at ``now``."""
        self.last_heard = now
        self._silent = False
        self.last[kind] = payload

    @property
    def ever_heard(self) -> bool:
        return self.last_heard > -math.inf

    def silent(self, now: float) -> bool:
        """Return True if no valid frame came for more than ``timeout_s``."""
        return now - self.last_heard > self.timeout_s

    def check(self, now: float) -> None:
        """Count a silence that began since the last call (call it periodically)."""
        if self.silent(now) and not self._silent:
            self._silent = True
            self.counts['ecu_silences'] += 1
