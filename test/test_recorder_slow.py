"""Nothing lost: every message published at the live rates for 60 s is in the bag."""

import json
import signal
import subprocess
import sys

from conftest import REPO, ros_env
import pytest
from recorder_helpers import DiagnosticsWatcher, wait_recorded
from rosbags.rosbag2 import Reader

from erva_ros.core.bag.session import recorder_ros_args

DURATION_S = 62.0


@pytest.mark.slow
@pytest.mark.ros
def test_counts_in_the_bag_equal_counts_published_over_a_minute(tmp_path):
    bag = str(tmp_path / 'minute')
    watcher = DiagnosticsWatcher()
    rec = subprocess.Popen([sys.executable, '-m', 'erva_ros.nodes.recorder_node',
                            *recorder_ros_args(bag, {'scenario': 'nothing-lost'},
                                               parameters={'diagnostics_period_s': 0.2})],
                           env=ros_env(), cwd=REPO, text=True, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE)
    try:
        # All eight contract topics at their live rates (six /erva topics and /clock at
        # 50 Hz, /diagnostics from three nodes at 1 Hz), from a separate process.
        pub = subprocess.run([sys.executable, '-m', 'erva_ros.ros.traffic', 'contract',
                              '--duration', str(DURATION_S), '--rate', '50',
                              '--ack-timeout', '60', '--wait', '120'],
                             env=ros_env(), cwd=REPO, capture_output=True, text=True,
                             timeout=DURATION_S + 600)
        assert pub.returncode == 0, pub.stderr
        published = json.loads(pub.stdout.strip().splitlines()[-1])
        # Stopped once it says it wrote all of it, as erva run does.
        wait_recorded(watcher, published['published'])
    finally:
        watcher.close()
        rec.send_signal(signal.SIGINT)
        try:
            _, err = rec.communicate(timeout=60)
        finally:
            if rec.poll() is None:
                rec.kill()
    assert rec.returncode == 0, err
    assert published['acked'] and len(published['published']) == 8
    assert published['published']['/erva/state'] == int(DURATION_S * 50)
    with Reader(bag) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        own = sum(1 for c, _, raw in reader.messages()
                  if c.topic == '/diagnostics' and b'recorder: bag recorder' in raw)
    for topic, n in published['published'].items():
        assert counts[topic] == n + (own if topic == '/diagnostics' else 0), topic
