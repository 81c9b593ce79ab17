"""``erva replay`` over real DDS: record -> replay -> record again gives the same messages."""

import json
import os
import signal
import subprocess
import sys
import time

from conftest import REPO, ros_env
import numpy as np
import pytest

from rclpy.serialization import deserialize_message

from erva_ros.core.bag.reader import open_bag
from erva_ros.core.bag.session import recorder_ros_args
from erva_ros.ros.bag_messages import message_class
from ros_msgs import decoded
from recorder_helpers import DiagnosticsWatcher, wait_recorded

pytestmark = pytest.mark.ros
STARTED = []   # processes started here, killed if a failing test left them running


@pytest.fixture(autouse=True, scope='module')
def no_stray_processes():
    yield
    while STARTED:
        proc = STARTED.pop()
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def start_recorder(bag_dir, node_name, topics=None):
    proc = subprocess.Popen([sys.executable, '-m', 'erva_ros.nodes.recorder_node',
                             *recorder_ros_args(bag_dir, {'scenario': node_name},
                                                node_name=node_name, topics=topics,
                                                parameters={'diagnostics_period_s': 0.2})],
                            env=ros_env(), cwd=REPO, text=True, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    STARTED.append(proc)
    end = time.monotonic() + 60   # generous: a loaded machine starts Python slowly
    while not os.path.exists(bag_dir):
        assert proc.poll() is None and time.monotonic() < end, proc.communicate()
        time.sleep(0.05)
    return proc


def stop(proc, watcher, published, name):
    """Stop recorder ``name`` once it says it wrote ``published`` ({topic: n})."""
    wait_recorded(watcher, published, name)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err


def by_topic(bag_dir, skip_status_of=None):
    """Return {topic: [(log_ns, publish_ns, data)]}, without the named recorder's statuses."""
    out = {}
    for m in open_bag(bag_dir).messages():
        if skip_status_of and m.topic == '/diagnostics' and \
                f'{skip_status_of}: bag recorder'.encode() in m.data:
            continue
        out.setdefault(m.topic, []).append((m.log_time_ns, m.publish_time_ns, m.data))
    return out


def scheduled_vs_published(original, played, rate):
    """Return (schedule offsets, publish times) in ns of the played messages, matched in order.

    The player schedules message i at (log_i - log_0) / rate after its start (log times of
    the original bag) and publishes it no earlier; the second recording keeps each
    message's source timestamp, i.e. when the player published it.
    """
    log0 = min(msgs[0][0] for topic, msgs in original.items() if topic in played)
    offsets, published = [], []
    for topic, msgs in played.items():
        assert len(msgs) == len(original[topic]), topic
        offsets += [(log - log0) / rate for log, _, _ in original[topic]]
        published += [pub for _, pub, _ in msgs]
    return np.array(offsets), np.array(published, dtype=np.int64)


def check_timing(original, played, stats, rate):
    """Every message was out between its scheduled time and that plus the player's lateness.

    The tolerance is what the player itself reports (``lateness_ms``, measured once each
    message was out), so a busy machine widens it only as far as it made the player late;
    2 ms allow for the system clock (source timestamps) being slewed against the monotonic
    one (the schedule) over a few seconds.
    """
    assert stats['lateness_ms']['p50'] >= 0              # never early
    offsets, published = scheduled_vs_published(original, played, rate)
    start = published - offsets                          # the start each message implies
    spread_ms = (start.max() - start.min()) * 1e-6
    assert spread_ms <= stats['lateness_ms']['max'] + 2.0, (spread_ms, stats['lateness_ms'])


@pytest.fixture(scope='module')
def recorded(tmp_path_factory):
    """Return a bag recorded from the contract traffic (3 s at 50 Hz)."""
    bag = str(tmp_path_factory.mktemp('replay') / 'original')
    watcher = DiagnosticsWatcher()
    try:
        rec = start_recorder(bag, 'rec_a')
        pub = subprocess.run([sys.executable, '-m', 'erva_ros.ros.traffic', 'contract',
                              '--duration', '3', '--ack-timeout', '60'], env=ros_env(),
                             cwd=REPO, capture_output=True, text=True, timeout=600)
        assert pub.returncode == 0, pub.stderr
        result = json.loads(pub.stdout.strip().splitlines()[-1])
        assert result['acked']
        stop(rec, watcher, result['published'], 'rec_a')
    finally:
        watcher.close()
    return bag


def replay(*args, timeout=600):
    proc = subprocess.run([sys.executable, '-m', 'erva_ros.cli', 'replay', *args, '--json'],
                          env=ros_env(), cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def test_record_replay_record_gives_the_same_messages(recorded, tmp_path):
    again = str(tmp_path / 'again')
    watcher = DiagnosticsWatcher()
    try:
        rec = start_recorder(again, 'rec_b')
        stats = replay(recorded, '--wait-for-subscribers', '60')
        stop(rec, watcher, stats['published'], 'rec_b')
    finally:
        watcher.close()
    assert stats['acknowledged'] and not stats['stopped']
    first, second = by_topic(recorded), by_topic(again, skip_status_of='rec_b')
    assert sorted(first) == sorted(second)
    for topic in first:
        cls = message_class(open_bag(recorded).topics[topic].type)
        assert [deserialize_message(d, cls) for _, _, d in second[topic]] == \
            [deserialize_message(d, cls) for _, _, d in first[topic]], topic
        if topic != '/diagnostics':
            # Byte for byte; the first recorder's own statuses reached it unpadded from
            # its own process and come back padded to 4 bytes, hence not for them.
            assert [d for _, _, d in second[topic]] == [d for _, _, d in first[topic]], topic
    assert stats['total'] == sum(len(v) for v in first.values())
    # Original timing: each message out at its original offset from the first, no
    # earlier and no later than the player says it was late.
    check_timing(first, second, stats, rate=1.0)


def test_rate_topics_and_clock(recorded, tmp_path):
    out = str(tmp_path / 'fast')
    watcher = DiagnosticsWatcher()
    try:
        rec = start_recorder(out, 'rec_c', topics=['state', 'sprung_accel', '/clock'])
        stats = replay(recorded, '--rate', '4', '--topics', '/erva/state', '--clock', '50',
                       '--wait-for-subscribers', '60')
        stop(rec, watcher, {**stats['published'], '/clock': stats['clock_ticks']}, 'rec_c')
    finally:
        watcher.close()
    assert stats['acknowledged'] and not stats['stopped']
    got = by_topic(out)
    original = by_topic(recorded)
    assert set(got) == {'/erva/state', '/clock'}          # only the chosen topic (+ clock)
    assert [d for _, _, d in got['/erva/state']] == [d for _, _, d in original['/erva/state']]
    check_timing(original, {'/erva/state': got['/erva/state']}, stats, rate=4.0)
    # /clock carries the playback (bag) time, one tick per 1/50 s of wall time from the
    # start until the last message was out (ticks fallen due meanwhile go out at once).
    clocks = np.array([msg.clock.sec * 10**9 + msg.clock.nanosec
                       for _, msg in decoded(open_bag(out), ['/clock'])], dtype=np.int64)
    states = original['/erva/state']
    bag_start, span_ns = states[0][0], states[-1][0] - states[0][0]
    last_scheduled_s = span_ns * 1e-9 / 4
    assert stats['clock_ticks'] == len(clocks) >= int(50 * last_scheduled_s) + 1
    assert np.all(np.diff(clocks) > 0)
    late_ns = stats['lateness_ms']['max'] * 1e6
    assert bag_start <= clocks[0] and clocks[-1] <= bag_start + span_ns + 4 * late_ns + 1e6
