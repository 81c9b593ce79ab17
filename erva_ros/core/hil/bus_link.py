"""The bridge's CAN bus link (no ROS): open, send, loss and retry, counted, never raising.

:class:`BusLink` owns the python-can bus of ecu_bridge_node.  An error of ``send`` or
``recv`` (interface down, socket closed) closes the bus (:meth:`BusLink.lost`), is
counted and kept as :attr:`BusLink.error`; :meth:`BusLink.retry` re-opens it through
the factory, at most once every ``retry_s``, until it works.  A full transmit queue
(ENOBUFS / EAGAIN: no ECU acknowledging, a busy bus) only drops that frame
(``send_errors``): the bus is still there.  Thread-safe: a sending and a receiving
thread may find the loss at the same time; it is handled once.
"""

import errno
import math
import threading
from typing import Callable, Dict, Optional

import can

#: Send errors that mean "queue full", not "interface gone" (SocketCAN gives ENOBUFS when
#: no node acknowledges; python-can's virtual bus when a receiver's queue stays full).
TRANSIENT_ERRNOS = frozenset({errno.ENOBUFS, errno.EAGAIN})
_TRANSIENT_TEXT = ('buffer full', 'one or more recipients')
#: python-can's errors of a bus that is gone or cannot take a frame.
BUS_ERRORS = (can.CanError, OSError, ValueError)
COUNTER_NAMES = ('frames_not_sent', 'send_errors', 'bus_losses', 'bus_open_attempts',
                 'bus_open_failures', 'reconnects')


def is_transient(exc: BaseException) -> bool:
    """Return True if a send error leaves the bus usable (the frame alone is lost)."""
    code = getattr(exc, 'error_code', None) or getattr(exc, 'errno', None)
    return code in TRANSIENT_ERRNOS or any(t in str(exc).lower() for t in _TRANSIENT_TEXT)


class BusLink:
    """A CAN bus that is re-opened after a loss (see module doc)."""

    def __init__(self, factory: Callable[[], can.BusABC], retry_s: float = 0.5,
                 send_timeout_s: float = 0.005):
        self._factory = factory
        self.retry_s = float(retry_s)
        self.send_timeout_s = float(send_timeout_s)
        self._lock = threading.Lock()           # the bus object
        self._bus: Optional[can.BusABC] = None
        self._ever_open = False
        self._last_attempt = -math.inf
        self.error = ''
        self.counts: Dict[str, int] = dict.fromkeys(COUNTER_NAMES, 0)

    @property
    def up(self) -> bool:
        return self._bus is not None

    @property
    def bus(self) -> Optional[can.BusABC]:
        """Return the CAN bus in use (None while it is lost)."""
        return self._bus

    def open(self, now: float) -> bool:
        """Try to open the bus now (``now`` on the caller's clock); return True if it is up."""
        if self._bus is not None:
            return True
        self.counts['bus_open_attempts'] += 1
        self._last_attempt = now
        try:
            bus = self._factory()
        except Exception as exc:  # any open failure is reported and retried, never raised
            self.counts['bus_open_failures'] += 1
            self.error = f'cannot open bus: {exc}'
            return False
        with self._lock:
            self._bus = bus
            if self._ever_open:
                self.counts['reconnects'] += 1
            self._ever_open = True
            self.error = ''
        return True

    def retry(self, now: float) -> None:
        """Re-open a lost bus, at most every ``retry_s``.

        An interface that opens but fails on send (SocketCAN on a link that is down) must
        not be hammered every watchdog tick.
        """
        if self._bus is None and now - self._last_attempt >= self.retry_s:
            self.open(now)

    def lost(self, bus: can.BusABC, exc: BaseException) -> None:
        """Drop ``bus`` after an error of its own (once, whichever thread saw it first)."""
        with self._lock:
            if self._bus is not bus:
                return                  # the other thread already handled it
            self._bus = None
            self.counts['bus_losses'] += 1
            self.error = f'bus lost: {exc}'
        try:
            bus.shutdown()
        except Exception:  # a dead interface may fail to close; it is dropped anyway
            pass

    def close(self) -> None:
        """Shut the bus down (node shutdown)."""
        with self._lock:
            bus, self._bus = self._bus, None
        if bus is not None:
            bus.shutdown()

    def send(self, msg: can.Message) -> bool:
        """Send one frame; return False if it was not sent (counted, never raised)."""
        bus = self._bus
        if bus is None:
            self.counts['frames_not_sent'] += 1
            return False
        try:
            bus.send(msg, timeout=self.send_timeout_s)
        except BUS_ERRORS as exc:
            self.counts['send_errors'] += 1
            if is_transient(exc):
                self.error = f'send failed, frame dropped: {exc}'
            else:
                self.lost(bus, exc)
            return False
        if self.error.startswith('send failed'):
            self.error = ''
        return True
