"""CDR, the wire format of ROS 2 messages: a small reader and writer, no ROS needed.

Format: plain CDR (XCDR1) little-endian, as rmw_fastrtps_cpp writes it: a 4-byte
encapsulation header ``00 01 00 00``, then the fields in order, each primitive aligned
to its size counted from the end of that header; strings are a uint32 length (with the
terminating NUL) and the bytes; sequences a uint32 count and the elements.  Only the
little-endian CDR encapsulation is accepted; anything truncated, oversized or
inconsistent raises :class:`CdrError`, which is a
:class:`~erva_ros.core.loop.validation.MessageRejected`: the caller counts and drops it.

Why our own: rclpy's conversion between bytes and a Python message object costs more
than anything the loop does with a message (a 10-point JointTrajectory 0.36 ms p50, a
JointState 0.16 ms), and reports and bag tools must run without the ROS wheels.  The
message families themselves are :mod:`erva_ros.core.contract`.
"""

import struct
from typing import List, Sequence, Tuple

from erva_ros.core.loop.validation import MessageRejected

#: Encapsulation header of plain little-endian CDR.
CDR_LE = b'\x00\x01\x00\x00'
#: Refuse sequences longer than this (a corrupt count must not allocate gigabytes).
MAX_ELEMENTS = 4096
NS = 1_000_000_000

_U32 = struct.Struct('<I')
_TIME = struct.Struct('<iI')


class CdrError(MessageRejected):
    """The bytes are not a well-formed message of the expected type."""


class Reader:
    """Sequential CDR reader over one message (offsets relative to the payload)."""

    __slots__ = ('buf', 'pos', 'end')

    def __init__(self, data: bytes):
        if len(data) < 4 or data[:4] != CDR_LE:
            raise CdrError('not little-endian plain CDR (encapsulation header)')
        self.buf = memoryview(data)[4:]
        self.pos = 0
        self.end = len(self.buf)

    def _align(self, n: int) -> None:
        self.pos += -self.pos % n

    def _need(self, n: int) -> None:
        if self.pos + n > self.end:
            raise CdrError(f'truncated at byte {self.pos + 4} (need {n} more)')

    def u32(self) -> int:
        """Return a uint32."""
        self._align(4)
        self._need(4)
        (v,) = _U32.unpack_from(self.buf, self.pos)
        self.pos += 4
        return v

    def count(self) -> int:
        """Return the element count of a sequence (at most MAX_ELEMENTS)."""
        n = self.u32()
        if n > MAX_ELEMENTS:
            raise CdrError(f'sequence of {n} elements (limit {MAX_ELEMENTS})')
        return n

    def time(self) -> Tuple[int, int]:
        """Return a builtin_interfaces/Time or Duration as (sec, nanosec)."""
        self._align(4)
        self._need(8)
        sec, nsec = _TIME.unpack_from(self.buf, self.pos)
        self.pos += 8
        return sec, nsec

    def time_ns(self) -> int:
        """Return a builtin_interfaces/Time or Duration in nanoseconds."""
        sec, nsec = self.time()
        return sec * NS + nsec

    def byte(self) -> int:
        """Return an octet / uint8."""
        self._need(1)
        v = self.buf[self.pos]
        self.pos += 1
        return v

    def i64(self) -> int:
        """Return an int64."""
        self._align(8)
        self._need(8)
        (v,) = struct.unpack_from('<q', self.buf, self.pos)
        self.pos += 8
        return v

    def double(self) -> float:
        """Return a float64."""
        self._align(8)
        self._need(8)
        (v,) = struct.unpack_from('<d', self.buf, self.pos)
        self.pos += 8
        return v

    def string(self, limit: int = MAX_ELEMENTS) -> str:
        """Return the next text field, UTF-8 decoded (at most ``limit`` bytes)."""
        n = self.u32()
        if n == 0 or n > limit:
            raise CdrError(f'string of length {n}')
        self._need(n)
        raw = bytes(self.buf[self.pos:self.pos + n - 1])
        self.pos += n
        try:
            return raw.decode()
        except UnicodeDecodeError:
            raise CdrError('string is not UTF-8') from None

    def strings(self) -> List[str]:
        """Return a sequence of strings."""
        return [self.string() for _ in range(self.count())]

    def doubles(self, n: int = -1) -> Tuple[float, ...]:
        """Return a sequence of float64 (``n`` >= 0: a fixed array of n, no count)."""
        if n < 0:
            n = self.count()
        if n == 0:
            return ()
        self._align(8)
        self._need(8 * n)
        v = struct.unpack_from(f'<{n}d', self.buf, self.pos)
        self.pos += 8 * n
        return v

    def header(self) -> int:
        """Return a std_msgs/Header's stamp in ns (its frame_id is read and dropped)."""
        stamp = self.time_ns()
        self.string()
        return stamp


class Writer:
    """Sequential CDR writer of one message; :meth:`bytes` returns it with its header."""

    __slots__ = ('out',)

    def __init__(self):
        self.out = bytearray(CDR_LE)

    def _align(self, n: int) -> None:
        self.out += b'\x00' * (-(len(self.out) - 4) % n)

    def u32(self, v: int) -> 'Writer':
        """Append a uint32."""
        self._align(4)
        self.out += _U32.pack(v)
        return self

    def time_ns(self, ns: int) -> 'Writer':
        """Append a builtin_interfaces/Time or Duration of ``ns`` nanoseconds."""
        self._align(4)
        sec, nsec = divmod(int(ns), NS)
        self.out += _TIME.pack(sec, nsec)
        return self

    def byte(self, v: int) -> 'Writer':
        """Append an octet / uint8."""
        self.out.append(v)
        return self

    def string(self, s: str) -> 'Writer':
        """Append ``s`` (UTF-8, NUL-terminated)."""
        raw = s.encode() + b'\x00'
        self.u32(len(raw))
        self.out += raw
        return self

    def strings(self, items: Sequence[str]) -> 'Writer':
        """Append a sequence of strings."""
        self.u32(len(items))
        for s in items:
            self.string(s)
        return self

    def doubles(self, values: Sequence[float], fixed: bool = False) -> 'Writer':
        """Append a sequence of float64 (``fixed``: an array, no count)."""
        n = len(values)
        if not fixed:
            self.u32(n)
        if n:
            self._align(8)
            self.out += struct.pack(f'<{n}d', *values)
        return self

    def header(self, stamp_ns: int, frame_id: str = '') -> 'Writer':
        """Append a std_msgs/Header."""
        return self.time_ns(stamp_ns).string(frame_id)

    def bytes(self) -> bytes:
        """Return what was written, encapsulation header included."""
        return bytes(self.out)


def header_stamp_ns(data: bytes) -> int:
    """Return the stamp (ns) of a message that starts with a std_msgs/Header or a Time.

    Every topic of the loop is such a message (rosgraph_msgs/Clock starts with its Time).
    """
    return Reader(data).time_ns()


__all__ = ['CDR_LE', 'MAX_ELEMENTS', 'NS', 'CdrError', 'Reader', 'Writer', 'header_stamp_ns']
