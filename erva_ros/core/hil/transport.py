"""CAN transports of the HIL loop, chosen by one string (SocketCAN, virtual, loopback UDP).

========================  ===================================================================
spec                      transport
========================  ===================================================================
``socketcan:can0``        the vehicle: Linux SocketCAN (``ip link set can0 up type can
                          bitrate 500000``).  Also ``socketcan:vcan0`` where vcan exists.
``virtual:NAME``          python-can's ``virtual`` bus: connects buses *inside one process*
                          only (tests that host the simulated ECU in the test process).
``udp:LOCAL:PEER``        :class:`LoopbackUdpBus`: a point-to-point CAN link between two
                          processes over UDP **unicast on 127.0.0.1** (bind LOCAL, send to
                          PEER).  What ``erva run --ecu virtual`` uses, because python-can's
                          virtual bus cannot cross processes, the kernel here has no vcan
                          module, and python-can's ``udp_multicast`` would send multicast.
========================  ===================================================================

:class:`LoopbackUdpBus` refuses any address that is not loopback, never sets
SO_REUSEADDR or multicast options, and accepts datagrams only from its peer's port,
so nothing leaves the machine and no third process can inject frames unnoticed.
"""

import ipaddress
import select
import socket
import struct
import time
from typing import Optional, Tuple

import can

#: Accepted transport kinds of :func:`open_bus`.
TRANSPORTS = ('socketcan', 'virtual', 'udp')
LOOPBACK_HOST = '127.0.0.1'

# Datagram: magic 'EC', version 1, flags (bit 0 extended, 1 remote, 2 error), id, dlc, data.
_HEADER = struct.Struct('!2sBBIB')
_MAGIC = b'EC'
_VERSION = 1
# Kernel receive timestamps, as python-can's SocketCAN backend uses them (Linux values;
# the socket module does not export them).
_SO_TIMESTAMPNS = 35
_TIMESPEC = struct.Struct('@ll')
_ANC_SIZE = socket.CMSG_SPACE(_TIMESPEC.size)


class LoopbackUdpBus(can.BusABC):
    """A python-can bus joining exactly two processes by UDP unicast on the loopback interface.

    ``channel`` is ``'LOCAL:PEER'`` (ports).  Frames are classic CAN (DLC ≤ 8).  A
    frame's timestamp is the kernel's receive time (SO_TIMESTAMPNS, epoch seconds), as
    with SocketCAN, so a reader that polls once per cycle still knows when each frame
    arrived.  After :meth:`shutdown` every operation raises
    :class:`can.CanOperationError`, as SocketCAN does when its interface goes down.
    """

    def __init__(self, channel: str, host: str = LOOPBACK_HOST, **kwargs):
        local, peer = parse_ports(channel)
        if not ipaddress.ip_address(host).is_loopback:
            raise ValueError(f'LoopbackUdpBus: host {host!r} is not a loopback address')
        family = socket.AF_INET6 if ':' in host else socket.AF_INET
        self.channel_info = f'udp loopback {host}:{local} -> {peer}'
        self._peer = (host, peer)
        self._sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            self._sock.bind((host, local))
        except OSError as exc:
            self._sock.close()
            raise can.CanInitializationError(
                f'cannot bind {host}:{local}: {exc.strerror}', exc.errno) from None
        self._sock.setblocking(False)
        self._kernel_stamps = True
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        except OSError:  # not Linux: user-space receive time instead
            self._kernel_stamps = False
        self.foreign_datagrams = 0
        self._closed = False
        super().__init__(channel=channel, **kwargs)

    def fileno(self) -> int:
        return self._sock.fileno()

    def _check_open(self) -> None:
        if self._closed:
            raise can.CanOperationError('LoopbackUdpBus is shut down')

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        self._check_open()
        if msg.dlc > 8 or msg.is_fd:
            raise ValueError('LoopbackUdpBus carries classic CAN frames (DLC <= 8) only')
        flags = (int(msg.is_extended_id) | int(msg.is_remote_frame) << 1
                 | int(msg.is_error_frame) << 2)
        data = bytes(msg.data[:msg.dlc]) if not msg.is_remote_frame else b''
        packet = _HEADER.pack(_MAGIC, _VERSION, flags, msg.arbitration_id, msg.dlc) + data
        try:
            self._sock.sendto(packet, self._peer)
        except (BlockingIOError, ConnectionRefusedError):
            # A full socket buffer or a peer not (yet) listening: the frame is lost,
            # as on a CAN bus without receivers; the E2E counters reveal it.
            pass
        except OSError as exc:
            raise can.CanOperationError(f'send failed: {exc.strerror}', exc.errno) from None

    def _recv_internal(self, timeout: Optional[float]) -> Tuple[Optional[can.Message], bool]:
        self._check_open()
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            try:
                packet, anc, _flags, addr = self._sock.recvmsg(64, _ANC_SIZE)
            except (BlockingIOError, ConnectionRefusedError):
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None, False
                try:
                    ready, _, _ = select.select([self._sock], [], [], remaining)
                except (OSError, ValueError):
                    self._check_open()
                    raise can.CanOperationError('LoopbackUdpBus socket failed') from None
                if not ready and deadline is not None and time.monotonic() >= deadline:
                    return None, False
                continue
            except OSError as exc:
                self._check_open()
                raise can.CanOperationError(f'receive failed: {exc.strerror}',
                                            exc.errno) from None
            msg = self._unpack(packet, addr, self._stamp(anc))
            if msg is not None:
                return msg, False

    def _stamp(self, anc) -> float:
        for level, kind, data in anc:
            if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS:
                sec, nsec = _TIMESPEC.unpack_from(data)
                return sec + nsec * 1e-9
        return time.time()

    def _unpack(self, packet: bytes, addr, stamp: float) -> Optional[can.Message]:
        if addr[1] != self._peer[1] or len(packet) < _HEADER.size:
            self.foreign_datagrams += 1
            return None
        magic, version, flags, can_id, dlc = _HEADER.unpack_from(packet)
        data = packet[_HEADER.size:]
        if magic != _MAGIC or version != _VERSION or dlc > 8 or (
                not flags & 2 and len(data) != dlc):
            self.foreign_datagrams += 1
            return None
        return can.Message(timestamp=stamp, arbitration_id=can_id, dlc=dlc,
                           data=data, is_extended_id=bool(flags & 1),
                           is_remote_frame=bool(flags & 2), is_error_frame=bool(flags & 4),
                           is_rx=True, channel=self.channel_info)

    def shutdown(self) -> None:
        if not self._closed:
            self._closed = True
            self._sock.close()
        super().shutdown()


def parse_ports(channel: str) -> Tuple[int, int]:
    """Return (local, peer) UDP ports from ``'LOCAL:PEER'``; ValueError with one line otherwise."""
    parts = str(channel).split(':')
    try:
        local, peer = (int(p) for p in parts)
    except ValueError:
        raise ValueError(f'udp channel must be LOCAL_PORT:PEER_PORT, got {channel!r}') from None
    for p in (local, peer):
        if not 1 <= p <= 65535:
            raise ValueError(f'udp port {p} out of range 1..65535')
    if local == peer:
        raise ValueError(f'udp channel {channel!r}: local and peer port must differ')
    return local, peer


def parse_spec(spec: str) -> Tuple[str, str]:
    """Split and check a bus spec ``KIND:CHANNEL``; ValueError with one line otherwise."""
    kind, sep, channel = str(spec).partition(':')
    if not sep or not channel or kind not in TRANSPORTS:
        raise ValueError(f'bus {spec!r}: expected socketcan:IFACE, virtual:NAME or '
                         'udp:LOCAL_PORT:PEER_PORT')
    if kind == 'udp':
        parse_ports(channel)
    return kind, channel


def open_bus(spec: str) -> can.BusABC:
    """Open the bus described by ``spec`` (see the module docstring).

    Raises ValueError for a malformed spec and can.CanError / OSError when the
    interface cannot be opened (for the caller to report and retry).
    """
    kind, channel = parse_spec(spec)
    if kind == 'udp':
        return LoopbackUdpBus(channel)
    if kind == 'virtual':
        return can.Bus(interface='virtual', channel=channel, receive_own_messages=False)
    return can.Bus(interface='socketcan', channel=channel)


def reverse_udp_spec(spec: str) -> str:
    """Return the peer's spec of a ``udp:L:P`` spec (``udp:P:L``); other specs unchanged."""
    kind, channel = parse_spec(spec)
    if kind != 'udp':
        return spec
    local, peer = parse_ports(channel)
    return f'udp:{peer}:{local}'


def free_udp_ports(n: int = 2) -> Tuple[int, ...]:
    """Return ``n`` distinct UDP ports on 127.0.0.1 that were free a moment ago."""
    socks = []
    try:
        for _ in range(n):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind((LOOPBACK_HOST, 0))
            socks.append(s)
        return tuple(s.getsockname()[1] for s in socks)
    finally:
        for s in socks:
            s.close()
