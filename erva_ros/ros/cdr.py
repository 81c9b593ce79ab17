"""CDR, the wire format of ROS messages, in one place: the hot path's direct (de)coding, sizes.

Converting a message between its CDR bytes and an rclpy Python object costs more than
anything the bridge or the estimator does with it (measured in the live loop: taking a
10-point ``trajectory_msgs/JointTrajectory`` 0.36 ms p50, a ``sensor_msgs/JointState``
0.16 ms).  The hot-path subscriptions therefore take the serialized message
(``raw=True``) and read the few fields they need with ``struct`` here, and the
estimator publishes its state as bytes encoded here (rclpy's ``publish`` accepts them).

Format: plain CDR (XCDR1) little-endian, as rmw_fastrtps_cpp writes it: a 4-byte
encapsulation header ``00 01 00 00``, then the fields in order, each primitive aligned
to its size counted from the end of that header; strings are a uint32 length (with the
terminating NUL) and the bytes; sequences a uint32 count and the elements.  Only the
little-endian CDR encapsulation is accepted; anything truncated, oversized or
inconsistent raises :class:`CdrError` (the caller counts and drops it).  The tests
check both directions against rclpy's own (de)serialization.

:func:`encoded_size` gives the exact CDR size of any message object (from its rosidl
type description), which the bag writer uses to trim rclpy's serialized bytes.
"""

import struct
from typing import List, Sequence, Tuple

#: Encapsulation header of plain little-endian CDR.
CDR_LE = b'\x00\x01\x00\x00'
#: Refuse sequences longer than this (a corrupt count must not allocate gigabytes).
MAX_ELEMENTS = 4096

_U32 = struct.Struct('<I')
_TIME = struct.Struct('<iI')
_ACCEL = struct.Struct('<iII4x6d')


class CdrError(ValueError):
    """The bytes are not a well-formed message of the expected type."""


def _aligned(pos: int, size: int) -> int:
    """Return ``pos`` rounded up to a multiple of ``size`` (CDR aligns each primitive)."""
    return pos + (-pos % size)


class _Reader:
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
        self._align(4)
        self._need(4)
        (v,) = _U32.unpack_from(self.buf, self.pos)
        self.pos += 4
        return v

    def count(self) -> int:
        n = self.u32()
        if n > MAX_ELEMENTS:
            raise CdrError(f'sequence of {n} elements (limit {MAX_ELEMENTS})')
        return n

    def time_ns(self) -> Tuple[int, int]:
        """builtin_interfaces/Time or Duration: (sec, nanosec)."""
        self._align(4)
        self._need(8)
        sec, nsec = _TIME.unpack_from(self.buf, self.pos)
        self.pos += 8
        return sec, nsec

    def byte(self) -> int:
        self._need(1)
        v = self.buf[self.pos]
        self.pos += 1
        return v

    def string(self) -> str:
        n = self.u32()
        if n == 0 or n > MAX_ELEMENTS:
            raise CdrError(f'string of length {n}')
        self._need(n)
        raw = bytes(self.buf[self.pos:self.pos + n - 1])
        self.pos += n
        try:
            return raw.decode()
        except UnicodeDecodeError:
            raise CdrError('string is not UTF-8') from None

    def strings(self) -> List[str]:
        return [self.string() for _ in range(self.count())]

    def doubles(self) -> Tuple[float, ...]:
        n = self.count()
        if n == 0:
            return ()
        self._align(8)
        self._need(8 * n)
        v = struct.unpack_from(f'<{n}d', self.buf, self.pos)
        self.pos += 8 * n
        return v

    def header(self) -> int:
        """std_msgs/Header: return the stamp in ns (frame_id is read and dropped)."""
        sec, nsec = self.time_ns()
        self.string()
        return sec * 1_000_000_000 + nsec


def decode_joint_state(data: bytes):
    """Return (stamp_ns, name, position, velocity, effort) of a sensor_msgs/JointState."""
    r = _Reader(data)
    stamp = r.header()
    return stamp, r.strings(), r.doubles(), r.doubles(), r.doubles()


def decode_joint_trajectory(data: bytes):
    """Return (stamp_ns, joint_names, [(positions, (sec, nanosec)), ...]) of a trajectory.

    trajectory_msgs/JointTrajectory; velocities, accelerations and effort are skipped.
    """
    r = _Reader(data)
    stamp = r.header()
    names = r.strings()
    points = []
    for _ in range(r.count()):
        positions = r.doubles()
        r.doubles()                     # velocities
        r.doubles()                     # accelerations
        r.doubles()                     # effort
        points.append((positions, r.time_ns()))
    return stamp, names, points


def header_stamp_ns(data: bytes) -> int:
    """Return the stamp (ns) of a message that starts with a std_msgs/Header or a Time.

    Every topic of the loop is such a message (rosgraph_msgs/Clock starts with its Time).
    """
    sec, nsec = _Reader(data).time_ns()
    return sec * 1_000_000_000 + nsec


def status_seqs(data: bytes) -> List[Tuple[str, int]]:
    """Return (node, status_seq) of each status in a diagnostic_msgs/DiagnosticArray.

    ``node`` is the status name's last path element (``/erva/nmpc_node`` -> ``nmpc_node``);
    statuses without a ``status_seq`` value are left out.
    """
    r = _Reader(data)
    r.header()
    out = []
    for _ in range(r.count()):
        r.byte()                                    # level
        name, _, _ = r.string(), r.string(), r.string()
        seq = None
        for _ in range(r.count()):
            key, value = r.string(), r.string()
            if key == 'status_seq':
                seq = int(value)
        if seq is not None:
            out.append((name.rsplit('/', 1)[-1], seq))
    return out


class JointStateEncoder:
    """Encode sensor_msgs/JointState messages with fixed names and an empty frame_id.

    The names are encoded once; each call packs the stamp and the value arrays.
    """

    def __init__(self, names: Sequence[str]):
        self.names = tuple(names)
        head = bytearray()
        head += _U32.pack(1) + b'\x00'  # frame_id '' (length 1: the NUL)
        head += b'\x00' * (-len(head) % 4)
        head += _U32.pack(len(self.names))
        for name in self.names:
            raw = name.encode() + b'\x00'
            head += _U32.pack(len(raw)) + raw
            head += b'\x00' * (-len(head) % 4)
        self._names = bytes(head)        # from payload offset 8 (after the stamp)

    def encode(self, stamp_ns: int, position: Sequence[float] = (),
               velocity: Sequence[float] = (), effort: Sequence[float] = ()) -> bytes:
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        out = bytearray(CDR_LE)
        out += _TIME.pack(sec, nsec)
        out += self._names
        for values in (position, velocity, effort):
            n = len(values)
            out += _U32.pack(n)
            if n:
                out += b'\x00' * (-(len(out) - 4) % 8)
                out += struct.pack(f'<{n}d', *values)
        return bytes(out)


def encode_accel_stamped(stamp_ns: int, linear=(0.0, 0.0, 0.0), angular=(0.0, 0.0, 0.0)
                         ) -> bytes:
    """Encode a geometry_msgs/AccelStamped with an empty frame_id (m/s², rad/s²)."""
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    # payload: stamp 0-7, frame_id length 8-11 and its NUL 12, padding to 16, 6 doubles
    return CDR_LE + _ACCEL.pack(sec, nsec, 1, *linear, *angular)


# Sizes of the CDR primitive types (rosidl_parser BasicType names), bytes.
_PRIMITIVE_SIZE = {'boolean': 1, 'octet': 1, 'char': 1, 'int8': 1, 'uint8': 1, 'int16': 2,
                   'uint16': 2, 'int32': 4, 'uint32': 4, 'int64': 8, 'uint64': 8, 'float': 4,
                   'double': 8, 'long double': 16, 'wchar': 2}


def encoded_size(msg) -> int:
    """Return the plain-CDR size of any ROS message object's fields (without the header).

    Generic, from the message's rosidl type description: what
    :func:`erva_ros.ros.bag_messages.serialize` trims rclpy's output to.
    """
    return _fields_end(msg, 0)


def _fields_end(msg, pos: int) -> int:
    """Return the offset after the fields of message ``msg`` encoded from ``pos``."""
    for name, field_type in zip(msg.get_fields_and_field_types(), msg.SLOT_TYPES):
        pos = _value_end(getattr(msg, name), field_type, pos)
    return pos


def _value_end(value, typ, pos: int) -> int:
    """Return the offset after ``value`` of rosidl type ``typ`` encoded at ``pos``."""
    from rosidl_parser import definition as d
    if isinstance(typ, d.BasicType):
        size = _PRIMITIVE_SIZE[typ.typename]
        return _aligned(pos, size) + size
    if isinstance(typ, d.AbstractString):
        return _aligned(pos, 4) + 4 + len(value.encode('utf-8')) + 1
    if isinstance(typ, d.NamespacedType):
        return _fields_end(value, pos)
    if isinstance(typ, d.AbstractNestedType):
        if not isinstance(typ, d.Array):
            pos = _aligned(pos, 4) + 4  # the element count
        inner = typ.value_type
        if isinstance(inner, d.BasicType):
            n = len(value)
            size = _PRIMITIVE_SIZE[inner.typename]
            return _aligned(pos, size) + n * size if n else pos
        for item in value:
            pos = _value_end(item, inner, pos)
        return pos
    raise TypeError(f'cannot size CDR of {typ!r}')  # wstrings: not used here


__all__ = ['CdrError', 'JointStateEncoder', 'encode_accel_stamped', 'decode_joint_state',
           'decode_joint_trajectory', 'header_stamp_ns', 'status_seqs', 'encoded_size',
           'CDR_LE', 'MAX_ELEMENTS']
