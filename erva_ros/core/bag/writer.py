"""rosbag2-compatible MCAP writer: one bag directory with ``<name>_0.mcap`` and metadata.yaml.

The file follows the rosbag2 MCAP storage plugin (``rosbag2_storage_mcap``, Jazzy):

* header profile ``ros2``; chunked, uncompressed by default (rosbag2's default; zstd/lz4
  chunk compression optional), message indexes, chunk indexes, statistics and summary
  offsets; the summary repeats schemas and channels;
* one schema per message type: name ``pkg/msg/Type``, encoding ``ros2msg``, data the
  definition with all dependent definitions (:mod:`erva_ros.core.bag.schemas`);
* one channel per topic: message encoding ``cdr``, metadata ``offered_qos_profiles``
  (YAML string, :mod:`erva_ros.core.bag.qos`) and ``topic_type_hash`` (RIHS01);
* messages: log time = receive time, publish time = the publisher's send time (DDS
  source timestamp), both in ns since the epoch (or sim time), as rosbag2 records them;
* on close a ``rosbag2`` metadata record (``serialized_metadata``) and ``metadata.yaml``.

Crash safety: the chunk in progress is closed and handed to the OS whenever it
reaches ``chunk_size`` bytes or ``flush_period_s`` has passed, so a killed recorder
loses at most that much; the session's own metadata record (``erva_session``) is
written first of all.  ``erva bag repair`` rebuilds index and metadata.yaml.
"""

import os
import time
from typing import Callable, Dict, List, Mapping, Optional, Sequence

from erva_ros import __version__
from erva_ros.core.bag import BagError
from erva_ros.core.bag import metadata as bag_meta
from erva_ros.core.bag.qos import dump_profiles
from erva_ros.core.bag.schemas import message_definition, type_description_hash

#: libmcap's default chunk size, which rosbag2 keeps (bytes).
DEFAULT_CHUNK_SIZE = 768 * 1024
DEFAULT_FLUSH_PERIOD_S = 1.0
COMPRESSIONS = ('none', 'zstd', 'lz4')
#: MCAP metadata record with the session description (scenario, parameters, ...).
SESSION_RECORD = 'erva_session'
#: MCAP metadata record rosbag2 writes on close.
ROSBAG2_RECORD = 'rosbag2'
PROFILE = 'ros2'
MESSAGE_ENCODING = 'cdr'
# Message record overhead in a chunk: opcode, length, channel, sequence, two times.
_RECORD_OVERHEAD = 1 + 8 + 2 + 4 + 8 + 8


def stamp_ns(stamp) -> int:
    """Return a builtin_interfaces/Time as integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


class _Topic:
    __slots__ = ('name', 'type', 'offered_qos', 'type_hash', 'channel_id', 'count')

    def __init__(self, name, type_name, offered_qos, type_hash, channel_id):
        self.name = name
        self.type = type_name
        self.offered_qos = list(offered_qos)
        self.type_hash = type_hash
        self.channel_id = channel_id
        self.count = 0


class BagWriter:
    """Write a rosbag2 bag directory (see module doc); not thread-safe."""

    def __init__(self, bag_dir: str, *, chunk_size: int = DEFAULT_CHUNK_SIZE,
                 compression: str = 'none', flush_period_s: float = DEFAULT_FLUSH_PERIOD_S,
                 fsync: bool = False, session: Optional[Mapping[str, str]] = None,
                 custom_data: Optional[Mapping[str, str]] = None,
                 clock: Callable[[], float] = time.monotonic):
        from mcap.writer import CompressionType, LIBRARY_IDENTIFIER, Writer

        if compression not in COMPRESSIONS:
            raise BagError(f'compression {compression!r}: choose from {", ".join(COMPRESSIONS)}')
        if chunk_size < 1024:
            raise BagError(f'chunk_size {chunk_size} B is below 1024 B')
        self.bag_dir = os.path.abspath(bag_dir)
        self.file_name = os.path.basename(self.bag_dir.rstrip(os.sep)) + '_0.mcap'
        self.file_path = os.path.join(self.bag_dir, self.file_name)
        self.chunk_size = int(chunk_size)
        self.flush_period_s = float(flush_period_s)
        self.fsync = bool(fsync)
        self.custom_data = dict(custom_data or {})
        self.error: Optional[str] = None
        self.closed = False
        self.flushes = 0
        self._clock = clock
        self._topics: Dict[str, _Topic] = {}
        self._schemas: Dict[str, int] = {}
        self._chunk_bytes = 0
        self._last_flush = clock()
        self._start_ns: Optional[int] = None
        self._end_ns: Optional[int] = None

        if os.path.lexists(self.bag_dir):
            raise BagError(f'bag directory {bag_dir} already exists')
        try:
            os.makedirs(os.path.dirname(self.bag_dir), exist_ok=True)
            os.mkdir(self.bag_dir)
        except OSError as exc:
            if isinstance(exc, FileExistsError) and os.path.isdir(self.bag_dir):
                raise BagError(f'bag directory {bag_dir} already exists') from None
            raise BagError(f'cannot create bag directory {bag_dir}: '
                           f'{exc.strerror or exc}') from None
        try:
            self._fh = open(self.file_path, 'xb')
            kind = {'none': CompressionType.NONE, 'zstd': CompressionType.ZSTD,
                    'lz4': CompressionType.LZ4}[compression]
            # Chunks are closed here (chunk_size, flush period), never by the library.
            self._mcap = Writer(self._fh, chunk_size=2 ** 62, compression=kind)
            self._mcap.start(profile=PROFILE,
                             library=f'{LIBRARY_IDENTIFIER}; erva_ros/{__version__}')
            if session:
                self._mcap.add_metadata(SESSION_RECORD, {str(k): str(v)
                                                         for k, v in session.items()})
            self._fh.flush()
        except OSError as exc:
            self._fail(exc)

    # -- topics and messages ---------------------------------------------------------------
    def has_topic(self, name: str) -> bool:
        return name in self._topics

    def add_topic(self, name: str, type_name: str, offered_qos: Sequence[Dict] = (),
                  type_hash: Optional[str] = None) -> None:
        """Create the channel of ``name`` (and the schema of its type, once per type).

        ``offered_qos``: the publishers' profiles (:func:`erva_ros.core.bag.qos.profile_to_dict`);
        ``type_hash``: RIHS01 from the graph; by default the one the type's share .json gives.
        """
        self._check()
        if name in self._topics:
            return
        if type_hash is None:
            type_hash = type_description_hash(type_name)
        try:
            schema_id = self._schemas.get(type_name)
            if schema_id is None:
                encoding, text = message_definition(type_name)
                schema_id = self._mcap.register_schema(type_name, encoding, text.encode())
                self._schemas[type_name] = schema_id
            channel_id = self._mcap.register_channel(
                name, MESSAGE_ENCODING, schema_id,
                {'offered_qos_profiles': dump_profiles(offered_qos),
                 'topic_type_hash': type_hash})
        except OSError as exc:
            self._fail(exc)
        self._topics[name] = _Topic(name, type_name, offered_qos, type_hash, channel_id)

    def write(self, topic: str, data: bytes, log_time_ns: int,
              publish_time_ns: Optional[int] = None, sequence: int = 0) -> None:
        """Append one CDR message of a created topic (times in ns)."""
        self._check()
        entry = self._topics.get(topic)
        if entry is None:
            raise BagError(f'topic {topic} was not created in {self.file_path}')
        log_time_ns = int(log_time_ns)
        publish_time_ns = log_time_ns if publish_time_ns is None else int(publish_time_ns)
        try:
            self._mcap.add_message(entry.channel_id, log_time_ns, data, publish_time_ns,
                                   int(sequence) & 0xFFFFFFFF)
        except OSError as exc:
            self._fail(exc)
        entry.count += 1
        if self._start_ns is None or log_time_ns < self._start_ns:
            self._start_ns = log_time_ns
        if self._end_ns is None or log_time_ns > self._end_ns:
            self._end_ns = log_time_ns
        self._chunk_bytes += len(data) + _RECORD_OVERHEAD
        if self._chunk_bytes >= self.chunk_size:
            self.flush()
        else:
            self.maybe_flush()

    def maybe_flush(self) -> bool:
        """Close the chunk in progress if ``flush_period_s`` has passed; return if it did."""
        if self._chunk_bytes and self._clock() - self._last_flush >= self.flush_period_s:
            self.flush()
            return True
        return False

    def flush(self) -> None:
        """Close the chunk in progress (with its message index) and hand it to the OS."""
        self._check()
        try:
            self._mcap.flush()
            if self.fsync:
                os.fsync(self._fh.fileno())
        except OSError as exc:
            self._fail(exc)
        self._chunk_bytes = 0
        self._last_flush = self._clock()
        self.flushes += 1

    def close(self) -> Dict:
        """Finish the MCAP file (summary, indexes) and write metadata.yaml; return it."""
        if self.closed:
            return self.metadata()
        self._check()
        meta = self.metadata()
        try:
            self._mcap.add_metadata(ROSBAG2_RECORD,
                                    {'serialized_metadata': bag_meta.dump_yaml(meta, False)})
            self._mcap.finish()
            self._fh.flush()
            if self.fsync:
                os.fsync(self._fh.fileno())
            self._fh.close()
        except OSError as exc:
            self._fail(exc)
        self.closed = True
        bag_meta.write_metadata(self.bag_dir, meta)
        return meta

    def abort(self) -> None:
        """Close the file as it is, without summary or metadata.yaml (a crash, for tests)."""
        if not self.closed:
            self.closed = True
            try:
                self._fh.close()
            except OSError:
                pass

    # -- state -------------------------------------------------------------------------------
    @property
    def message_count(self) -> int:
        return sum(t.count for t in self._topics.values())

    @property
    def counts(self) -> Dict[str, int]:
        return {name: t.count for name, t in self._topics.items()}

    @property
    def bytes_written(self) -> int:
        try:
            return self._fh.tell()
        except (OSError, ValueError):
            return 0

    def topics(self) -> List[Dict]:
        """Return the ``topics_with_message_count`` entries of metadata.yaml."""
        return [bag_meta.topic_entry(t.name, t.type, t.offered_qos, t.type_hash, t.count)
                for t in self._topics.values()]

    def metadata(self) -> Dict:
        """Return the BagMetadata mapping of what has been written so far."""
        return bag_meta.bag_metadata(self.file_name, self.topics(), self._start_ns,
                                     self._end_ns, self.custom_data)

    def _check(self) -> None:
        if self.error:
            raise BagError(self.error)
        if self.closed:
            raise BagError(f'{self.file_path} is already closed')

    def _fail(self, exc: OSError):
        self.error = f'cannot write {self.file_path}: {exc.strerror or exc}'
        self.closed = True
        try:
            self._fh.close()
        except (OSError, AttributeError, ValueError):
            pass
        raise BagError(self.error) from None

    def __enter__(self) -> 'BagWriter':
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


__all__ = ['BagWriter', 'stamp_ns', 'DEFAULT_CHUNK_SIZE', 'SESSION_RECORD',
           'ROSBAG2_RECORD']
