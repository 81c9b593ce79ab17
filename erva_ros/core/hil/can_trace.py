"""The bridge's CAN trace: every raw frame on its bus, both directions, in a BLF or ASC file.

Written with python-can's writers (``can.Logger`` picks :class:`can.BLFWriter` or
:class:`can.ASCWriter` by the suffix), which Vector's tools and python-can's readers read.
Timestamps are epoch seconds, the clock of the bag's receive stamps: a received frame
keeps its kernel receive time (the one the bridge stamps its ECU cycles with, so a
cycle's first frame has exactly the stamp of its ``ecu/measurements``), a sent frame gets
the time it went out.  Frames are marked Rx / Tx.  Every frame is logged, also one the
E2E check then refuses.

The loop's threads only queue the frame; a writer thread of its own packs, compresses
and writes (a BLF container is zlib-compressed every 128 kB).  :meth:`CanTrace.close`
writes what is queued and finishes the file (node shutdown or cleanup).  ASC keeps the
measurement's start to the millisecond only: read back, its absolute times may be up to
1 ms early; BLF keeps them to the nanosecond.
"""

import os
import queue
import threading
import time
from typing import Optional

import can

from erva_ros.core.model.params import ParamError

#: File suffixes of the formats written.
SUFFIXES = ('.blf', '.asc')


def check_path(path: str, key: str = 'can_log') -> None:
    """Raise ParamError (one line) unless ``path`` can become a trace file."""
    suffix = os.path.splitext(path)[1].lower()
    if suffix not in SUFFIXES:
        raise ParamError(f'{key} {path!r}: the file must end in .blf or .asc')
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise ParamError(f'{key} {path!r}: directory {folder} does not exist')
    if not os.access(folder, os.W_OK):
        raise ParamError(f'{key} {path!r}: directory {folder} is not writable')
    if os.path.isdir(path):
        raise ParamError(f'{key} {path!r}: is a directory')


class CanTrace:
    """A trace file being written (see module doc)."""

    def __init__(self, path: str):
        check_path(path)
        try:
            self._writer = can.Logger(path)
        except OSError as exc:
            raise ParamError(f'can_log {path!r}: {exc.strerror or exc}') from None
        self.path = path
        self.frames = 0
        self._queue: 'queue.SimpleQueue[Optional[can.Message]]' = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._write, name='can_trace', daemon=True)
        self._thread.start()

    def received(self, msg: can.Message) -> None:
        """Log a frame read from the bus (its own receive time)."""
        self._put(msg, msg.timestamp or time.time(), True)

    def sent(self, msg: can.Message, t: Optional[float] = None) -> None:
        """Log a frame sent on the bus at epoch time ``t`` (default now)."""
        self._put(msg, time.time() if t is None else t, False)

    def _put(self, msg: can.Message, t: float, rx: bool) -> None:
        self.frames += 1
        self._queue.put(can.Message(timestamp=t, arbitration_id=msg.arbitration_id,
                                    is_extended_id=msg.is_extended_id, dlc=msg.dlc,
                                    data=bytes(msg.data), is_rx=rx, channel=0))

    def _write(self) -> None:
        while True:
            msg = self._queue.get()
            if msg is None:
                return
            self._writer.on_message_received(msg)

    def close(self) -> None:
        """Write what is queued and finish the file."""
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
            self._writer.stop()


__all__ = ['CanTrace', 'SUFFIXES', 'check_path']
