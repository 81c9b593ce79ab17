"""A headless Foxglove viewer: subscribe to every channel of a server and count what arrives.

The load a connected Foxglove app puts on the server, without the app: the benchmark
(`erva bench --live --foxglove-ab`) runs it as a separate process next to the session.
The WebSocket side is the ``websockets`` library (extra ``erva_ros[foxglove]``): the
SDK's ``foxglove.sdk.v1`` subprotocol, JSON advertise and subscribe, binary messageData
(opcode 1, uint32 subscription id, uint64 log time, the message).  ``--stall`` subscribes
and then never reads: the viewer that must not slow anything (a small TCP window and a
one-frame queue, so the library stops reading the socket too).

    python -m erva_ros.session.bench.foxglove_viewer --port 8765 [--stall] [--seconds S]

Prints one JSON line at the end: messages and bytes per topic.
"""

import argparse
import json
import socket
import struct
import sys
import time
from typing import Dict, Optional

from websockets.exceptions import ConnectionClosed, WebSocketException
from websockets.sync.client import connect

from erva_ros.ros.foxglove_server import SUBPROTOCOL

#: messageData: opcode, subscription id, log time; then the message bytes.
_MESSAGE_DATA = 0x01
_HEADER = struct.Struct('<BIQ')
#: The stalled viewer's receive buffer (bytes): its window fills after a few messages.
STALL_RCVBUF = 4096


def _connect(host: str, port: int, stall: bool, timeout_s: float):
    """Return an open websockets connection; the socket made here (window set first)."""
    sock = socket.socket(socket.AF_INET6 if ':' in host else socket.AF_INET)
    if stall:   # before connecting: the TCP window is agreed then
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, STALL_RCVBUF)
    sock.settimeout(timeout_s)
    try:
        sock.connect((host, port))
    except OSError:
        sock.close()
        raise
    sock.settimeout(None)
    return connect(f'ws://{host}:{port}' if ':' not in host else f'ws://[{host}]:{port}',
                   sock=sock, subprotocols=[SUBPROTOCOL], proxy=None, max_size=None,
                   max_queue=1 if stall else 16, compression=None, open_timeout=timeout_s,
                   ping_interval=None, close_timeout=1)


def watch(host: str, port: int, stall: bool = False, seconds: Optional[float] = None,
          connect_timeout: float = 60.0) -> Dict:
    """Subscribe to every channel and count the messages until the server goes away."""
    end_connect = time.monotonic() + connect_timeout
    while True:
        try:
            ws = _connect(host, port, stall, max(1.0, end_connect - time.monotonic()))
            break
        except (OSError, WebSocketException):
            if time.monotonic() > end_connect:
                raise
            time.sleep(0.1)
    topics: Dict[int, str] = {}
    counts: Dict[str, int] = {}
    size: Dict[str, int] = {}
    subscribed = 0
    end = None if seconds is None else time.monotonic() + seconds
    with ws:
        try:
            while end is None or time.monotonic() < end:
                frame = ws.recv(timeout=None if end is None else max(0.01,
                                                                     end - time.monotonic()))
                if isinstance(frame, str):
                    msg = json.loads(frame)
                    if msg.get('op') != 'advertise':
                        continue
                    subs = []
                    for ch in msg['channels']:
                        subscribed += 1
                        topics[subscribed] = ch['topic']
                        subs.append({'id': subscribed, 'channelId': ch['id']})
                    ws.send(json.dumps({'op': 'subscribe', 'subscriptions': subs}))
                    if stall:
                        # Never read again: the server's queue for us fills and overflows.
                        while end is None or time.monotonic() < end:
                            time.sleep(0.1)
                        break
                elif len(frame) >= _HEADER.size and frame[0] == _MESSAGE_DATA:
                    _, sub, _ = _HEADER.unpack_from(frame)
                    topic = topics.get(sub, '?')
                    counts[topic] = counts.get(topic, 0) + 1
                    size[topic] = size.get(topic, 0) + len(frame) - _HEADER.size
        except (ConnectionClosed, TimeoutError, OSError):
            pass
    return {'subscribed': subscribed, 'messages': counts, 'bytes': size,
            'total': sum(counts.values())}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='python -m erva_ros.session.bench.foxglove_viewer',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('--host', default='127.0.0.1', help='server address (127.0.0.1)')
    parser.add_argument('--port', type=int, required=True, help='server port')
    parser.add_argument('--stall', action='store_true',
                        help='subscribe, then never read (a viewer that does not keep up)')
    parser.add_argument('--seconds', type=float, default=None,
                        help='stop after S seconds (default: when the server goes away)')
    parser.add_argument('--connect-timeout', type=float, default=60.0, metavar='S',
                        help='keep trying to connect for S seconds (default 60)')
    args = parser.parse_args(argv)
    try:
        result = watch(args.host, args.port, args.stall, args.seconds, args.connect_timeout)
    except (OSError, WebSocketException) as exc:   # refused, or not a Foxglove server
        print(f'foxglove_viewer: error: {exc}', file=sys.stderr)
        return 2
    print(json.dumps(result), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
