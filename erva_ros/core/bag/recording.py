"""recorder_node's core: one bag being written, and what the recorder reports of it.

:class:`Recording` wraps the :class:`~erva_ros.core.bag.writer.BagWriter` of a session:
every message taken is counted; the first write error (directory exists, disk full) is
kept as the recording's error, reported once, and from then on messages are counted as
lost, never written half; the writer splits the bag into files as configured
(``max_bag_duration_s``, ``max_bag_size_bytes``); :meth:`close` finishes the last file
(summary, indexes, metadata.yaml).  No ROS inside.
"""

from typing import Any, Callable, Dict, Mapping, Optional

from erva_ros.core.bag import BagError
from erva_ros.core.bag.writer import BagWriter
from erva_ros.core.reports import RecorderReport


class Recording:
    """A bag being written (see the module doc); ``on_error(text)`` is told the first error."""

    def __init__(self, p: Mapping[str, Any], session: Mapping[str, str],
                 report: RecorderReport, on_error: Callable[[str], None]):
        self.report = report
        self.on_error = on_error
        self.error: Optional[str] = None
        self.writer: Optional[BagWriter] = None
        try:
            self.writer = BagWriter(p['bag_dir'], chunk_size=p['chunk_size'],
                                    compression=p['compression'],
                                    flush_period_s=p['flush_period_s'], fsync=p['fsync'],
                                    session=session, custom_data=session,
                                    max_bag_duration_s=p['max_bag_duration_s'],
                                    max_bag_size_bytes=p['max_bag_size_bytes'])
        except BagError as exc:
            self.fail(str(exc))

    @property
    def ok(self) -> bool:
        """Return True while the bag is being written."""
        return self.writer is not None and self.error is None

    def fail(self, message: str) -> None:
        """Stop writing: the first error is the recording's."""
        if self.error is None:
            self.error = self.report.error = message
            self.on_error(message)

    def add_topic(self, topic: str, type_name: str, offered, type_hash) -> None:
        """Create a topic's channel (its publishers' QoS and type hash)."""
        try:
            self.writer.add_topic(topic, type_name, offered, type_hash)
        except BagError as exc:
            self.fail(str(exc))

    def write(self, topic: str, data: bytes, log_time: int, publish_time: int, seq: int,
              add_channel: Callable[[], None]) -> None:
        """Write one message (``add_channel`` first if its topic has none yet)."""
        self.report.received += 1
        if not self.ok:
            self.report.lost += 1
            return
        try:
            if not self.writer.has_topic(topic):
                add_channel()
            self.writer.write(topic, data, log_time, publish_time, seq)
        except BagError as exc:
            self.report.lost += 1
            self.fail(str(exc))

    def flush(self) -> None:
        """Close the chunk and hand it to the OS when due (at most ``flush_period_s``)."""
        if self.ok:
            try:
                self.writer.maybe_flush()
            except BagError as exc:
                self.fail(str(exc))

    def close(self) -> Optional[Dict]:
        """Finish the file; return its metadata (None if the recording failed)."""
        if not self.ok:
            return None
        try:
            return self.writer.close()
        except BagError as exc:
            self.fail(str(exc))
            return None

    def fill(self) -> None:
        """Bring the report's figures up to date."""
        r, w = self.report, self.writer
        if w is not None:
            r.written, r.bytes, r.flushes = w.message_count, w.bytes_written, w.flushes
            r.topics = len(w.counts)
            # Per topic, so `erva run` can wait until the bag holds what was published.
            r.count = dict(w.counts)


__all__ = ['Recording']
