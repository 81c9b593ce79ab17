"""A headless Foxglove viewer: subscribe to every channel of a server and count what arrives.

The load a connected Foxglove app puts on the server, without the app: the benchmark
(`erva bench --live --foxglove-ab`) runs it as a separate process next to the session.
Standard library only (RFC 6455 client, the SDK's ``foxglove.sdk.v1`` subprotocol:
JSON advertise, subscribe, binary messageData).  ``--stall`` subscribes and then never
reads: the viewer that must not slow anything.

    python -m erva_ros.session.foxglove_viewer --port 8765 [--stall] [--seconds S]

Prints one JSON line at the end: messages and bytes per topic.
"""

import argparse
import base64
import json
import os
import socket
import struct
import sys
import time
from typing import Dict, Optional, Tuple

from erva_ros.ros.foxglove_server import SUBPROTOCOL

_TEXT, _BINARY, _CLOSE, _PING, _PONG = 0x1, 0x2, 0x8, 0x9, 0xA


class ViewerConnection:
    """One WebSocket connection to a Foxglove server (client side of RFC 6455)."""

    def __init__(self, host: str, port: int, timeout: float = 10.0,
                 rcvbuf: Optional[int] = None):
        self.sock = socket.socket(socket.AF_INET6 if ':' in host else socket.AF_INET)
        if rcvbuf:   # before connecting: the TCP window is agreed then
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(timeout)
        self.sock.connect((host, port))
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f'GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n'
                           f'Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n'
                           f'Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: '
                           f'{SUBPROTOCOL}\r\n\r\n').encode())
        self._buf = b''
        while b'\r\n\r\n' not in self._buf:
            self._buf += self._recv()
        head, self._buf = self._buf.split(b'\r\n\r\n', 1)
        if not head.startswith(b'HTTP/1.1 101'):
            raise ConnectionError(head.split(b'\r\n', 1)[0].decode(errors='replace'))

    def _recv(self) -> bytes:
        chunk = self.sock.recv(1 << 16)
        if not chunk:
            raise ConnectionError('closed by the server')
        return chunk

    def _take(self, n: int) -> bytes:
        while len(self._buf) < n:
            self._buf += self._recv()
        out, self._buf = self._buf[:n], self._buf[n:]
        return out

    def send_text(self, text: str, opcode: int = _TEXT) -> None:
        """Send one masked frame (clients must mask)."""
        payload = text.encode()
        n = len(payload)
        head = bytes([0x80 | opcode])
        if n < 126:
            head += bytes([0x80 | n])
        elif n < 1 << 16:
            head += bytes([0x80 | 126]) + struct.pack('>H', n)
        else:
            head += bytes([0x80 | 127]) + struct.pack('>Q', n)
        mask = os.urandom(4)
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))

    def recv(self) -> Tuple[int, bytes]:
        """Return (opcode, payload) of the next data frame; answer pings on the way."""
        while True:
            b0, b1 = self._take(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack('>H', self._take(2))[0]
            elif n == 127:
                n = struct.unpack('>Q', self._take(8))[0]
            payload = self._take(n)
            opcode = b0 & 0x0F
            if opcode == _PING:
                self.send_text(payload.decode(errors='replace'), _PONG)
            elif opcode == _CLOSE:
                raise ConnectionError('closed by the server')
            elif opcode in (_TEXT, _BINARY):
                return opcode, payload


def watch(host: str, port: int, stall: bool = False, seconds: Optional[float] = None,
          connect_timeout: float = 60.0) -> Dict:
    """Subscribe to every channel and count the messages until the server goes away."""
    end_connect = time.monotonic() + connect_timeout
    while True:
        try:
            # A stalled viewer with a small window: the server's queue overflows sooner.
            conn = ViewerConnection(host, port, rcvbuf=4096 if stall else None)
            break
        except OSError:
            if time.monotonic() > end_connect:
                raise
            time.sleep(0.1)
    conn.sock.settimeout(None)
    topics: Dict[int, str] = {}
    counts: Dict[str, int] = {}
    size: Dict[str, int] = {}
    subscribed = 0
    end = None if seconds is None else time.monotonic() + seconds
    try:
        while end is None or time.monotonic() < end:
            if end is not None:
                conn.sock.settimeout(max(0.01, end - time.monotonic()))
            opcode, payload = conn.recv()
            if opcode == _TEXT:
                msg = json.loads(payload)
                if msg.get('op') == 'advertise':
                    subs = []
                    for ch in msg['channels']:
                        subscribed += 1
                        topics[subscribed] = ch['topic']
                        subs.append({'id': subscribed, 'channelId': ch['id']})
                    conn.send_text(json.dumps({'op': 'subscribe', 'subscriptions': subs}))
                    if stall:
                        # Never read again: the server's queue for us fills and overflows.
                        while end is None or time.monotonic() < end:
                            time.sleep(0.1)
                        break
            elif payload[:1] == b'\x01':
                topic = topics.get(struct.unpack_from('<I', payload, 1)[0], '?')
                counts[topic] = counts.get(topic, 0) + 1
                size[topic] = size.get(topic, 0) + len(payload) - 13
    except (ConnectionError, socket.timeout, OSError):
        pass
    finally:
        conn.sock.close()
    return {'subscribed': subscribed, 'messages': counts, 'bytes': size,
            'total': sum(counts.values())}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='python -m erva_ros.session.foxglove_viewer',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('--host', default='127.0.0.1', help='server address (127.0.0.1)')
    parser.add_argument('--port', type=int, required=True, help='server port')
    parser.add_argument('--stall', action='store_true',
                        help='subscribe, then never read (a viewer that does not keep up)')
    parser.add_argument('--seconds', type=float, default=None,
                        help='stop after S seconds (default: when the server goes away)')
    args = parser.parse_args(argv)
    try:
        result = watch(args.host, args.port, args.stall, args.seconds)
    except OSError as exc:
        print(f'foxglove_viewer: error: {exc}', file=sys.stderr)
        return 2
    print(json.dumps(result), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
