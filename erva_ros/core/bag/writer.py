"""rosbag2-compatible MCAP writer: a bag directory of ``<name>_<i>.mcap`` files and metadata.yaml.

The files follow the rosbag2 MCAP storage plugin (``rosbag2_storage_mcap``, Jazzy):

* header profile ``ros2``; chunked, uncompressed by default (rosbag2's default; zstd/lz4
  chunk compression optional), message indexes, chunk indexes, statistics and summary
  offsets; the summary repeats schemas and channels;
* one schema per message type: name ``pkg/msg/Type``, encoding ``ros2msg``, data the
  definition with all dependent definitions (:mod:`erva_ros.core.bag.schemas`);
* one channel per topic: message encoding ``cdr``, metadata ``offered_qos_profiles``
  (YAML string, :mod:`erva_ros.core.bag.qos`) and ``topic_type_hash`` (RIHS01);
* messages: log time = receive time, publish time = the publisher's send time (DDS
  source timestamp), both in ns since the epoch (or sim time), as rosbag2 records them;
* on closing a file a ``rosbag2`` metadata record (``serialized_metadata``: the bag so
  far), and metadata.yaml.

Splitting, as ``ros2 bag record --max-bag-duration/--max-bag-size`` (rosbag2's
SequentialWriter): before a message is written, if the open file already holds
``max_bag_size_bytes`` or the message's log time is more than ``max_bag_duration_s``
after the file's first message, the file is finished and ``<bag>_<i+1>.mcap`` started
with the same channels and session record; metadata.yaml is rewritten then, listing the
finished files.  Each file's summary (one chunk index per chunk, ~1 KB each in the
``mcap`` writer) is held in memory only until that file is finished: splitting bounds
the writer's memory in a long session.

Crash safety: the chunk in progress is closed and handed to the OS whenever it
reaches ``chunk_size`` bytes or ``flush_period_s`` has passed, so a killed recorder
loses at most that much; the session's own metadata record (``erva_session``) is
written first of all in every file.  ``erva bag repair`` finishes the last file and
rebuilds metadata.yaml.
"""

from array import array
import os
import time
from typing import Callable, Dict, List, Mapping, Optional, Sequence

from mcap.writer import CompressionType, LIBRARY_IDENTIFIER, Writer

from erva_ros import __version__
from erva_ros.core.bag import BagError
from erva_ros.core.bag import metadata as bag_meta
from erva_ros.core.bag.qos import dump_profiles
from erva_ros.core.bag.schemas import message_definition, type_description_hash

#: libmcap's default chunk size, which rosbag2 keeps (bytes).
DEFAULT_CHUNK_SIZE = 768 * 1024
DEFAULT_FLUSH_PERIOD_S = 1.0
#: Smallest max_bag_size_bytes (rosbag2_storage_mcap's minimum split file size).
MIN_SPLIT_SIZE = 1024
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
                 max_bag_duration_s: float = 0.0, max_bag_size_bytes: int = 0,
                 clock: Callable[[], float] = time.monotonic):
        if compression not in COMPRESSIONS:
            raise BagError(f'compression {compression!r}: choose from {", ".join(COMPRESSIONS)}')
        if chunk_size < 1024:
            raise BagError(f'chunk_size {chunk_size} B is below 1024 B')
        if not max_bag_duration_s >= 0:
            raise BagError(f'max_bag_duration_s {max_bag_duration_s} is negative (0: no limit)')
        if max_bag_size_bytes and not max_bag_size_bytes >= MIN_SPLIT_SIZE:
            raise BagError(f'max_bag_size_bytes {max_bag_size_bytes} B is below '
                           f'{MIN_SPLIT_SIZE} B (0: no limit)')
        self.bag_dir = os.path.abspath(bag_dir)
        self.bag_name = os.path.basename(self.bag_dir.rstrip(os.sep))
        self.chunk_size = int(chunk_size)
        self.compression = compression
        self.flush_period_s = float(flush_period_s)
        self.max_bag_duration_ns = int(round(float(max_bag_duration_s) * 1e9))
        self.max_bag_size_bytes = int(max_bag_size_bytes)
        self.fsync = bool(fsync)
        self.session = {str(k): str(v) for k, v in (session or {}).items()}
        self.custom_data = dict(custom_data or {})
        self.error: Optional[str] = None
        self.closed = False
        self.flushes = 0
        self._clock = clock
        self._topics: Dict[str, _Topic] = {}
        self._last_flush = clock()
        self._start_ns: Optional[int] = None
        self._end_ns: Optional[int] = None
        # Per finished file: first log time, last log time, messages (3 int64 each: a
        # week of 5-minute files is 48 KB); and their bytes.
        self._finished = array('q')
        self._finished_bytes = 0
        self._fh = None
        self._closed_meta: Optional[Dict] = None

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
        self._open_file()

    # -- files -------------------------------------------------------------------------------
    def _open_file(self) -> None:
        """Start file ``<bag>_<i>.mcap``: header, session record, every known channel."""
        self.file_name = f'{self.bag_name}_{len(self._finished) // 3}.mcap'
        self.file_path = os.path.join(self.bag_dir, self.file_name)
        self._file_start_ns: Optional[int] = None
        self._file_end_ns: Optional[int] = None
        self._file_count = 0
        self._file_bytes = 0       # what the file held at its last flush
        self._chunk_bytes = 0
        self._schemas: Dict[str, int] = {}
        try:
            self._fh = open(self.file_path, 'xb')
            kind = {'none': CompressionType.NONE, 'zstd': CompressionType.ZSTD,
                    'lz4': CompressionType.LZ4}[self.compression]
            # Chunks are closed here (chunk_size, flush period), never by the library.
            self._mcap = Writer(self._fh, chunk_size=2 ** 62, compression=kind)
            self._mcap.start(profile=PROFILE,
                             library=f'{LIBRARY_IDENTIFIER}; erva_ros/{__version__}')
            if self.session:
                self._mcap.add_metadata(SESSION_RECORD, self.session)
            for topic in self._topics.values():
                self._register(topic)
            self._fh.flush()
            self._file_bytes = self._fh.tell()
        except OSError as exc:
            self._fail(exc)

    def _register(self, topic: _Topic) -> None:
        """Create ``topic``'s channel (and its type's schema, once per file) in this file."""
        schema_id = self._schemas.get(topic.type)
        if schema_id is None:
            encoding, text = message_definition(topic.type)
            schema_id = self._mcap.register_schema(topic.type, encoding, text.encode())
            self._schemas[topic.type] = schema_id
        topic.channel_id = self._mcap.register_channel(
            topic.name, MESSAGE_ENCODING, schema_id,
            {'offered_qos_profiles': dump_profiles(topic.offered_qos),
             'topic_type_hash': topic.type_hash})

    def _finish_file(self) -> Dict:
        """Finish the current file (its rosbag2 record, summary, indexes); return the metadata.

        The metadata describes the bag up to and including this file.  The file's writer
        (its chunk indexes) is let go.
        """
        self._check()
        meta = self.metadata()
        try:
            self._mcap.add_metadata(ROSBAG2_RECORD,
                                    {'serialized_metadata': bag_meta.dump_yaml(meta, False)})
            self._mcap.finish()
            self._fh.flush()
            if self.fsync:
                os.fsync(self._fh.fileno())
            size = self._fh.tell()
            self._fh.close()
        except OSError as exc:
            self._fail(exc)
        self._mcap = None
        self._finished.extend((self._file_start_ns or 0, self._file_end_ns or 0,
                               self._file_count))
        self._finished_bytes += size
        return meta

    def split(self) -> None:
        """Finish the current file, write metadata.yaml of the finished files, start the next.

        As ``ros2 bag record --max-bag-duration/--max-bag-size``: the next file is
        ``<bag>_<i+1>.mcap`` with the same channels and session record.
        """
        meta = self._finish_file()
        self.closed = True      # between two files: nothing open
        try:
            bag_meta.write_metadata(self.bag_dir, meta)
        except BagError as exc:
            self.error = str(exc)
            raise
        self.closed = False
        self._open_file()

    def _split_due(self, log_time_ns: int) -> bool:
        """Return True if the next message, at ``log_time_ns``, belongs in a new file.

        rosbag2's rule (SequentialWriter::should_split_bagfile): the file already holds
        max_bag_size bytes (here: with its open chunk), or the message is more than
        max_bag_duration after the file's first one (log times).
        """
        if not self._file_count:
            return False
        if (self.max_bag_size_bytes
                and self._file_bytes + self._chunk_bytes >= self.max_bag_size_bytes):
            return True
        return bool(self.max_bag_duration_ns
                    and log_time_ns - self._file_start_ns > self.max_bag_duration_ns)

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
        topic = _Topic(name, type_name, offered_qos, type_hash, 0)
        try:
            self._register(topic)
        except OSError as exc:
            self._fail(exc)
        self._topics[name] = topic

    def write(self, topic: str, data: bytes, log_time_ns: int,
              publish_time_ns: Optional[int] = None, sequence: int = 0) -> None:
        """Append one CDR message of a created topic (times in ns); split first when due."""
        self._check()
        entry = self._topics.get(topic)
        if entry is None:
            raise BagError(f'topic {topic} was not created in {self.file_path}')
        log_time_ns = int(log_time_ns)
        publish_time_ns = log_time_ns if publish_time_ns is None else int(publish_time_ns)
        if self._split_due(log_time_ns):
            self.split()
        try:
            self._mcap.add_message(entry.channel_id, log_time_ns, data, publish_time_ns,
                                   int(sequence) & 0xFFFFFFFF)
        except OSError as exc:
            self._fail(exc)
        entry.count += 1
        self._file_count += 1
        if self._file_start_ns is None or log_time_ns < self._file_start_ns:
            self._file_start_ns = log_time_ns
        if self._file_end_ns is None or log_time_ns > self._file_end_ns:
            self._file_end_ns = log_time_ns
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
            self._file_bytes = self._fh.tell()
        except OSError as exc:
            self._fail(exc)
        self._chunk_bytes = 0
        self._last_flush = self._clock()
        self.flushes += 1

    def close(self) -> Dict:
        """Finish the last file (summary, indexes) and write metadata.yaml; return it."""
        if self.closed:
            return self._closed_meta or self.metadata()
        meta = self._finish_file()
        self.closed = True
        self._fh = None
        bag_meta.write_metadata(self.bag_dir, meta)
        self._closed_meta = meta
        return meta

    def abort(self) -> None:
        """Close the file as it is, without summary or metadata.yaml (a crash, for tests)."""
        if not self.closed:
            self.closed = True
            try:
                self._fh.close()
            except OSError:
                pass
            self._mcap = None

    # -- state -------------------------------------------------------------------------------
    @property
    def message_count(self) -> int:
        return sum(t.count for t in self._topics.values())

    @property
    def counts(self) -> Dict[str, int]:
        return {name: t.count for name, t in self._topics.items()}

    @property
    def file_count(self) -> int:
        """Return the number of files started so far (finished ones and the open one)."""
        return len(self._finished) // 3 + (0 if self.closed else 1)

    @property
    def bytes_written(self) -> int:
        """Return the bytes of all files so far (the open one's up to its last flush)."""
        return self._finished_bytes + (0 if self.closed else self._file_bytes)

    def topics(self) -> List[Dict]:
        """Return the ``topics_with_message_count`` entries of metadata.yaml."""
        return [bag_meta.topic_entry(t.name, t.type, t.offered_qos, t.type_hash, t.count)
                for t in self._topics.values()]

    def files(self) -> List[Dict]:
        """Return the ``files`` entries of metadata.yaml: the finished files and the open one."""
        done = self._finished
        out = [bag_meta.file_entry(f'{self.bag_name}_{i // 3}.mcap', done[i], done[i + 1],
                                   done[i + 2]) for i in range(0, len(done), 3)]
        if not self.closed:
            out.append(bag_meta.file_entry(self.file_name, self._file_start_ns,
                                           self._file_end_ns, self._file_count))
        return out

    def metadata(self) -> Dict:
        """Return the BagMetadata mapping of what has been written so far."""
        return bag_meta.bag_metadata(self.files(), self.topics(), self.custom_data)

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
