"""ROS messages of a bag: the Python class of a type, CDR from and to message objects.

The bag file I/O (erva_ros/core/bag) works on bytes and type names; what needs the
generated message classes or rclpy's (de)serialiser lives here, in the ros ring.
"""

import importlib
from typing import Dict, Iterable, Iterator, Optional, Tuple

from erva_ros.core.bag import BagError
from erva_ros.core.bag.reader import Bag, BagMessage
from erva_ros.core.bag.schemas import split_type
from erva_ros.core.bag.writer import BagWriter
from erva_ros.ros.cdr import encoded_size


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
    (:func:`erva_ros.ros.cdr.encoded_size`).
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


def decoded(bag: Bag, topics: Optional[Iterable[str]] = None
            ) -> Iterator[Tuple[BagMessage, object]]:
    """Yield (message, deserialised ROS message) in log-time order (rclpy, CDR)."""
    from rclpy.serialization import deserialize_message
    classes: Dict[str, object] = {}
    for m in bag.messages(topics):
        cls = classes.get(m.type)
        if cls is None:
            cls = classes[m.type] = message_class(m.type)
        try:
            yield m, deserialize_message(m.data, cls)
        except Exception:  # noqa: BLE001 -- rclpy raises RMWError on bad CDR
            raise BagError(f'{bag.mcap_path}: a {m.type} message on {m.topic} at '
                           f'{m.log_time_ns} ns does not decode') from None


__all__ = ['message_class', 'serialize', 'write_message', 'decoded']
