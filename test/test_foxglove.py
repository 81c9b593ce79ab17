"""`erva run --foxglove` and `erva replay --foxglove` against a Foxglove client written here.

The client speaks the Foxglove WebSocket protocol with the `websockets` package:
serverInfo and advertise (JSON text), subscribe, then binary messageData frames
(opcode 1, uint32 subscription id, uint64 log time, the message bytes).  The
foxglove-sdk 0.30.3 server offers the subprotocol ``foxglove.sdk.v1`` (the messages of
``foxglove.websocket.v1``); the client asks for both, as the Foxglove app does.
Messages are decoded with rclpy's deserializer; the bags are read with the mcap
reader and mcap-ros2-support's decoder (not ours).  Pass/fail on counts and values only.
"""

import json
import os
import socket
import struct
import subprocess
import sys
import threading
import time

import pytest

from conftest import REPO, ros_env

pytest.importorskip('foxglove')
websockets_client = pytest.importorskip('websockets.sync.client')
from websockets.exceptions import ConnectionClosed  # noqa: E402 (after the skip)

PROTOCOLS = ['foxglove.sdk.v1', 'foxglove.websocket.v1']
MESSAGE_DATA, TIME = 1, 2
TS_NS = 20_000_000


class Viewer:
    """A minimal Foxglove viewer: channels as advertised, subscriptions, received data."""

    def __init__(self, port, rcvbuf=None, max_queue=16):
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        if rcvbuf:   # a small window: a viewer that does not read stalls the server soon
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        sock.connect(('127.0.0.1', port))
        self.ws = websockets_client.connect(
            f'ws://127.0.0.1:{port}', sock=sock, subprotocols=PROTOCOLS, proxy=None,
            max_size=None, max_queue=max_queue, ping_interval=None, close_timeout=1,
            compression=None, legacy=True)
        self.channels = {}      # topic -> advertised channel
        self.server_info = None
        self.subscriptions = {}  # subscription id -> topic
        self.received = []      # (topic, log time ns, bytes)
        self.times = []

    def _handle(self, frame):
        if isinstance(frame, str):
            msg = json.loads(frame)
            if msg['op'] == 'serverInfo':
                self.server_info = msg
            elif msg['op'] == 'advertise':
                self.channels.update({c['topic']: c for c in msg['channels']})
            return
        if frame[0] == MESSAGE_DATA:
            sub, log_time = struct.unpack_from('<IQ', frame, 1)
            self.received.append((self.subscriptions[sub], log_time, bytes(frame[13:])))
        elif frame[0] == TIME:
            self.times.append(struct.unpack_from('<Q', frame, 1)[0])

    def wait_channels(self, topics, timeout=60.0):
        end = time.monotonic() + timeout
        while not set(topics) <= set(self.channels):
            assert time.monotonic() < end, f'not advertised: {set(topics) - set(self.channels)}'
            self._handle(self.ws.recv(timeout=max(0.1, end - time.monotonic())))

    def subscribe(self, topics):
        subs = [{'id': i + 1, 'channelId': self.channels[t]['id']} for i, t in enumerate(topics)]
        self.subscriptions.update({i + 1: t for i, t in enumerate(topics)})
        self.ws.send(json.dumps({'op': 'subscribe', 'subscriptions': subs}))

    def read_until_closed(self, timeout=300.0):
        end = time.monotonic() + timeout
        try:
            while time.monotonic() < end:
                self._handle(self.ws.recv(timeout=end - time.monotonic()))
        except (ConnectionClosed, TimeoutError):
            pass

    def of(self, topic):
        return [(t, data) for top, t, data in self.received if top == topic]

    def close(self):
        self.ws.close()


def _bag_messages(bag_dir):
    """Return {topic: [(log time, bytes, decoded)]} read by the mcap libraries."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    mcaps = [f for f in os.listdir(bag_dir) if f.endswith('.mcap')]
    assert len(mcaps) == 1, os.listdir(bag_dir)
    out = {}
    with open(os.path.join(bag_dir, mcaps[0]), 'rb') as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append((message.log_time, message.data, decoded))
    return out


def _stamp(header):
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def _start(*args):
    return subprocess.Popen([sys.executable, '-m', 'erva_ros.cli', *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=ros_env(), cwd=REPO, start_new_session=True)


def _served_port(proc, timeout=120.0):
    """Read the command's stderr until it names the Foxglove URL; return the port."""
    lines = []
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        line = proc.stderr.readline()
        if not line:
            break
        lines.append(line)
        if 'Foxglove: open ws://127.0.0.1:' in line:
            return int(line.split('ws://127.0.0.1:')[1].split()[0])
    proc.kill()
    raise AssertionError('no Foxglove URL:\n' + ''.join(lines) + proc.stderr.read())


def _finish(proc, timeout=240):
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, err
    return json.loads(out), err


# -- options -----------------------------------------------------------------------------------
def test_address_parsing_and_defaults():
    from erva_ros.commands.run import FOXGLOVE_DEFAULT
    from erva_ros.ros import foxglove_server as fg
    assert FOXGLOVE_DEFAULT == fg.DEFAULT_ADDRESS == '127.0.0.1:8765'
    assert fg.parse_address('9000') == ('127.0.0.1', 9000)   # loopback unless named
    assert fg.parse_address('0.0.0.0:80') == ('0.0.0.0', 80)
    assert fg.parse_address('[::1]:0') == ('::1', 0)
    assert fg.parse_address('localhost:8765') == ('localhost', 8765)
    for bad in ('', 'x', ':80', '1.2.3.4:', '70000', '-1', '::1:80', '[::1]80'):
        with pytest.raises(ValueError):
            fg.parse_address(bad)
    assert fg.is_loopback('127.0.0.2') and fg.is_loopback('::1') and fg.is_loopback('localhost')
    assert not fg.is_loopback('0.0.0.0') and not fg.is_loopback('192.0.2.1')


def _one_error_line(proc, *needles):
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert all(n in lines[0] for n in needles), lines[0]
    assert proc.stdout == ''


def test_unusable_address_is_one_line_exit_2_before_anything_starts(erva, tmp_path):
    with socket.socket() as taken:
        taken.bind(('127.0.0.1', 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        run = erva('run', '--foxglove', f'127.0.0.1:{port}', '--record', tmp_path)
        _one_error_line(run, 'erva run: error: --foxglove', str(port), 'in use')
        replay = erva('replay', os.path.join(REPO, 'bags', 'sample'), '--foxglove', port)
        _one_error_line(replay, 'erva replay: error: --foxglove', 'in use')
    assert os.listdir(tmp_path) == []          # no bag: the recorder never started
    # 192.0.2.1 (TEST-NET-1) is no interface of this machine.
    run = erva('run', '--foxglove', '192.0.2.1:8765', '--no-record')
    _one_error_line(run, 'erva run: error: --foxglove', '192.0.2.1:8765')
    run = erva('run', '--foxglove', 'localhost:http', '--no-record')
    _one_error_line(run, 'erva run: error: --foxglove', 'not a number')


# -- the server alone ----------------------------------------------------------------------------
def test_a_viewer_that_never_reads_loses_its_oldest_and_is_counted():
    """Logging never waits for a stalled viewer; the SDK's queue overflow is counted."""
    from erva_ros.ros.foxglove_server import FoxgloveServer
    server = FoxgloveServer('127.0.0.1', 0, backlog=64, session={'scenario': 'test'})
    try:
        server.add_topic('/erva/damping_cmd', 'trajectory_msgs/msg/JointTrajectory')
        stalled = Viewer(server.port, rcvbuf=4096, max_queue=1)
        stalled.wait_channels(['/erva/damping_cmd'])
        stalled.subscribe(['/erva/damping_cmd'])
        end = time.monotonic() + 60
        while not server.stats()['clients_subscribed']:
            assert time.monotonic() < end
            time.sleep(0.01)
        payload = b'\x00\x01\x00\x00' + bytes(1000)
        logged = 0
        # The kernel's socket buffers take a few MB, then the 64-message queue overflows.
        while not server.stats()['overflow_events'] and logged < 200_000:
            server.log('/erva/damping_cmd', payload, logged)
            logged += 1
        stats = server.stats()
        assert stats['overflow_events'] >= 1, stats
        assert stats['forwarded_total'] == logged
        assert list(stats['offered'].values()) == [logged]   # everything was offered to it
        # It never read: far less than was offered is in its buffers.
        stalled.ws.close_timeout = 0.1
    finally:
        server.close()


# -- live --------------------------------------------------------------------------------------
@pytest.mark.ros
def test_viewer_gets_the_live_loop_as_the_bag_holds_it(tmp_path):
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectory

    proc = _start('run', '--foxglove', '127.0.0.1:0', '--duration', 4, '--record', tmp_path,
                  '--json')
    try:
        viewer = Viewer(_served_port(proc))
        topics = ['/erva/state', '/erva/damping_cmd', '/erva/session']
        viewer.wait_channels(topics)
        assert viewer.server_info['supportedEncodings'] == ['cdr']
        for topic, type_name in (('/erva/state', 'sensor_msgs/msg/JointState'),
                                 ('/erva/damping_cmd', 'trajectory_msgs/msg/JointTrajectory')):
            channel = viewer.channels[topic]
            assert (channel['encoding'], channel['schemaEncoding']) == ('cdr', 'ros2msg')
            assert channel['schemaName'] == type_name
            assert 'MSG: std_msgs/Header' in channel['schema']
        viewer.subscribe(topics)
        viewer.read_until_closed()      # the server stops after the loop's nodes
        viewer.close()
    finally:
        summary, _ = _finish(proc)
    assert summary['ok'], summary['errors']
    session = [json.loads(data) for _, data in viewer.of('/erva/session')]
    assert session and session[0]['scenario'] == 'paper'
    assert session[0]['controller'] == 'preview'
    bag = _bag_messages(summary['bag'])
    published = summary['messages']['published']
    for topic, cls, key in (('/erva/state', JointState, 'state'),
                            ('/erva/damping_cmd', JointTrajectory, 'damping_cmd')):
        recorded = {_stamp(decoded.header): (data, decoded) for _, data, decoded in bag[topic]}
        got = [deserialize_message(data, cls) for _, data in viewer.of(topic)]
        stamps = [_stamp(m.header) for m in got]
        # ~50 Hz: a 4 s run has 201 states; the viewer subscribed before the loop ran, so
        # it has them all, in order, one period apart (counted, not timed).
        assert len(got) == published[key], (topic, len(got), published[key])
        assert stamps == sorted(stamps)
        if key == 'state':   # (a command may be the safe one, stamped off the grid)
            assert all(b - a == TS_NS for a, b in zip(stamps, stamps[1:]))
        # The viewer saw exactly what the bag holds, stamp for stamp.
        assert sorted(recorded) == stamps, topic
        for msg, stamp in zip(got, stamps):
            data, decoded = recorded[stamp]
            if key == 'state':
                assert list(msg.position) == list(decoded.position)
                assert list(msg.velocity) == list(decoded.velocity)
                assert list(msg.name) == list(decoded.name)
            else:
                assert [list(p.positions) for p in msg.points] == [
                    list(p.positions) for p in decoded.points]
    fox = summary['foxglove']
    assert fox['clients_seen'] == 1 and fox['overflow_events'] == 0
    # Counted per viewer (as of the server's last periodic status).
    assert list(fox['offered'].values())[0] > 0
    assert summary['nodes']['foxglove_server']['stopped_cleanly']


@pytest.mark.ros
def test_a_stalled_viewer_slows_nothing_and_the_bag_loses_nothing(tmp_path):
    proc = _start('run', '--foxglove', '127.0.0.1:0', '--duration', 4, '--record', tmp_path,
                  '--json')
    stalled = None
    try:
        # It subscribes to everything, then never reads (nor does its library: 1 frame).
        stalled = Viewer(_served_port(proc), rcvbuf=4096, max_queue=1)
        stalled.wait_channels(['/erva/state', '/erva/damping_cmd', '/diagnostics'])
        stalled.subscribe(sorted(stalled.channels))
        summary, _ = _finish(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
        if stalled is not None:
            threading.Thread(target=stalled.close, daemon=True).start()
    assert summary['ok'], summary['errors']
    assert summary['messages']['dropped_total'] == 0      # the monitor got everything
    assert summary['plant']['steps'] == 200
    # One command per state, as in test_run_realtime (a loaded machine may make the NMPC
    # skip to the newest state: counted as missed samples).
    assert summary['commands']['for_samples'] + summary['nmpc']['missed_samples'] == 201
    bag = _bag_messages(summary['bag'])
    published = summary['messages']['published']
    for key, n in published.items():
        assert len(bag[f'/erva/{key}']) == n, key
    assert summary['recording']['lost'] == 0
    assert len(bag['/erva/road/preview']) == published['road/preview']
    assert published['road/preview'] + summary['road']['samples_skipped'] == 201
    fox = summary['foxglove']
    # (The server's counters as of its last periodic status, up to 1 s before the end.)
    assert fox['clients_seen'] == 1 and fox['received'] > 0
    assert summary['nodes']['foxglove_server']['stopped_cleanly']


# -- replay ------------------------------------------------------------------------------------
@pytest.mark.ros
def test_replay_serves_the_bag_with_its_bytes_and_times():
    from mcap.reader import make_reader
    sample = os.path.join(REPO, 'bags', 'sample')
    proc = _start('replay', sample, '--foxglove', '127.0.0.1:0', '--rate', 4, '--json')
    try:
        viewer = Viewer(_served_port(proc))
        viewer.wait_channels(['/erva/state', '/erva/session'])
        topics = sorted(viewer.channels)
        viewer.subscribe(topics)
        viewer.read_until_closed()
        viewer.close()
    finally:
        stats, _ = _finish(proc)
    with open(os.path.join(sample, 'sample_0.mcap'), 'rb') as fh:
        reader = make_reader(fh)
        session = next(m.metadata for m in reader.iter_metadata() if m.name == 'erva_session')
        recorded = {}
        for _, channel, message in reader.iter_messages(log_time_order=True):
            recorded.setdefault(channel.topic, []).append((message.log_time, message.data))
    assert set(recorded) | {'/erva/session'} == set(topics)
    for topic, messages in recorded.items():
        assert viewer.of(topic) == messages, topic     # every message: same bytes, same time
    assert json.loads(viewer.of('/erva/session')[0][1]) == session
    # The server's time follows the bag's, as played.
    assert viewer.times == sorted(viewer.times) and len(viewer.times) == stats['total']
    total = sum(map(len, recorded.values()))
    assert stats['foxglove']['forwarded_total'] == stats['total'] == total


# -- the benchmark's headless viewer (erva_ros.session.bench.foxglove_viewer) -----------------
def test_headless_viewer_answers_binary_pings_and_counts_every_message():
    """The viewer of `erva bench --live --foxglove-ab`, run as the benchmark runs it.

    The server here (websockets' own) pings with a payload that is not UTF-8: the pong
    must carry it back byte for byte (websockets checks, and only then sets the event),
    and every message sent before the close is counted, per topic, with its size.
    """
    from websockets.sync.server import serve
    payloads = {'/erva/state': [bytes([0xff, 0xfe, i]) * 10 for i in range(40)],
                '/erva/damping_cmd': [bytes([0x80 + i]) * 7 for i in range(25)]}
    seen = {}

    def session(ws):
        seen['subprotocol'] = ws.subprotocol
        ws.send(json.dumps({'op': 'serverInfo', 'name': 'test', 'capabilities': []}))
        ws.send(json.dumps({'op': 'advertise', 'channels': [
            {'id': 10 + i, 'topic': t, 'encoding': 'cdr', 'schemaName': 'x', 'schema': ''}
            for i, t in enumerate(payloads)]}))
        request = json.loads(ws.recv(timeout=60))
        seen['subscribe'] = request
        subs = {s['channelId']: s['id'] for s in request['subscriptions']}
        seen['pong'] = ws.ping(b'\xff\x00\xfe\x80').wait(timeout=60)
        for i, (topic, messages) in enumerate(payloads.items()):
            for k, data in enumerate(messages):
                ws.send(struct.pack('<BIQ', MESSAGE_DATA, subs[10 + i], k) + data)
        ws.close()

    with serve(session, '127.0.0.1', 0, subprotocols=PROTOCOLS, compression=None) as server:
        port = server.socket.getsockname()[1]
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        proc = subprocess.run([sys.executable, '-m', 'erva_ros.session.bench.foxglove_viewer',
                               '--port', str(port)], env=ros_env(), cwd=REPO,
                              capture_output=True, text=True, timeout=120)
        server.shutdown()
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert seen['subprotocol'] == 'foxglove.sdk.v1' and seen['pong'] is True
    assert [s['id'] for s in seen['subscribe']['subscriptions']] == [1, 2]
    assert result == {'subscribed': 2, 'total': 65,
                      'messages': {t: len(m) for t, m in payloads.items()},
                      'bytes': {t: sum(map(len, m)) for t, m in payloads.items()}}


def test_headless_viewer_without_a_server_is_one_line_exit_2():
    with socket.socket() as free:
        free.bind(('127.0.0.1', 0))
        port = free.getsockname()[1]     # bound, not listening: refused
    proc = subprocess.run([sys.executable, '-m', 'erva_ros.session.bench.foxglove_viewer',
                           '--port', str(port), '--connect-timeout', '0.5'],
                          env=ros_env(), cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('foxglove_viewer: error: '), proc.stderr
