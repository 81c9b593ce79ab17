"""Decode the three message types a drive's bag gives the map, from CDR bytes, without ROS.

A small decoder of its own, for
``sensor_msgs/JointState`` (``ecu/measurements``), ``geometry_msgs/PointStamped``
(``road/height``) and ``geometry_msgs/PoseWithCovarianceStamped`` (``road/estimate``):
plain little-endian CDR, each primitive aligned to its size from the end of the 4-byte
encapsulation header.  Anything malformed raises :class:`CdrFormatError`.
"""

import struct
from typing import List, Tuple

_LE = b'\x00\x01\x00\x00'
_MAX = 4096


class CdrFormatError(ValueError):
    """The bytes are not a well-formed message of the expected type."""


class _Cursor:
    def __init__(self, data: bytes):
        if len(data) < 8 or data[:4] != _LE:
            raise CdrFormatError('not little-endian plain CDR')
        self.buf = memoryview(data)[4:]
        self.pos = 0

    def _take(self, size: int, align: int) -> int:
        self.pos += -self.pos % align
        start = self.pos
        self.pos += size
        if self.pos > len(self.buf):
            raise CdrFormatError('truncated message')
        return start

    def u32(self) -> int:
        return struct.unpack_from('<I', self.buf, self._take(4, 4))[0]

    def stamp_ns(self) -> int:
        sec, nsec = struct.unpack_from('<iI', self.buf, self._take(8, 4))
        return sec * 1_000_000_000 + nsec

    def string(self) -> str:
        n = self.u32()
        if not 0 < n <= _MAX:
            raise CdrFormatError(f'string of length {n}')
        start = self._take(n, 1)
        try:
            return bytes(self.buf[start:start + n - 1]).decode()
        except UnicodeDecodeError:
            raise CdrFormatError('string is not UTF-8') from None

    def doubles(self, n: int = -1) -> Tuple[float, ...]:
        if n < 0:
            n = self.u32()
            if n > _MAX:
                raise CdrFormatError(f'sequence of {n} elements')
        if n == 0:
            return ()
        return struct.unpack_from(f'<{n}d', self.buf, self._take(8 * n, 8))

    def header(self) -> int:
        stamp = self.stamp_ns()
        self.string()
        return stamp


def joint_state(data: bytes) -> Tuple[int, List[str], Tuple[float, ...]]:
    """Return (stamp ns, names, positions) of a sensor_msgs/JointState."""
    c = _Cursor(data)
    stamp = c.header()
    n = c.u32()
    if n > _MAX:
        raise CdrFormatError(f'{n} names')
    names = [c.string() for _ in range(n)]
    return stamp, names, c.doubles()


def point_stamped(data: bytes) -> Tuple[int, Tuple[float, float, float]]:
    """Return (stamp ns, (x, y, z)) of a geometry_msgs/PointStamped."""
    c = _Cursor(data)
    stamp = c.header()
    return stamp, c.doubles(3)


def pose_with_covariance_stamped(data: bytes) -> Tuple[int, Tuple[float, ...], Tuple[float, ...]]:
    """Return (stamp ns, position (x, y, z), covariance (36)) of a PoseWithCovarianceStamped."""
    c = _Cursor(data)
    stamp = c.header()
    position = c.doubles(3)
    c.doubles(4)                    # orientation
    return stamp, position, c.doubles(36)


__all__ = ['CdrFormatError', 'joint_state', 'point_stamped', 'pose_with_covariance_stamped']
