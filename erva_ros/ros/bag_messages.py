"""ROS messages of a bag: the Python class of a type, CDR from and to message objects.

The bag file I/O (erva_ros/core/bag) works on bytes and type names; what needs the
generated message classes or rclpy's (de)serialiser lives here, in the ros ring.
"""

import importlib
from typing import Optional

from rosidl_parser import definition as d

from erva_ros.core.bag import BagError
from erva_ros.core.bag.schemas import split_type
from erva_ros.core.bag.writer import BagWriter


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


def _aligned(pos: int, size: int) -> int:
    """Return ``pos`` rounded up to a multiple of ``size`` (CDR aligns each primitive)."""
    return pos + (-pos % size)


def message_class(type_name: str):
    """Return the Python message class of 'pkg/msg/Type' (the generated rosidl module)."""
    package, namespace, name = split_type(type_name)
    try:
        return getattr(importlib.import_module(f'{package}.{namespace}'), name)
    except (ImportError, AttributeError):
        raise BagError(f'message type {type_name} is not installed') from None


def serialize(msg) -> bytes:
    """Return the CDR bytes of a ROS message (``rclpy.serialization``), exactly as long.

    ``serialize_message`` hands back rmw_fastrtps' size *estimate*, which can exceed
    the encoding by a few bytes of junk; strict readers (rosbags) reject that, and
    what travels over DDS ends where the encoding ends.  The exact length is the
    4-byte encapsulation header plus the classic-CDR size of the fields
    (:func:`encoded_size`).
    """
    from rclpy.serialization import serialize_message
    data = serialize_message(msg)
    end = 4 + encoded_size(msg)
    if end > len(data):
        raise BagError(f'CDR size of {type(msg).__name__} computed as {end} B, '
                       f'but rclpy produced {len(data)} B')
    return data[:end]


def write_message(writer: BagWriter, topic: str, msg, log_time_ns: int,
                  publish_time_ns: Optional[int] = None) -> None:
    """Serialise a ROS message object (CDR, :func:`serialize`) and append it to ``writer``."""
    writer.write(topic, serialize(msg), log_time_ns, publish_time_ns)


__all__ = ['encoded_size', 'message_class', 'serialize', 'write_message']
