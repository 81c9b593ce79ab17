"""Message definitions (ros2msg) and type hashes exactly as rosbag2 stores them in MCAP.

rosbag2 (Jazzy, ``rosbag2_cpp::LocalMessageDefinitionSource::get_full_text``) finds
``<share>/<pkg>/msg/<Type>.msg`` through the ament index and concatenates the
definition with every type it depends on, depth first, each dependency once::

    <text of the root .msg, verbatim>
    ================================================================================
    MSG: std_msgs/Header
    <text of std_msgs/msg/Header.msg>
    ================================================================================
    MSG: builtin_interfaces/Time
    ...

A dependency is named as the field type is written in the .msg file
(``std_msgs/Header``; ``pkg/Type`` for an unqualified type of the same package), and
the dependencies of one file are visited in sorted order.  When no .msg exists the
.idl is used the same way with ``IDL:`` headers.  The wheels ship the same share
files as a ROS install (found via ``AMENT_PREFIX_PATH``, else ``sys.prefix/share``),
together with ``<Type>.json`` type descriptions that carry the RIHS01 type hash.
"""

import functools
import json
import os
import re
from typing import Dict, List, Set, Tuple

from erva_ros.core.bag import BagError
from erva_ros.core.model.params import ParamError
from erva_ros.core.settings.files import share_directory as find

#: Field types in a .msg ("foo_msgs/Bar" in "foo_msgs/Bar[] bar"); rosbag2's regex.
MSG_FIELD_TYPE_RE = re.compile(r'(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+')
#: Included types in an .idl (#include <foo_msgs/msg/Bar.idl>); rosbag2's regex.
IDL_FIELD_TYPE_RE = re.compile(r'(?:^|\n)#include\s+(?:"|<)([a-zA-Z0-9_/]+)\.idl(?:"|>)')
PRIMITIVE_TYPES = frozenset((
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
    'int32', 'uint32', 'int64', 'uint64', 'string'))
_NAME = r'[a-zA-Z][a-zA-Z0-9_]*'
_TYPE_RE = re.compile(rf'^({_NAME})/(?:({_NAME})/)?({_NAME})$')
DELIMITER = '=' * 80 + '\n'
#: Schema encodings of the two formats (mcap well-known values).
ENCODINGS = {'msg': 'ros2msg', 'idl': 'ros2idl'}


def split_type(type_name: str) -> Tuple[str, str, str]:
    """Return (package, namespace, name) of 'pkg/msg/Type' or 'pkg/Type' (namespace 'msg')."""
    m = _TYPE_RE.match(type_name)
    if not m:
        raise BagError(f'message type {type_name!r} is not of the form pkg/msg/Type')
    return m.group(1), m.group(2) or 'msg', m.group(3)


def share_directory(package: str) -> str:
    """Return the share directory of ``package`` (its .msg files); BagError if not found."""
    try:
        return find(package)
    except ParamError as exc:
        raise BagError(str(exc)) from None


def _read_definition(type_name: str, fmt: str) -> Tuple[str, str]:
    package, namespace, name = split_type(type_name)
    path = os.path.join(share_directory(package), namespace, f'{name}.{fmt}')
    try:
        with open(path, encoding='utf-8') as fh:
            return fh.read(), package
    except OSError:
        raise FileNotFoundError(path) from None


def _dependencies(text: str, fmt: str, package: str) -> List[str]:
    if fmt == 'idl':
        return sorted(set(IDL_FIELD_TYPE_RE.findall(text)))
    deps: Set[str] = set()
    for field_type in MSG_FIELD_TYPE_RE.findall(text):
        if field_type in PRIMITIVE_TYPES:
            continue
        deps.add(field_type if '/' in field_type else f'{package}/{field_type}')
    return sorted(deps)


@functools.lru_cache(maxsize=None)
def message_definition(type_name: str) -> Tuple[str, str]:
    """Return (schema encoding, full text) of ``type_name`` as rosbag2 writes its MCAP schema."""
    def full_text(fmt: str) -> str:
        seen: Set[str] = set()

        def append(name: str, depth: int) -> str:
            if depth <= 0:
                raise BagError(f'definition of {type_name} nests too deeply')
            text, package = _read_definition(name, fmt)
            out = text
            for dep in _dependencies(text, fmt, package):
                if dep not in seen:
                    seen.add(dep)
                    out += '\n' + DELIMITER + f'{fmt.upper()}: {dep}\n' + append(dep, depth - 1)
            return out
        return append(type_name, 50)

    try:
        return ENCODINGS['msg'], full_text('msg')
    except FileNotFoundError:
        pass
    try:
        return ENCODINGS['idl'], DELIMITER + f'IDL: {type_name}\n' + full_text('idl')
    except FileNotFoundError as exc:
        raise BagError(f'no .msg or .idl definition for {type_name} ({exc})') from None


@functools.lru_cache(maxsize=None)
def type_description_hash(type_name: str) -> str:
    """Return the RIHS01 type hash of ``type_name`` from its share .json, or '' if none."""
    package, namespace, name = split_type(type_name)
    full = f'{package}/{namespace}/{name}'
    path = os.path.join(share_directory(package), namespace, f'{name}.json')
    try:
        with open(path, encoding='utf-8') as fh:
            hashes: List[Dict[str, str]] = json.load(fh).get('type_hashes', [])
    except (OSError, ValueError):
        return ''
    return next((h.get('hash_string', '') for h in hashes if h.get('type_name') == full), '')


__all__ = ['message_definition', 'type_description_hash', 'split_type',
           'share_directory', 'DELIMITER']
