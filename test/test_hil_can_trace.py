"""`erva run --ecu virtual --can-log FILE`: the bridge's CAN trace, read back as others would.

The trace is read with python-can's readers (can.BLFReader / can.ASCReader), its payloads
decoded with cantools on config/erva_ecu.dbc and the session's bag with the mcap reader
(mcap-ros2-support): none of it is erva_ros's code.  Both directions are there, each
frame once: every ECU frame the bridge accepted is one message of its ecu/* topic, with
the same values; every CONTROLLED command frame is the bridge's copy of a damping_cmd of
the bag, of its cycle.  The timestamps are the bag's clock (epoch seconds): a cycle's
first frame has exactly the cycle's stamp, and the recorder received each ecu/* message
after the bridge had received its frame.
"""

import json
import os

import can
import cantools
import pytest

from conftest import REPO, run_erva

pytestmark = pytest.mark.ros

TS = 0.02
DBC = os.path.join(REPO, 'config', 'erva_ecu.dbc')
#: Frame id -> the bag topics (the first of each carries the checked signals).
ECU_TOPICS = {0x200: ('/erva/ecu/damping_applied',),
              0x201: ('/erva/ecu/sprung_accel', '/erva/ecu/suspension'),
              0x202: ('/erva/ecu/generator',)}


def _bag(bag_dir, topics):
    """Return {topic: [(log time ns, header stamp ns, message)]}, read with mcap."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    mcaps = [f for f in os.listdir(bag_dir) if f.endswith('.mcap')]
    assert len(mcaps) == 1, os.listdir(bag_dir)
    out = {t: [] for t in topics}
    with open(os.path.join(bag_dir, mcaps[0]), 'rb') as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _, channel, message, msg in reader.iter_decoded_messages(topics=list(topics)):
            h = msg.header.stamp
            out[channel.topic].append((message.log_time, h.sec * 10**9 + h.nanosec, msg))
    return out


def _signals(msg):
    """Return the ECU frame's values as the bag's topic carries them."""
    if 'CE_APPLIED' in msg:
        return [msg['CE_APPLIED'], msg['CE_MEAN']]
    if 'SPRUNG_ACCEL' in msg:
        return [msg['SPRUNG_ACCEL']]
    return None                   # generator: in stroke terms on the topic (v_gen = l·φ')


def _topic_values(topic, msg):
    if topic.endswith('damping_applied'):
        return list(msg.position)
    return [msg.accel.linear.z]


@pytest.mark.parametrize('suffix', ['blf', 'asc'])
def test_can_trace_holds_every_frame_both_ways_as_the_bag_has_them(tmp_path, suffix):
    trace = tmp_path / f'bus.{suffix}'
    proc = run_erva('run', '--ecu', 'virtual', '--duration', 3, '--json',
                    '--record', tmp_path / 'bags', '--can-log', trace, timeout=240)
    assert proc.returncode == 0, proc.stderr
    s = json.loads(proc.stdout)
    bridge = s['hil']['bridge']
    assert all(bridge[f'dropped_{k}'] == 0 for k in ('crc', 'counter', 'length')), bridge
    # ASC keeps the measurement's start to the ms: its absolute times read back up to
    # 1 ms early; BLF keeps them to the ns (a float of epoch seconds: 0.24 us).
    tol = 1e-6 if suffix == 'blf' else 1e-3 + 1e-6
    reader = (can.BLFReader(str(trace)) if suffix == 'blf'
              else can.ASCReader(str(trace), relative_timestamp=False))
    frames = list(reader)
    db = cantools.database.load_file(DBC)
    rx = [f for f in frames if f.is_rx]
    tx = [f for f in frames if not f.is_rx]
    assert {f.arbitration_id for f in rx} == set(ECU_TOPICS)
    assert {f.arbitration_id for f in tx} == {0x100}
    assert all(f.dlc == 8 for f in frames)

    topics = [t for ts in ECU_TOPICS.values() for t in ts] + ['/erva/damping_cmd']
    bag = _bag(s['bag'], topics)
    # ECU -> bridge: each frame one message of each of its topics, in order, same values.
    first = {}                               # cycle stamp -> earliest frame time
    received = []                            # (cycle stamp, frame time)
    for fid, names in ECU_TOPICS.items():
        got = [f for f in rx if f.arbitration_id == fid]
        for topic in names:
            assert len(bag[topic]) == len(got) > 100, (topic, len(bag[topic]), len(got))
        for f, (log_ns, stamp_ns, msg) in zip(got, bag[names[0]]):
            want = _signals(db.decode_message(fid, bytes(f.data)))
            if want is not None:
                assert _topic_values(names[0], msg) == pytest.approx(want, rel=1e-12)
            assert f.timestamp >= stamp_ns * 1e-9 - tol            # not before its cycle
            assert log_ns * 1e-9 >= f.timestamp - tol              # recorded after it
            first[stamp_ns] = min(first.get(stamp_ns, float('inf')), f.timestamp)
            received.append((stamp_ns, f.timestamp))
    # A cycle's stamp is the receive time of its first frame: the trace's clock.
    assert all(abs(t - stamp * 1e-9) <= tol for stamp, t in first.items())
    # ... and its frames come before the next cycle's (the ECU sends a cycle's frames in
    # turn on one bus; how long after the first they come depends on the load: a stalled
    # ECU process once spread a cycle over 198 ms).
    stamps = sorted(first)
    after = dict(zip(stamps, stamps[1:]))
    assert all(t <= first[after[stamp]] + tol for stamp, t in received if stamp in after)

    # Bridge -> ECU: every CONTROLLED frame is a damping_cmd of the bag, in order (the
    # refused ones have none), of its cycle, with its first value (clamped, 2 Ns/m LSB).
    lo, hi = 0.0, 0.95 * 120.0 ** 2 / 0.6          # config/hil.yaml: duty, kappa, R
    cmds = sorted(bag['/erva/damping_cmd'], key=lambda m: m[0])
    decoded = [(f, db.decode_message(0x100, bytes(f.data), decode_choices=False)) for f in tx]
    controlled = [(f, m) for f, m in decoded if m['CMD_MODE'] == 1]
    assert len(controlled) == bridge['commands_received'] > 100
    i = 0
    for f, m in controlled:
        while i < len(cmds):
            _, stamp_ns, msg = cmds[i]
            i += 1
            c_e = min(max(msg.points[0].positions[0], lo), hi)
            if (round(stamp_ns * 1e-9 / TS) % 256 == m['CMD_CYCLE']
                    and abs(m['CMD_CE'] - c_e) <= 1.0):
                break
        else:
            raise AssertionError(f'frame {m} at {f.timestamp} has no damping_cmd')
        assert f.timestamp >= stamp_ns * 1e-9 - tol      # sent after its sample
    safe = [m for _, m in decoded if m['CMD_MODE'] == 0]
    assert all(m['CMD_CYCLE'] == 0 for m in safe)
