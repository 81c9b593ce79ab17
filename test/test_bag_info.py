"""``erva bag info`` and the reader; corrupt, truncated and non-bag inputs to every command."""

import json
import os
import shutil

import pytest
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from erva_ros.core.bag.reader import open_bag

from erva_ros.ros.bag_messages import write_message
from erva_ros.core.bag.writer import BagWriter

T0 = 1_800_000_000 * 10 ** 9


def _write(bag_dir, n=400, flush_every=None):
    """Write n states and n clocks (chunks of ~50 messages); return the writer."""
    w = BagWriter(bag_dir, chunk_size=4096, session={'scenario': 'info-test',
                                                     'parameters': json.dumps({'M_s': 250})})
    w.add_topic('/erva/state', 'sensor_msgs/msg/JointState')
    w.add_topic('/clock', 'rosgraph_msgs/msg/Clock')
    for k in range(n):
        t = T0 + k * 20_000_000
        write_message(w, '/erva/state', JointState(name=['z_s'], position=[k * 1.0]), t)
        write_message(w, '/clock', Clock(), t + 1)
    return w


@pytest.fixture
def good_bag(tmp_path):
    path = str(tmp_path / 'good')
    _write(path).close()
    return path


def test_info_lists_topics_counts_duration_and_session(erva, good_bag):
    proc = erva('bag', 'info', good_bag, check=True)
    out = proc.stdout
    assert 'Topic: /erva/state | Type: sensor_msgs/msg/JointState | Count: 400' in out
    assert 'Duration:          7.980000001s' in out
    assert 'scenario: info-test' in out and 'parameters: {"M_s": 250}' in out
    info = json.loads(erva('bag', 'info', good_bag, '--json', check=True).stdout)
    assert info['message_count'] == 800 and info['complete'] and info['metadata_yaml']
    assert {t['name']: t['count'] for t in info['topics']} == {'/clock': 400,
                                                               '/erva/state': 400}
    assert info['topics'][1]['rate_hz'] == pytest.approx(50.0, rel=1e-6)
    assert info['session']['scenario'] == 'info-test' and info['warnings'] == []
    # The .mcap file alone opens too.
    assert open_bag(os.path.join(good_bag, 'good_0.mcap')).message_count == 800


def test_info_prints_times_and_options_as_ros2_bag_info(erva, good_bag, tmp_path):
    """rosbag2 Jazzy's format_bag_meta_data: local time with 9 decimals, then seconds."""
    out = erva('bag', 'info', good_bag, env={'TZ': 'UTC'}, check=True).stdout
    # T0 = 1.8e9 s is 2027-01-15 08:00:00 UTC; the last message 7.98 s + 1 ns later.
    assert 'Start:             Jan 15 2027 08:00:00.000000000 (1800000000.000000000)\n' in out
    assert 'End:               Jan 15 2027 08:00:07.980000001 (1800000007.980000001)\n' in out
    assert 'ROS Distro:        jazzy\n' in out and 'Service:           0\n' in out
    later = erva('bag', 'info', good_bag, env={'TZ': 'Asia/Tokyo'}, check=True).stdout
    assert 'Start:             Jan 15 2027 17:00:00.000000000 (1800000000.000000000)' in later
    assert erva('bag', 'info', '-t', good_bag, check=True).stdout.split() == [
        '/clock', '/erva/state']
    verbose = erva('bag', 'info', '-v', '-s', 'mcap', good_bag, check=True).stdout
    assert 'Service information: ' in verbose and 'scenario: info-test' in verbose
    empty = str(tmp_path / 'empty')
    BagWriter(empty).close()
    out = erva('bag', 'info', empty, check=True).stdout
    for key in ('Duration', 'Start', 'End'):
        assert f'{key + ":":<19}unknown\n' in out, out


def test_a_torn_file_is_read_up_to_its_last_chunk(tmp_path):
    path = str(tmp_path / 'torn')
    w = _write(path)
    w.flush()
    flushed = w.message_count
    write_message(w, '/clock', Clock(), T0 + 10 ** 12)   # in the open chunk: lost
    w.abort()
    with open(w.file_path, 'ab') as fh:
        fh.write(b'\x06' + b'\xff' * 20)  # a record torn mid-write
    bag = open_bag(path)
    assert not bag.complete and bag.message_count == flushed
    assert [m.data for m in bag.messages(['/erva/state'])][-1] == \
        [m.data for m in open_bag(path).messages(['/erva/state'])][-1]
    assert any('erva bag repair' in w for w in bag.warnings())


def _cases(tmp_path, good_bag):
    """Yield (name, path) of inputs that are not readable bags."""
    d = tmp_path / 'cases'
    d.mkdir(parents=True)
    yield 'missing', str(d / 'nope')
    (d / 'empty').mkdir()
    yield 'empty directory', str(d / 'empty')
    (d / 'text.txt').write_text('hello, I am not a bag\n')
    yield 'text file', str(d / 'text.txt')
    (d / 'empty.mcap').write_bytes(b'')
    yield 'empty mcap', str(d / 'empty.mcap')
    (d / 'random.mcap').write_bytes(os.urandom(5000))
    yield 'random bytes', str(d / 'random.mcap')
    (d / 'magic.mcap').write_bytes(b'\x89MCAP0\r\n' + os.urandom(3000))
    yield 'magic then garbage', str(d / 'magic.mcap')
    for name, text in [('yaml garbage', 'rosbag2_bagfile_information: [\n  : :'),
                       ('wrong yaml', 'just: a mapping\n'),
                       ('sqlite3', 'rosbag2_bagfile_information:\n  version: 9\n'
                                   '  storage_identifier: sqlite3\n'
                                   '  relative_file_paths: [x_0.db3]\n'),
                       ('future version', 'rosbag2_bagfile_information:\n  version: 10\n')]:
        bag = d / name.replace(' ', '_')
        shutil.copytree(good_bag, bag)
        (bag / 'metadata.yaml').write_text(text)
        yield name, str(bag)
    bag = d / 'missing_file'
    shutil.copytree(good_bag, bag)
    os.remove(bag / 'good_0.mcap')
    yield 'metadata names a missing file', str(bag)


def _erva_here(capsys, *args):
    """Run ``erva ARGS`` in this process (the main() `python -m erva_ros.cli` runs)."""
    from erva_ros.cli import main
    capsys.readouterr()
    code = main([str(a) for a in args])
    return code, capsys.readouterr().err


@pytest.mark.parametrize('command', [['bag', 'info'], ['report'], ['replay']])
def test_bad_inputs_give_one_line_not_a_traceback(erva, capsys, tmp_path, good_bag, command):
    # The first case as a user runs it (its own process), the others through the same
    # main() in this process: a second of Python start-up each saved, same one line.
    cases = list(_cases(tmp_path / command[0], good_bag))
    proc = erva(*command, cases[0][1])
    results = [(cases[0][0], proc.returncode, proc.stderr)]
    results += [(name, *_erva_here(capsys, *command, path)) for name, path in cases[1:]]
    for name, code, err in results:
        lines = err.strip().splitlines()
        assert code == 2, (name, err)
        assert len(lines) == 1 and 'Traceback' not in err, (name, err)
        assert lines[0].startswith(f'erva {command[0]}: error: '), (name, lines)


def test_damaged_chunk_with_intact_summary_is_one_line(erva, tmp_path, good_bag):
    path = os.path.join(good_bag, 'good_0.mcap')
    data = bytearray(open(path, 'rb').read())
    middle = len(data) // 3
    data[middle:middle + 64] = os.urandom(64)
    open(path, 'wb').write(bytes(data))
    for command in (['report', good_bag], ['bag', 'info', good_bag]):
        proc = erva(*command)
        assert proc.returncode in (0, 2), proc.stderr
        assert 'Traceback' not in proc.stderr and len(proc.stderr.strip().splitlines()) <= 1


@pytest.mark.ros
@pytest.mark.parametrize('command', [['bag', 'info'], ['report'], ['replay', '--rate', '50'],
                                     ['bag', 'play', '--rate', '50'], ['identify'],
                                     ['map', 'build', '--out', 'MAP']])
def test_every_reader_warns_about_a_truncated_bag(erva, good_bag, tmp_path, command):
    """A bag cut at 60 % of its file: each command that reads it says so (one home)."""
    path = os.path.join(good_bag, 'good_0.mcap')
    with open(path, 'r+b') as fh:
        fh.truncate(os.path.getsize(path) * 6 // 10)
    args = [str(tmp_path / 'map.db') if a == 'MAP' else a for a in command]
    proc = erva(*args[:2], good_bag, *args[2:]) if command[0] in ('bag', 'map') else \
        erva(args[0], good_bag, *args[1:])
    out = proc.stdout + proc.stderr
    assert 'not closed properly' in out and 'erva bag repair' in out, out
    if command[0] in ('replay', 'bag') and command[-1] == '50':
        assert proc.returncode == 0 and 'warning: the file was not closed' in proc.stderr
