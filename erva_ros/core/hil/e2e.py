"""End-to-end protection of the ERVA CAN frames, AUTOSAR E2E profile 1 style (variant 1A).

Layout of every 8-byte frame (Intel byte order, see ``config/erva_ecu.dbc``)::

    byte 0        CRC-8 over [Data-ID low byte, Data-ID high byte, bytes 1..7]
    byte 1 [3:0]  alive counter 0..14 (15 is never sent, as in profile 1)
    byte 1 [7:4]  message-specific (mode)
    bytes 2..7    payload

The CRC is CRC-8/SAE-J1850 (polynomial 0x1D, no reflection) with the *effective*
parameters of profile 1: start value 0x00 and final XOR 0x00 (profile 1 calls the
AUTOSAR CRC library with start 0xFF and XORs the result with 0xFF, which cancels the
library's own 0xFF XORs).  The 16-bit Data ID is not transmitted; it enters the CRC
(DataIDMode BOTH), so a frame that arrives under the wrong CAN ID fails the check.

Why profile 1 rather than a bigger CRC: a classic CAN frame already carries a 15-bit
CRC against bit errors on the wire; E2E protects against faults *between* the
applications (stale buffers, wrong routing, a stuck sender), for which an 8-bit CRC
with a Data ID plus a 4-bit alive counter is the automotive norm for 8-byte frames.

Receiver rules (:class:`E2EChecker`), stricter than profile 1 as the issue asks:
a wrong length, a bad CRC, a repeated counter (delta 0) or a skipped counter
(delta > ``max_delta_counter``, default 1) drops the frame and counts it.  After a
skip the stream re-synchronises on the dropped frame, so one lost frame costs one
more.  The first frame, and the first one after a silence (no intact frame) longer
than ``timeout_s``, starts a new stream (accepted, counted as ``resyncs``).
"""

from dataclasses import dataclass, field
import enum
from typing import Dict, Optional

#: Alive counters run 0..COUNTER_MODULO-1 (profile 1: 0..14).
COUNTER_MODULO = 15
FRAME_LENGTH = 8


def _crc8_table(poly: int) -> bytes:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ poly) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return bytes(table)


_TABLE_1D = _crc8_table(0x1D)


def crc8_sae_j1850(data: bytes, init: int = 0x00, xorout: int = 0x00) -> int:
    """Return the CRC-8/SAE-J1850 (poly 0x1D) of ``data``.

    ``init = xorout = 0xFF`` gives the catalogue CRC-8/SAE-J1850 (check 0x4B);
    the defaults (0x00, 0x00) are what E2E profile 1 effectively computes.
    """
    crc = init
    for b in data:
        crc = _TABLE_1D[crc ^ b]
    return crc ^ xorout


def e2e_crc(data_id: int, payload: bytes) -> int:
    """Return the profile-1 CRC of a frame: Data ID (low, high byte) then bytes 1..7."""
    return crc8_sae_j1850(bytes((data_id & 0xFF, (data_id >> 8) & 0xFF)) + bytes(payload[1:]))


def protect(data_id: int, frame: bytearray, counter: int) -> bytearray:
    """Write ``counter`` into byte 1 [3:0] and the CRC into byte 0 of ``frame`` (in place)."""
    frame[1] = (frame[1] & 0xF0) | (counter % COUNTER_MODULO)
    frame[0] = e2e_crc(data_id, frame)
    return frame


class E2EStatus(enum.Enum):
    """Result of checking one received frame."""

    OK = 'ok'                   # next counter, CRC good
    INITIAL = 'initial'         # first frame of a (new) stream: accepted
    WRONG_LENGTH = 'wrong_length'
    BAD_CRC = 'bad_crc'
    REPEATED = 'repeated'       # same counter as the last accepted frame
    SKIPPED = 'skipped'         # counter jumped by more than max_delta_counter
    BAD_COUNTER = 'bad_counter'  # counter value 15, never sent

    @property
    def accepted(self) -> bool:
        """Return True if the frame's data may be used."""
        return self in (E2EStatus.OK, E2EStatus.INITIAL)


#: Counter names of the rejection statuses (as reported on /diagnostics).
REJECT_COUNTERS = ('wrong_length', 'bad_crc', 'repeated', 'skipped', 'bad_counter')


@dataclass
class E2EChecker:
    """Receiver state of one protected message (one Data ID)."""

    data_id: int
    timeout_s: float
    max_delta_counter: int = 1
    last_counter: Optional[int] = None
    last_time: float = float('-inf')
    counts: Dict[str, int] = field(default_factory=lambda: dict.fromkeys(
        ('accepted', 'resyncs') + REJECT_COUNTERS, 0))

    def reset(self) -> None:
        """Forget the stream (next frame starts a new one), e.g. after the bus came back."""
        self.last_counter = None
        self.last_time = float('-inf')

    def check(self, data: bytes, now: float) -> E2EStatus:
        """Check one frame received at ``now`` (s) and update the counters."""
        status = self._classify(data, now)
        if status.accepted:
            self.counts['accepted'] += 1
            if status is E2EStatus.INITIAL:
                self.counts['resyncs'] += 1
        else:
            self.counts[status.value] += 1
        return status

    def _classify(self, data: bytes, now: float) -> E2EStatus:
        if len(data) != FRAME_LENGTH:
            return E2EStatus.WRONG_LENGTH
        if data[0] != e2e_crc(self.data_id, data):
            return E2EStatus.BAD_CRC
        counter = data[1] & 0x0F
        if counter >= COUNTER_MODULO:
            return E2EStatus.BAD_COUNTER
        fresh_stream = self.last_counter is None or now - self.last_time > self.timeout_s
        # Any intact frame keeps the stream alive, so a sender stuck on one counter
        # value is rejected for as long as it repeats, never re-accepted as "new".
        self.last_time = now
        delta = None if fresh_stream else (counter - self.last_counter) % COUNTER_MODULO
        if delta == 0:
            return E2EStatus.REPEATED
        self.last_counter = counter
        if delta is None:
            return E2EStatus.INITIAL
        if delta > self.max_delta_counter:
            return E2EStatus.SKIPPED       # dropped, but the stream re-syncs on it
        return E2EStatus.OK


@dataclass
class E2ESender:
    """Sender state of one protected message: the rolling alive counter."""

    data_id: int
    counter: int = 0

    def protect(self, frame: bytearray) -> bytearray:
        """Stamp the next counter value and the CRC into ``frame``."""
        protect(self.data_id, frame, self.counter)
        self.counter = (self.counter + 1) % COUNTER_MODULO
        return frame
