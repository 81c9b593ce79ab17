"""``erva bag repair``: a bag cut anywhere becomes complete, indexed and playable again."""

import os
import shutil
import subprocess
import sys

from mcap.reader import make_reader
from rosbags.rosbag2 import Reader
from sensor_msgs.msg import JointState

from erva_ros.core.bag.reader import open_bag

from erva_ros.ros.bag_messages import write_message
from erva_ros.core.bag.repair import repair_bag
from erva_ros.core.bag.writer import BagWriter

T0 = 1_800_000_000 * 10 ** 9

# A child that writes a bag, flushes every 50 messages, then kills itself (SIGKILL).
CRASHER = r'''
import os, signal, sys
from sensor_msgs.msg import JointState
from erva_ros.core.bag.writer import BagWriter
from erva_ros.ros.bag_messages import write_message
w = BagWriter(sys.argv[1], session={'scenario': 'crash'}, flush_period_s=1e9)
w.add_topic('/erva/state', 'sensor_msgs/msg/JointState')
for k in range(530):
    write_message(w, '/erva/state', JointState(position=[float(k)]), %d + k * 20000000)
    if (k + 1) %% 50 == 0:
        w.flush()
os.kill(os.getpid(), signal.SIGKILL)
''' % T0


def test_sigkilled_writer_is_repaired_up_to_its_last_flush(tmp_path, erva):
    bag = str(tmp_path / 'crashed')
    proc = subprocess.run([sys.executable, '-c', CRASHER, bag], capture_output=True)
    assert proc.returncode == -9
    assert not os.path.exists(os.path.join(bag, 'metadata.yaml'))
    assert open_bag(bag).message_count == 500           # readable before the repair
    out = erva('bag', 'repair', bag, check=True).stdout
    assert 'recovered 500 messages on 1 topics' in out and 'crashed_0.mcap.orig' in out
    with Reader(bag) as reader:                          # metadata.yaml + indexed file
        positions = [m for _, _, m in reader.messages()]
        assert reader.message_count == len(positions) == 500
    with open(os.path.join(bag, 'crashed_0.mcap'), 'rb') as fh:
        summary = make_reader(fh).get_summary()
        assert summary.statistics.message_count == 500 and summary.chunk_indexes
    bag_read = open_bag(bag)
    assert bag_read.complete and bag_read.session['scenario'] == 'crash'
    assert bag_read.warnings() == []
    # Repairing a complete bag only rewrites metadata.yaml.
    assert 'was complete' in erva('bag', 'repair', bag, check=True).stdout


def test_any_cut_recovers_a_prefix(tmp_path):
    src = str(tmp_path / 'src')
    w = BagWriter(src, chunk_size=2048, session={'scenario': 'cut'})
    w.add_topic('/erva/state', 'sensor_msgs/msg/JointState')
    for k in range(300):
        write_message(w, '/erva/state', JointState(position=[float(k)]), T0 + k)
    w.close()
    path = os.path.join(src, 'src_0.mcap')
    data = open(path, 'rb').read()
    seen = set()
    for cut in range(200, len(data), max(1, len(data) // 60)):
        bag = tmp_path / f'cut{cut}'
        bag.mkdir()
        (bag / f'cut{cut}_0.mcap').write_bytes(data[:cut])
        result = repair_bag(str(bag), keep_original=False)
        recovered = [m.data for m in open_bag(str(bag)).messages()]
        n = result['messages']
        assert len(recovered) == n <= 300
        originals = [m.data for m in open_bag(src).messages()]
        assert recovered == originals[:n]     # a prefix, in order, nothing invented
        seen.add(n)
        shutil.rmtree(bag)
    assert len(seen) > 5 and max(seen) >= 250   # cuts land in different chunks
