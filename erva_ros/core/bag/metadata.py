"""``metadata.yaml`` of a bag directory, as rosbag2 Jazzy writes it (bag format version 9).

Fields, in rosbag2's order (``rosbag2_storage/yaml.hpp``, ``BagMetadata``)::

    rosbag2_bagfile_information:
      version: 9
      storage_identifier: mcap
      duration: {nanoseconds}                  # last - first message log time (receive time)
      starting_time: {nanoseconds_since_epoch} # first message log time
      message_count
      topics_with_message_count:               # [{topic_metadata: {name, type,
                                               #   serialization_format: cdr,
                                               #   offered_qos_profiles: [..],
                                               #   type_description_hash}, message_count}]
      compression_format: ""                   # rosbag2 file/message compression: none
      compression_mode: ""
      relative_file_paths: [<bag>_0.mcap, <bag>_1.mcap, ...]   # a split bag: several
      files: [{path, starting_time, duration, message_count}]   # one per file, in order
      custom_data: ~                           # or a map of strings
      ros_distro: jazzy

The text is emitted in yaml-cpp's block style (sequences indented under their key, no
trailing newline) so that the file looks like one ``ros2 bag record`` wrote.  The same
mapping, without the root key, is stored in the MCAP file as the ``rosbag2`` metadata
record (``serialized_metadata``), as the rosbag2 MCAP storage plugin does on close.
"""

import datetime
import functools
import json
import os
import re
from typing import Dict, List, Mapping, Optional, Sequence

import yaml

from erva_ros.core.bag import BagError

BAG_FORMAT_VERSION = 9
STORAGE_IDENTIFIER = 'mcap'
ROS_DISTRO = 'jazzy'
METADATA_FILE = 'metadata.yaml'
ROOT_KEY = 'rosbag2_bagfile_information'


def format_duration(ns: int) -> str:
    """Return a duration as ``ros2 bag info`` prints it: seconds, 9 decimals (10.945622281)."""
    ns = int(ns)
    return f'{ns // 10**9}.{ns % 10**9:09d}'


def format_time_point(ns: Optional[int], utc: bool = False) -> str:
    """Return a time as ``ros2 bag info`` (Jazzy) prints it, or ``unknown`` for None.

    As rosbag2_py's ``format_time_point``: the local date and time (``%b %e %Y
    %H:%M:%S``) with nine decimals, then the seconds since the epoch, e.g.
    ``Dec  7 2026 15:46:41.473955228 (1796658401.473955228)``.  ``utc``: in UTC instead.
    """
    if ns is None:
        return 'unknown'
    sec = int(ns) // 10**9
    tz = datetime.timezone.utc if utc else None
    when = datetime.datetime.fromtimestamp(sec, tz=tz)
    frac = f'{int(ns) % 10**9:09d}'
    return f'{when.strftime("%b %e %Y %H:%M:%S")}.{frac} ({sec}.{frac})'


def topic_entry(name: str, type_name: str, offered_qos: Sequence[Dict], type_hash: str,
                count: int, serialization_format: str = 'cdr') -> Dict:
    """Return one ``topics_with_message_count`` entry."""
    return {'topic_metadata': {'name': name, 'type': type_name,
                               'serialization_format': serialization_format,
                               'offered_qos_profiles': list(offered_qos),
                               'type_description_hash': type_hash},
            'message_count': int(count)}


def file_entry(path: str, start_ns: Optional[int], end_ns: Optional[int], count: int) -> Dict:
    """Return one ``files`` entry: a file's first log time, its span and its messages."""
    start = int(start_ns) if count and start_ns is not None else 0
    duration = max(0, int(end_ns) - start) if count and end_ns is not None else 0
    return {'path': path, 'starting_time': {'nanoseconds_since_epoch': start},
            'duration': {'nanoseconds': duration}, 'message_count': int(count)}


def bag_metadata(files: Sequence[Dict], topics: Sequence[Dict],
                 custom_data: Optional[Mapping[str, str]] = None) -> Dict:
    """Return the BagMetadata mapping of an MCAP bag of ``files`` (:func:`file_entry`, in order).

    The bag's start and duration span its files' (times: log time, ns), as rosbag2's.
    """
    count = sum(int(t['message_count']) for t in topics)
    spans = [(f['starting_time']['nanoseconds_since_epoch'], f['duration']['nanoseconds'])
             for f in files if f['message_count']]
    start = min(s for s, _ in spans) if spans else 0
    duration = max(s + d for s, d in spans) - start if spans else 0
    custom = {str(k): str(v) for k, v in sorted((custom_data or {}).items())} or None
    return {
        'version': BAG_FORMAT_VERSION,
        'storage_identifier': STORAGE_IDENTIFIER,
        'duration': {'nanoseconds': duration},
        'starting_time': {'nanoseconds_since_epoch': start},
        'message_count': count,
        'topics_with_message_count': list(topics),
        'compression_format': '',
        'compression_mode': '',
        'relative_file_paths': [f['path'] for f in files],
        'files': list(files),
        'custom_data': custom,
        'ros_distro': ROS_DISTRO,
    }


# -- yaml-cpp style emitter -----------------------------------------------------------------
_PLAIN_RE = re.compile(r'[A-Za-z0-9_/][A-Za-z0-9_./+-]*')


def _scalar(value) -> str:
    if value is None:
        return '~'
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    text = str(value)
    if _PLAIN_RE.fullmatch(text) and not _looks_typed(text):
        return text
    return json.dumps(text, ensure_ascii=False)  # a JSON string is a YAML double-quoted one


@functools.lru_cache(maxsize=256)   # the same names and QoS texts at every split
def _looks_typed(text: str) -> bool:
    """Return True if YAML would read the plain ``text`` as something other than a string."""
    try:
        return yaml.safe_load(text) != text
    except yaml.YAMLError:
        return True


def _emit_map(mapping: Mapping, indent: int) -> List[str]:
    pad = ' ' * indent
    lines: List[str] = []
    for key, value in mapping.items():
        if isinstance(value, Mapping) and value:
            lines.append(f'{pad}{key}:')
            lines.extend(_emit_map(value, indent + 2))
        elif isinstance(value, (list, tuple)) and value:
            lines.append(f'{pad}{key}:')
            lines.extend(_emit_seq(value, indent + 2))
        elif isinstance(value, Mapping):
            lines.append(f'{pad}{key}: {{}}')
        elif isinstance(value, (list, tuple)):
            lines.append(f'{pad}{key}: []')
        else:
            lines.append(f'{pad}{key}: {_scalar(value)}')
    return lines


def _emit_seq(seq: Sequence, indent: int) -> List[str]:
    pad = ' ' * indent
    lines: List[str] = []
    for item in seq:
        if isinstance(item, Mapping) and item:
            sub = _emit_map(item, indent + 2)
            lines.append(pad + '- ' + sub[0][indent + 2:])
            lines.extend(sub[1:])
        else:
            lines.append(f'{pad}- {_scalar(item)}')
    return lines


def dump_yaml(metadata: Mapping, root: bool = True) -> str:
    """Return ``metadata`` as yaml-cpp prints it, under ``rosbag2_bagfile_information``."""
    if root:
        return '\n'.join([f'{ROOT_KEY}:'] + _emit_map(metadata, 2))
    return '\n'.join(_emit_map(metadata, 0))


def write_metadata(bag_dir: str, metadata: Mapping) -> str:
    """Write ``bag_dir/metadata.yaml`` atomically (temp file + rename); return its path."""
    path = os.path.join(bag_dir, METADATA_FILE)
    tmp = path + '.tmp'
    try:
        with open(tmp, 'w', encoding='utf-8') as fh:
            fh.write(dump_yaml(metadata))
        os.replace(tmp, path)
    except OSError as exc:
        raise BagError(f'cannot write {path}: {exc.strerror or exc}') from None
    return path


def read_metadata(bag_dir: str) -> Dict:
    """Read and check ``bag_dir/metadata.yaml``; return the BagMetadata mapping."""
    path = os.path.join(bag_dir, METADATA_FILE)
    try:
        with open(path, encoding='utf-8') as fh:
            doc = yaml.safe_load(fh)
    except FileNotFoundError:
        raise BagError(f'{bag_dir}: no metadata.yaml (not a bag directory, or the recorder '
                       'was killed: run "erva bag repair")') from None
    except (OSError, UnicodeDecodeError) as exc:
        raise BagError(f'cannot read {path}: {getattr(exc, "strerror", None) or exc}') from None
    except yaml.YAMLError as exc:
        where = getattr(exc, 'problem_mark', None)
        line = f' (line {where.line + 1})' if where is not None else ''
        raise BagError(f'{path} is not valid YAML{line}') from None
    meta = doc.get(ROOT_KEY) if isinstance(doc, dict) else None
    if not isinstance(meta, dict):
        raise BagError(f'{path} has no {ROOT_KEY} mapping: not a rosbag2 metadata file')
    version = meta.get('version')
    if not isinstance(version, int) or not 1 <= version <= BAG_FORMAT_VERSION:
        raise BagError(f'{path}: unsupported bag format version {version!r} '
                       f'(1..{BAG_FORMAT_VERSION})')
    storage = meta.get('storage_identifier')
    if storage != STORAGE_IDENTIFIER:
        raise BagError(f'{path}: storage {storage!r} is not supported (only mcap bags)')
    files = meta.get('relative_file_paths')
    if not isinstance(files, list) or not files or not all(isinstance(f, str) for f in files):
        raise BagError(f'{path}: relative_file_paths is missing or empty')
    if meta.get('compression_mode') not in (None, '', 'none', 'None'):
        raise BagError(f'{path}: rosbag2 {meta["compression_mode"]} compression is not '
                       'supported (MCAP chunk compression is)')
    return meta


__all__ = ['format_duration', 'format_time_point',
           'bag_metadata', 'file_entry', 'topic_entry', 'dump_yaml', 'write_metadata',
           'read_metadata', 'METADATA_FILE', 'BAG_FORMAT_VERSION']
