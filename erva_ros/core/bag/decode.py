"""Decoders of recorded CDR messages that the ROS ring's ``ros/cdr.py`` does not have.

Plain little-endian CDR (XCDR1), as rmw_fastrtps_cpp writes it and the recorder keeps
it: a 4-byte encapsulation header, then the fields, each primitive aligned to its size
counted from the end of that header.  Only what `erva identify` reads from a bag without
rclpy: ``geometry_msgs/PointStamped`` (road/height) and ``geometry_msgs/AccelStamped``
(sprung_accel).  Anything malformed raises :class:`CdrDecodeError` (a ValueError).
"""

import struct
from typing import Tuple

_HEAD = struct.Struct('<iII')          # stamp sec, nanosec, frame_id length
_CDR_LE = b'\x00\x01\x00\x00'


class CdrDecodeError(ValueError):
    """The bytes are not a well-formed message of the expected type."""


def _header(data: bytes) -> Tuple[int, int]:
    """Return (stamp ns, offset of the first field after the header, in the payload)."""
    if len(data) < 4 + _HEAD.size or data[:4] != _CDR_LE:
        raise CdrDecodeError('not little-endian plain CDR, or shorter than a header')
    sec, nsec, n = _HEAD.unpack_from(data, 4)
    if n == 0 or 4 + _HEAD.size + n > len(data):
        raise CdrDecodeError(f'frame_id of length {n} does not fit the message')
    return sec * 1_000_000_000 + nsec, _HEAD.size + n


def _doubles(data: bytes, pos: int, count: int) -> Tuple[float, ...]:
    pos += -pos % 8                       # align to 8, counted from the payload start
    if 4 + pos + 8 * count > len(data):
        raise CdrDecodeError(f'truncated: {count} doubles do not fit the message')
    return struct.unpack_from(f'<{count}d', data, 4 + pos)


def decode_point_stamped(data: bytes) -> Tuple[int, Tuple[float, float, float]]:
    """Return (stamp ns, (x, y, z)) of a geometry_msgs/PointStamped."""
    stamp, pos = _header(data)
    return stamp, _doubles(data, pos, 3)


def decode_accel_stamped(data: bytes) -> Tuple[int, Tuple[float, ...], Tuple[float, ...]]:
    """Return (stamp ns, linear (x, y, z), angular (x, y, z)) of a geometry_msgs/AccelStamped."""
    stamp, pos = _header(data)
    v = _doubles(data, pos, 6)
    return stamp, v[:3], v[3:]


__all__ = ['CdrDecodeError', 'decode_point_stamped', 'decode_accel_stamped']
