"""Read a bag: a rosbag2 directory (metadata.yaml + one .mcap file) or a bare .mcap file.

A properly closed file is read through its summary and indexes (messages in log-time
order).  A file whose writer died (no summary, possibly a torn last chunk) is scanned
record by record up to the first incomplete or damaged record; everything before it
is usable, and :attr:`Bag.complete` is False (``erva bag repair`` makes it whole).
Every problem surfaces as one :class:`~erva_ros.core.bag.BagError` line.
"""

from dataclasses import dataclass, field
import datetime
import os
from typing import Dict, Iterable, Iterator, List, Optional, Tuple

from erva_ros.core.bag import BagError
from erva_ros.core.bag.metadata import METADATA_FILE, read_metadata
from erva_ros.core.bag.qos import load_profiles
from erva_ros.core.bag.writer import ROSBAG2_RECORD, SESSION_RECORD

MCAP_MAGIC = b'\x89MCAP0\r\n'
#: Files up to this size are read in full by ``info`` for per-topic rates (bytes).
RATE_SCAN_LIMIT = 256 * 1024 * 1024


@dataclass
class TopicInfo:
    """One channel of the bag."""

    name: str
    type: str
    count: int = 0
    serialization_format: str = 'cdr'
    offered_qos: List[Dict] = field(default_factory=list)
    type_hash: str = ''


@dataclass
class BagMessage:
    """One recorded message: CDR bytes and its two times (ns)."""

    topic: str
    type: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    data: bytes


@dataclass
class ScanResult:
    """Everything readable from the start of an MCAP file, in file order."""

    header: object = None
    schemas: Dict[int, object] = field(default_factory=dict)
    channels: Dict[int, object] = field(default_factory=dict)
    messages: List[object] = field(default_factory=list)
    metadata: List[object] = field(default_factory=list)
    complete: bool = False          # reached the footer
    stopped_at: Optional[str] = None  # why scanning stopped early


def scan_mcap(path: str) -> ScanResult:
    """Read ``path`` record by record until its end or the first torn/damaged record."""
    from mcap.records import Channel, Footer, Header, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    out = ScanResult()
    size = os.path.getsize(path)
    with open(path, 'rb') as fh:
        reader = StreamReader(fh, validate_crcs=True, record_size_limit=max(size, 1024))
        try:
            for record in reader.records:
                if isinstance(record, Message):
                    out.messages.append(record)
                elif isinstance(record, Channel):
                    out.channels.setdefault(record.id, record)
                elif isinstance(record, Schema):
                    out.schemas.setdefault(record.id, record)
                elif isinstance(record, Metadata):
                    out.metadata.append(record)
                elif isinstance(record, Header):
                    out.header = record
                elif isinstance(record, Footer):
                    out.complete = True
        except Exception as exc:  # noqa: BLE001 -- any parse error ends the readable part
            name = type(exc).__name__
            out.stopped_at = ('the file ends inside a record' if name == 'EndOfFile'
                              else f'damaged record ({name}: {exc})'.strip())
            if out.header is None:
                raise BagError(f'{path}: not a readable MCAP file ({out.stopped_at})') from None
    return out


def resolve_bag_path(path: str) -> Tuple[Optional[str], str, Optional[Dict]]:
    """Return (bag directory or None, .mcap path, metadata.yaml mapping or None)."""
    if not os.path.exists(path):
        raise BagError(f'{path}: no such file or directory')
    if os.path.isdir(path):
        if os.path.exists(os.path.join(path, METADATA_FILE)):
            meta = read_metadata(path)
            files = meta['relative_file_paths']
            if len(files) != 1:
                raise BagError(f'{path}: split bags ({len(files)} files) are not supported')
            mcap_path = os.path.join(path, os.path.basename(files[0]))
            if not os.path.isfile(mcap_path):
                raise BagError(f'{path}: metadata.yaml names {files[0]}, which is missing')
            return path, mcap_path, meta
        found = sorted(f for f in os.listdir(path) if f.endswith('.mcap'))
        if not found:
            raise BagError(f'{path}: not a bag directory (no metadata.yaml, no .mcap file)')
        if len(found) > 1:
            raise BagError(f'{path}: no metadata.yaml and {len(found)} .mcap files')
        return path, os.path.join(path, found[0]), None
    if path.endswith(METADATA_FILE):
        return resolve_bag_path(os.path.dirname(path) or '.')
    return None, path, None


def _check_magic(path: str) -> None:
    try:
        with open(path, 'rb') as fh:
            magic = fh.read(len(MCAP_MAGIC))
    except OSError as exc:
        raise BagError(f'cannot read {path}: {exc.strerror or exc}') from None
    if magic != MCAP_MAGIC:
        raise BagError(f'{path}: not an MCAP file' + (' (empty)' if not magic else ''))


class Bag:
    """A bag opened for reading (see module doc)."""

    def __init__(self, path: str):
        self.path = path
        self.bag_dir, self.mcap_path, self.metadata_yaml = resolve_bag_path(path)
        _check_magic(self.mcap_path)
        self.size_bytes = os.path.getsize(self.mcap_path)
        self.topics: Dict[str, TopicInfo] = {}
        self.session: Dict[str, str] = {}
        self.rosbag2_record: Optional[str] = None
        self.profile = ''
        self.library = ''
        self.complete = False
        self.stopped_at: Optional[str] = None
        self.damaged: Optional[str] = None      # set when reading messages failed
        self.start_ns: Optional[int] = None
        self.end_ns: Optional[int] = None
        self.message_count = 0
        self._scan: Optional[ScanResult] = None
        self._channels: Dict[int, Tuple[str, str]] = {}
        try:
            self._open_indexed()
        except BagError:
            raise
        except Exception:  # noqa: BLE001 -- no usable summary: fall back to a scan
            self._open_scanned()

    # -- opening ---------------------------------------------------------------------------
    def _open_indexed(self) -> None:
        from mcap.reader import make_reader
        with open(self.mcap_path, 'rb') as fh:
            fh.seek(-len(MCAP_MAGIC), os.SEEK_END)
            if fh.read() != MCAP_MAGIC:  # torn: the footer cannot be trusted
                raise ValueError('no trailing magic')
            fh.seek(0)
            reader = make_reader(fh)
            header = reader.get_header()
            summary = reader.get_summary()
            if summary is None or summary.statistics is None:
                raise ValueError('no summary')
            metadata = list(reader.iter_metadata())
        self.profile, self.library = header.profile, header.library
        stats = summary.statistics
        for cid, ch in summary.channels.items():
            self._add_channel(cid, ch, summary.schemas.get(ch.schema_id),
                              stats.channel_message_counts.get(cid, 0))
        self._take_metadata(metadata)
        self.message_count = stats.message_count
        if stats.message_count:
            self.start_ns, self.end_ns = stats.message_start_time, stats.message_end_time
        self.complete = True

    def _open_scanned(self) -> None:
        scan = scan_mcap(self.mcap_path)
        self._scan = scan
        self.profile, self.library = scan.header.profile, scan.header.library
        counts: Dict[int, int] = {}
        for m in scan.messages:
            counts[m.channel_id] = counts.get(m.channel_id, 0) + 1
        for cid, ch in scan.channels.items():
            self._add_channel(cid, ch, scan.schemas.get(ch.schema_id), counts.get(cid, 0))
        self._take_metadata(scan.metadata)
        scan.messages.sort(key=lambda m: m.log_time)
        self.message_count = len(scan.messages)
        if scan.messages:
            self.start_ns, self.end_ns = scan.messages[0].log_time, scan.messages[-1].log_time
        self.complete = False
        self.stopped_at = scan.stopped_at or 'no summary section'

    def _add_channel(self, cid, ch, schema, count) -> None:
        type_name = schema.name if schema is not None else ''
        try:
            qos = load_profiles(ch.metadata.get('offered_qos_profiles', ''))
        except Exception:  # noqa: BLE001 -- bad QoS text only loses the QoS
            qos = []
        self._channels[cid] = (ch.topic, type_name)
        self.topics[ch.topic] = TopicInfo(ch.topic, type_name, int(count), ch.message_encoding,
                                          qos, ch.metadata.get('topic_type_hash', ''))

    def _take_metadata(self, records) -> None:
        for rec in records:
            if rec.name == SESSION_RECORD:
                self.session.update(rec.metadata)
            elif rec.name == ROSBAG2_RECORD:
                self.rosbag2_record = rec.metadata.get('serialized_metadata')

    # -- messages --------------------------------------------------------------------------
    def messages(self, topics: Optional[Iterable[str]] = None) -> Iterator[BagMessage]:
        """Yield the messages of ``topics`` (default: all) in log-time order."""
        wanted = None if topics is None else set(topics)
        if self._scan is not None:
            for m in self._scan.messages:
                topic, type_name = self._channels.get(m.channel_id, ('', ''))
                if topic and (wanted is None or topic in wanted):
                    yield BagMessage(topic, type_name, m.log_time, m.publish_time,
                                     m.sequence, bytes(m.data))
            return
        from mcap.reader import make_reader
        try:
            with open(self.mcap_path, 'rb') as fh:
                reader = make_reader(fh)
                for schema, channel, m in reader.iter_messages(
                        topics=None if wanted is None else sorted(wanted), log_time_order=True):
                    yield BagMessage(channel.topic, schema.name if schema else '', m.log_time,
                                     m.publish_time, m.sequence, bytes(m.data))
        except BagError:
            raise
        except Exception as exc:  # noqa: BLE001 -- a damaged chunk despite a summary
            raise BagError(f'{self.mcap_path}: damaged data ({type(exc).__name__}: {exc}); '
                           'try "erva bag repair"') from None

    # -- summary ---------------------------------------------------------------------------
    @property
    def duration_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) * 1e-9

    def warnings(self) -> List[str]:
        """Return what a user should know about this bag (one line each)."""
        out = []
        if not self.complete:
            out.append(f'the file was not closed properly ({self.stopped_at}); '
                       f'{self.message_count} messages are readable; run "erva bag repair"')
        if self.bag_dir is not None and self.metadata_yaml is None:
            out.append('metadata.yaml is missing (ros2 bag play needs it): '
                       'run "erva bag repair"')
        if self.damaged:
            out.append(self.damaged)
        if self.profile != 'ros2':
            out.append(f'MCAP profile is {self.profile!r}, not ros2')
        bad = sorted(t.name for t in self.topics.values() if t.serialization_format != 'cdr')
        if bad:
            out.append(f'topics not in cdr encoding: {", ".join(bad)}')
        if self.metadata_yaml is not None and self.complete:
            n = self.metadata_yaml.get('message_count')
            if n != self.message_count:
                out.append(f'metadata.yaml counts {n} messages, the MCAP file '
                           f'{self.message_count}')
        return out

    def _topic_spans(self) -> Dict[str, Tuple[int, int]]:
        """Return each topic's first and last log time (ns); reads every message."""
        spans: Dict[str, Tuple[int, int]] = {}
        try:
            for m in self.messages():
                first, last = spans.get(m.topic, (m.log_time_ns, m.log_time_ns))
                spans[m.topic] = (min(first, m.log_time_ns), max(last, m.log_time_ns))
        except BagError as exc:
            self.damaged = str(exc)
            return {}
        return spans

    def info(self) -> Dict:
        """Return what ``erva bag info`` shows, as plain data."""
        from erva_ros.core.bag.session_check import session_warnings

        def iso(ns):
            if ns is None:
                return None
            t = datetime.datetime.fromtimestamp(ns * 1e-9, tz=datetime.timezone.utc)
            return t.isoformat(timespec='milliseconds').replace('+00:00', 'Z')

        dur = self.duration_s
        span = self._topic_spans() if self.size_bytes <= RATE_SCAN_LIMIT else {}
        topics = []
        for t in sorted(self.topics.values(), key=lambda t: t.name):
            first, last = span.get(t.name, (0, 0))
            rate = (t.count - 1) / ((last - first) * 1e-9) if last > first else None
            topics.append({'name': t.name, 'type': t.type, 'count': t.count,
                           'rate_hz': None if rate is None else round(rate, 3),
                           'serialization_format': t.serialization_format,
                           'type_hash': t.type_hash})
        meta = self.metadata_yaml or {}
        return {
            'path': self.path, 'file': self.mcap_path, 'size_bytes': self.size_bytes,
            'storage': 'mcap', 'profile': self.profile, 'library': self.library,
            'ros_distro': meta.get('ros_distro'),
            'bag_format_version': meta.get('version'),
            'complete': self.complete, 'metadata_yaml': self.metadata_yaml is not None,
            'start': iso(self.start_ns), 'end': iso(self.end_ns),
            'start_ns': self.start_ns, 'end_ns': self.end_ns,
            'duration_s': round(dur, 9), 'message_count': self.message_count,
            'topics': topics, 'session': dict(self.session),
            'warnings': self.warnings() + session_warnings(self),
        }


def open_bag(path: str) -> Bag:
    """Open ``path`` as a bag; any failure is a one-line :class:`BagError`."""
    try:
        return Bag(path)
    except BagError:
        raise
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise BagError(f'{path}: cannot read bag ({type(exc).__name__}: {exc})') from None


__all__ = ['Bag', 'BagMessage', 'TopicInfo', 'open_bag', 'scan_mcap', 'resolve_bag_path']
