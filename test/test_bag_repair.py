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


def _crashed(tmp_path):
    bag = str(tmp_path / 'crashed')
    proc = subprocess.run([sys.executable, '-c', CRASHER, bag], capture_output=True)
    assert proc.returncode == -9
    return bag


def _snapshot(bag):
    return {name: open(os.path.join(bag, name), 'rb').read() for name in os.listdir(bag)}


def test_repair_out_writes_the_bag_elsewhere_and_leaves_the_original(tmp_path, erva):
    bag = _crashed(tmp_path)
    before = _snapshot(bag)
    out = tmp_path / 'repaired'
    proc = erva('bag', 'repair', bag, '--out', out, check=True)
    assert f'{out}: rewrote the MCAP file' in proc.stdout and '.orig' not in proc.stdout
    assert _snapshot(bag) == before                      # not touched
    assert sorted(os.listdir(out)) == ['crashed_0.mcap', 'metadata.yaml']
    with Reader(str(out)) as reader:                     # a reader we did not write
        assert reader.message_count == len(list(reader.messages())) == 500
    assert open_bag(str(out)).session['scenario'] == 'crash'
    # A complete bag is copied with its metadata.yaml.
    again = tmp_path / 'again'
    assert 'copied the MCAP file' in erva('bag', 'repair', out, '--out', again,
                                          check=True).stdout
    assert open_bag(str(again)).message_count == 500


def test_a_full_disk_is_one_line_and_out_gets_around_it(tmp_path, erva):
    # The repaired file goes where a full disk is: /dev/full answers every write ENOSPC.
    bag = _crashed(tmp_path)
    before = _snapshot(bag)
    os.symlink('/dev/full', os.path.join(bag, 'crashed_0.mcap.repair'))
    proc = erva('bag', 'repair', bag)
    assert proc.returncode == 1 and proc.stdout == ''
    assert proc.stderr.splitlines() == [
        f'erva bag: error: cannot write the repaired bag in {bag}: No space left on device; '
        'give --out DIR on another disk'], proc.stderr
    assert _snapshot(bag) == before                      # nothing lost, nothing left over
    out = tmp_path / 'elsewhere'
    assert 'recovered 500 messages' in erva('bag', 'repair', bag, '--out', out,
                                            check=True).stdout


def test_repair_out_refuses_the_bag_itself_and_a_full_directory(tmp_path, erva):
    bag = _crashed(tmp_path)
    busy = tmp_path / 'busy'
    busy.mkdir()
    (busy / 'x').write_text('x')
    for out, message in ((bag, 'that is the bag itself'),
                         (busy, 'exists and is not an empty directory')):
        proc = erva('bag', 'repair', bag, '--out', out)
        assert proc.returncode == 2 and len(proc.stderr.splitlines()) == 1, proc.stderr
        assert message in proc.stderr
    proc = erva('bag', 'repair', bag, '--out', tmp_path / 'o', '--no-backup')
    assert proc.returncode == 2 and '--no-backup applies to a repair in place' in proc.stderr
