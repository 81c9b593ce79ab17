"""Read a bag: a rosbag2 directory (metadata.yaml + its .mcap files) or a bare .mcap file.

A bag split into ``<bag>_0.mcap``, ``<bag>_1.mcap``, ... (``max_bag_duration_s``,
``max_bag_size_bytes``) is read as one: its topics, counts and times over all files,
its messages file after file in log-time order.  A properly closed file is read
through its summary and indexes.  A file whose writer died (no summary, possibly a
torn last chunk) is scanned record by record up to the first incomplete or damaged
record; everything before it is usable, and :attr:`Bag.complete` is False (``erva bag
repair`` makes it whole).
Every problem surfaces as one :class:`~erva_ros.core.bag.BagError` line.
"""

from dataclasses import dataclass, field
import datetime
import heapq
import os
import re
from typing import Callable, Dict, Iterable, Iterator, List, Optional, Tuple

from mcap.reader import make_reader

from mcap.records import Channel, Footer, Header, Message, Metadata, Schema

from mcap.stream_reader import StreamReader

from erva_ros.core.bag import BagError
from erva_ros.core.bag.metadata import METADATA_FILE, read_metadata
from erva_ros.core.bag.qos import load_profiles
from erva_ros.core.bag.session_check import loop_offset_s, loop_start_ns, session_warnings
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


_NUMBERED = re.compile(r'(.+)_(\d+)\.mcap')


def _numbered(names: Iterable[str]) -> List[Tuple[str, int, str]]:
    """Return the ``<prefix>_<i>.mcap`` names of ``names`` as (prefix, i, name), in order."""
    out = []
    for name in names:
        m = _NUMBERED.fullmatch(name)
        if m:
            out.append((m.group(1), int(m.group(2)), name))
    return sorted(out)


def dir_files(path: str) -> List[str]:
    """Return the .mcap files of bag directory ``path`` without metadata.yaml, in order.

    Its one .mcap file, or its ``<bag>_<i>.mcap`` files by number; else a BagError.
    """
    names = [f for f in os.listdir(path) if f.endswith('.mcap')]
    if not names:
        raise BagError(f'{path}: not a bag directory (no metadata.yaml, no .mcap file)')
    numbered = _numbered(names)
    if len(names) == 1:
        return [os.path.join(path, names[0])]
    if len(numbered) != len(names) or len({p for p, _, _ in numbered}) != 1:
        raise BagError(f'{path}: no metadata.yaml and {len(names)} .mcap files that are not '
                       'the <bag>_<i>.mcap files of one bag')
    return [os.path.join(path, n) for _, _, n in numbered]


def resolve_bag_path(path: str) -> Tuple[Optional[str], List[str], Optional[Dict]]:
    """Return (bag directory or None, its .mcap paths in order, metadata.yaml or None).

    A bag directory's files are those metadata.yaml lists, then any later file of the
    same numbering it does not list yet (the one being written when a split bag's
    recorder died); without metadata.yaml, its one .mcap file or its ``<bag>_<i>.mcap``
    files by number.
    """
    if not os.path.exists(path):
        raise BagError(f'{path}: no such file or directory')
    if os.path.isdir(path):
        names = [f for f in os.listdir(path) if f.endswith('.mcap')]
        if os.path.exists(os.path.join(path, METADATA_FILE)):
            meta = read_metadata(path)
            files = [os.path.basename(f) for f in meta['relative_file_paths']]
            missing = [f for f in files if not os.path.isfile(os.path.join(path, f))]
            if missing:
                raise BagError(f'{path}: metadata.yaml names {", ".join(missing)}, which '
                               f'{"is" if len(missing) == 1 else "are"} missing')
            last = _numbered(files[-1:])
            if last:
                prefix, index, _ = last[0]
                files += [name for p, i, name in _numbered(names) if p == prefix and i > index]
            return path, [os.path.join(path, f) for f in files], meta
        return path, dir_files(path), None
    if path.endswith(METADATA_FILE):
        return resolve_bag_path(os.path.dirname(path) or '.')
    return None, [path], None


def _check_magic(path: str) -> None:
    try:
        with open(path, 'rb') as fh:
            magic = fh.read(len(MCAP_MAGIC))
    except OSError as exc:
        raise BagError(f'cannot read {path}: {exc.strerror or exc}') from None
    if magic != MCAP_MAGIC:
        raise BagError(f'{path}: not an MCAP file' + (' (empty)' if not magic else ''))


@dataclass
class BagFile:
    """One MCAP file of a bag, read through its summary or (not closed properly) scanned."""

    path: str
    size_bytes: int = 0
    listed: bool = True                 # in metadata.yaml (or there is none)
    complete: bool = False
    stopped_at: Optional[str] = None
    message_count: int = 0
    start_ns: Optional[int] = None
    end_ns: Optional[int] = None
    header: object = None
    channels: Dict[int, Tuple[object, object, int]] = field(default_factory=dict, repr=False)
    metadata: List[object] = field(default_factory=list, repr=False)
    scan: Optional[ScanResult] = field(default=None, repr=False)

    def open(self) -> 'BagFile':
        _check_magic(self.path)
        self.size_bytes = os.path.getsize(self.path)
        try:
            self._open_indexed()
        except BagError:
            raise
        except Exception:  # noqa: BLE001 -- no usable summary: fall back to a scan
            self._open_scanned()
        return self

    def _open_indexed(self) -> None:
        with open(self.path, 'rb') as fh:
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
        stats = summary.statistics
        self.header, self.metadata = header, metadata
        self.channels = {cid: (ch, summary.schemas.get(ch.schema_id),
                               stats.channel_message_counts.get(cid, 0))
                         for cid, ch in summary.channels.items()}
        self.message_count = stats.message_count
        if stats.message_count:
            self.start_ns, self.end_ns = stats.message_start_time, stats.message_end_time
        self.complete = True

    def _open_scanned(self) -> None:
        scan = scan_mcap(self.path)
        self.scan = scan
        counts: Dict[int, int] = {}
        for m in scan.messages:
            counts[m.channel_id] = counts.get(m.channel_id, 0) + 1
        self.header, self.metadata = scan.header, scan.metadata
        self.channels = {cid: (ch, scan.schemas.get(ch.schema_id), counts.get(cid, 0))
                         for cid, ch in scan.channels.items()}
        scan.messages.sort(key=lambda m: m.log_time)
        self.message_count = len(scan.messages)
        if scan.messages:
            self.start_ns, self.end_ns = scan.messages[0].log_time, scan.messages[-1].log_time
        self.complete = False
        self.stopped_at = scan.stopped_at or 'no summary section'

    def messages(self, wanted: Optional[set]) -> Iterator[BagMessage]:
        """Yield this file's messages of ``wanted`` topics (None: all) in log-time order."""
        if self.scan is not None:
            for m in self.scan.messages:
                ch, schema, _ = self.channels.get(m.channel_id, (None, None, 0))
                if ch is not None and (wanted is None or ch.topic in wanted):
                    yield BagMessage(ch.topic, schema.name if schema else '', m.log_time,
                                     m.publish_time, m.sequence, bytes(m.data))
            return
        try:
            with open(self.path, 'rb') as fh:
                reader = make_reader(fh)
                for schema, channel, m in reader.iter_messages(
                        topics=None if wanted is None else sorted(wanted), log_time_order=True):
                    yield BagMessage(channel.topic, schema.name if schema else '', m.log_time,
                                     m.publish_time, m.sequence, bytes(m.data))
        except BagError:
            raise
        except Exception as exc:  # noqa: BLE001 -- a damaged chunk despite a summary
            raise BagError(f'{self.path}: damaged data ({type(exc).__name__}: {exc}); '
                           'try "erva bag repair"') from None

    @property
    def duration_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) * 1e-9


def topics_of(files: Iterable[BagFile]) -> Dict[str, TopicInfo]:
    """Return the topics of ``files`` by name, in first use, their counts summed."""
    topics: Dict[str, TopicInfo] = {}
    for f in files:
        for ch, schema, count in f.channels.values():
            known = topics.get(ch.topic)
            if known is not None:
                known.count += int(count)
                continue
            try:
                qos = load_profiles(ch.metadata.get('offered_qos_profiles', ''))
            except Exception:  # noqa: BLE001 -- bad QoS text only loses the QoS
                qos = []
            topics[ch.topic] = TopicInfo(ch.topic, schema.name if schema is not None else '',
                                         int(count), ch.message_encoding, qos,
                                         ch.metadata.get('topic_type_hash', ''))
    return topics


class Bag:
    """A bag opened for reading: all its files, in order, as one (see module doc)."""

    def __init__(self, path: str):
        self.path = path
        self.bag_dir, self.mcap_paths, self.metadata_yaml = resolve_bag_path(path)
        listed = None
        if self.metadata_yaml is not None:
            listed = {os.path.basename(f) for f in self.metadata_yaml['relative_file_paths']}
        self.files: List[BagFile] = [
            BagFile(p, listed=listed is None or os.path.basename(p) in listed).open()
            for p in self.mcap_paths]
        self.size_bytes = sum(f.size_bytes for f in self.files)
        self.session: Dict[str, str] = {}
        self.rosbag2_record: Optional[str] = None
        first = self.files[0].header
        self.profile, self.library = first.profile, first.library
        self.complete = all(f.complete for f in self.files)
        self.damaged: Optional[str] = None      # set when reading messages failed
        counted = [f for f in self.files if f.message_count]
        self.start_ns = min((f.start_ns for f in counted), default=None)
        self.end_ns = max((f.end_ns for f in counted), default=None)
        self.message_count = sum(f.message_count for f in self.files)
        self.topics = topics_of(self.files)
        for f in self.files:
            self._take_metadata(f.metadata)

    @property
    def stopped_at(self) -> Optional[str]:
        """Return why the first file not closed properly could be read only so far."""
        for f in self.files:
            if not f.complete:
                return f.stopped_at
        return None

    def _take_metadata(self, records) -> None:
        for rec in records:
            if rec.name == SESSION_RECORD:
                self.session.update(rec.metadata)
            elif rec.name == ROSBAG2_RECORD:
                self.rosbag2_record = rec.metadata.get('serialized_metadata')

    # -- messages --------------------------------------------------------------------------
    def messages(self, topics: Optional[Iterable[str]] = None) -> Iterator[BagMessage]:
        """Yield the messages of ``topics`` (default: all) in log-time order, file after file.

        Files whose time spans overlap (messages received out of order around a split)
        are merged; the others are read one at a time.
        """
        wanted = None if topics is None else set(topics)
        for group in self._overlapping():
            if len(group) == 1:
                yield from group[0].messages(wanted)
            else:
                yield from heapq.merge(*(f.messages(wanted) for f in group),
                                       key=lambda m: m.log_time_ns)

    def _overlapping(self) -> List[List[BagFile]]:
        """Return the files with messages in runs whose time spans overlap (merged)."""
        groups: List[List[BagFile]] = []
        end = None
        for f in self.files:
            if not f.message_count:
                continue
            if groups and f.start_ns <= end:
                groups[-1].append(f)
            else:
                groups.append([f])
            end = f.end_ns if end is None else max(end, f.end_ns)
        return groups

    # -- summary ---------------------------------------------------------------------------
    @property
    def duration_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) * 1e-9

    def warnings(self) -> List[str]:
        """Return what a user should know about this bag (one line each)."""
        out = []
        broken = [f for f in self.files if not f.complete]
        if broken:
            which = ('the file' if len(self.files) == 1 else
                     ', '.join(os.path.basename(f.path) for f in broken))
            out.append(f'{which} {"was" if len(broken) == 1 else "were"} not closed properly '
                       f'({self.stopped_at}); {self.message_count} messages are readable; run '
                       '"erva bag repair"')
        unlisted = [os.path.basename(f.path) for f in self.files if not f.listed]
        if unlisted:
            out.append(f'metadata.yaml does not list {", ".join(unlisted)} (the recorder '
                       'stopped while writing it): run "erva bag repair"')
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
        listed = [f for f in self.files if f.listed]
        if self.metadata_yaml is not None and all(f.complete for f in listed):
            n = self.metadata_yaml.get('message_count')
            held = sum(f.message_count for f in listed)
            if n != held:
                out.append(f'metadata.yaml counts {n} messages, the MCAP '
                           f'{"file" if len(listed) == 1 else "files it lists"} {held}')
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
            'path': self.path, 'size_bytes': self.size_bytes,
            'files': [{'path': f.path, 'size_bytes': f.size_bytes, 'complete': f.complete,
                       'message_count': f.message_count, 'start_ns': f.start_ns,
                       'end_ns': f.end_ns, 'duration_s': round(f.duration_s, 9)}
                      for f in self.files],
            'storage': 'mcap', 'profile': self.profile, 'library': self.library,
            'ros_distro': meta.get('ros_distro'),
            'bag_format_version': meta.get('version'),
            'complete': self.complete, 'metadata_yaml': self.metadata_yaml is not None,
            'start': iso(self.start_ns), 'end': iso(self.end_ns),
            'start_ns': self.start_ns, 'end_ns': self.end_ns,
            'duration_s': round(dur, 9), 'message_count': self.message_count,
            'topics': topics, 'session': dict(self.session),
            'loop_start_ns': loop_start_ns(self), 'loop_offset_s': loop_offset_s(self),
            'warnings': self.warnings() + session_warnings(self),
        }


def open_bag(path: str, warn: Optional[Callable[[str], None]] = None) -> Bag:
    """Open ``path`` as a bag; any failure is a one-line :class:`BagError`.

    ``warn(line)`` is called with each of :meth:`Bag.warnings` (a file not closed properly,
    unlisted files, a missing metadata.yaml, ...): every command that reads a bag passes
    one, so a truncated bag is never read in silence.
    """
    try:
        bag = Bag(path)
    except BagError:
        raise
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise BagError(f'{path}: cannot read bag ({type(exc).__name__}: {exc})') from None
    if warn is not None:
        for line in bag.warnings():
            warn(line)
    return bag


__all__ = ['Bag', 'BagFile', 'BagMessage', 'TopicInfo', 'open_bag', 'scan_mcap',
           'resolve_bag_path', 'dir_files', 'topics_of']
