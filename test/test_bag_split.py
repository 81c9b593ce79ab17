"""Split bags: <bag>_0.mcap, <bag>_1.mcap, ... as rosbag2 writes them, read back as one bag.

Every file is checked with readers we did not write: the ``mcap`` package (each file
complete, with its summary) and ``rosbags`` (the bag through metadata.yaml).
"""

import gc
import json
import os
import shutil
import tracemalloc

from mcap.reader import make_reader
import numpy as np
import pytest
from rosbags.rosbag2 import Reader
import yaml

from erva_ros.core.bag import BagError
from erva_ros.core.bag.metadata import read_metadata
from erva_ros.core.bag.reader import open_bag
from erva_ros.core.bag.repair import repair_bag
from erva_ros.core.bag.writer import BagWriter

T0 = 1_800_000_000 * 10 ** 9
MS = 1_000_000
STATE, ACCEL = '/erva/state', '/erva/sprung_accel'


def _files(bag):
    """Return the bag's .mcap file names, by number."""
    names = [f for f in os.listdir(bag) if f.endswith('.mcap')]
    return sorted(names, key=lambda n: int(n.rsplit('_', 1)[1][:-len('.mcap')]))


def _read(path):
    """Return one file as the mcap package reads it: summary, messages, metadata records."""
    with open(path, 'rb') as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        messages = [(ch.topic, m.log_time, bytes(m.data))
                    for _, ch, m in reader.iter_messages(log_time_order=True)]
        records = {r.name: dict(r.metadata) for r in reader.iter_metadata()}
    return summary, messages, records


def _write(bag, n=1000, step_ns=10 * MS, close=True, **kw):
    """Write ``n`` messages, every ``step_ns``, alternating two topics; return them."""
    w = BagWriter(bag, session={'scenario': 'split'}, custom_data={'scenario': 'split'},
                  flush_period_s=1e9, **kw)
    w.add_topic(STATE, 'sensor_msgs/msg/JointState')
    w.add_topic(ACCEL, 'geometry_msgs/msg/AccelStamped')
    sent = []
    for k in range(n):
        topic = STATE if k % 2 == 0 else ACCEL
        data = k.to_bytes(4, 'little') * 16
        w.write(topic, data, T0 + k * step_ns)
        sent.append((topic, T0 + k * step_ns, data))
        if k % 20 == 19:
            w.flush()
    if close:
        w.close()
    return w, sent


def test_split_by_duration_as_rosbag2(tmp_path):
    bag = str(tmp_path / 'b')
    w, sent = _write(bag, max_bag_duration_s=2.0)
    names = _files(bag)
    # rosbag2's rule: a message more than 2 s after the file's first starts the next file.
    assert names == [f'b_{i}.mcap' for i in range(5)] and w.file_count == 5
    meta = read_metadata(bag)
    assert meta['relative_file_paths'] == names
    assert [f['path'] for f in meta['files']] == names
    got, firsts = [], []
    for i, name in enumerate(names):
        summary, messages, records = _read(os.path.join(bag, name))
        assert summary is not None and summary.chunk_indexes      # complete, indexed
        assert {c.topic for c in summary.channels.values()} == {STATE, ACCEL}
        assert records['erva_session'] == {'scenario': 'split'}   # each file describes itself
        own = yaml.safe_load(records['rosbag2']['serialized_metadata'])
        assert own['relative_file_paths'] == names[:i + 1]        # the bag up to this file
        entry = meta['files'][i]
        stats = summary.statistics
        assert entry['message_count'] == stats.message_count == len(messages)
        assert entry['starting_time']['nanoseconds_since_epoch'] == stats.message_start_time
        assert entry['duration']['nanoseconds'] == \
            stats.message_end_time - stats.message_start_time <= 2 * 10 ** 9
        firsts.append(messages[0][1])
        got += messages
    assert all(b - a > 2 * 10 ** 9 for a, b in zip(firsts, firsts[1:]))
    assert got == sent                                  # every message once, in order
    assert meta['message_count'] == sum(f['message_count'] for f in meta['files']) == 1000
    assert meta['starting_time']['nanoseconds_since_epoch'] == T0
    assert meta['duration']['nanoseconds'] == 999 * 10 * MS
    with Reader(bag) as reader:                          # the bag as rosbag2 tools see it
        assert [(c.topic, t, bytes(d)) for c, t, d in reader.messages()] == sent
    back = open_bag(bag)
    assert back.complete and back.warnings() == [] and len(back.files) == 5
    assert back.message_count == 1000 and back.topics[STATE].count == 500
    assert [(m.topic, m.log_time_ns, m.data) for m in back.messages()] == sent
    assert [m.log_time_ns for m in back.messages([ACCEL])] == [t for tp, t, _ in sent
                                                               if tp == ACCEL]
    assert w.bytes_written == sum(os.path.getsize(os.path.join(bag, n)) for n in names)


def test_split_by_size(tmp_path):
    bag = str(tmp_path / 's')
    limit = 16 * 1024
    _, sent = _write(bag, n=2000, chunk_size=4096, max_bag_size_bytes=limit)
    names = _files(bag)
    assert len(names) >= 5
    sizes = [os.path.getsize(os.path.join(bag, n)) for n in names]
    assert all(limit <= s < 2 * limit for s in sizes[:-1]), sizes
    assert sum(len(_read(os.path.join(bag, n))[1]) for n in names) == 2000
    assert [(m.topic, m.log_time_ns, m.data) for m in open_bag(bag).messages()] == sent
    with pytest.raises(BagError, match='below 1024 B'):
        BagWriter(str(tmp_path / 'tiny'), max_bag_size_bytes=100)


def test_metadata_lists_the_finished_files_while_recording(tmp_path):
    bag = str(tmp_path / 'live')
    w, sent = _write(bag, n=450, close=False, max_bag_duration_s=2.0)   # 4.5 s: in file 2
    assert _files(bag) == ['live_0.mcap', 'live_1.mcap', 'live_2.mcap']
    meta = read_metadata(bag)
    assert meta['relative_file_paths'] == ['live_0.mcap', 'live_1.mcap']
    assert meta['message_count'] == 402 == sum(f['message_count'] for f in meta['files'])
    with Reader(bag) as reader:               # rosbag2 tools read the finished files
        assert [(c.topic, t, bytes(d)) for c, t, d in reader.messages()] == sent[:402]
    w.close()
    assert read_metadata(bag)['message_count'] == 450


def test_killed_in_the_second_file_is_repaired_with_every_flushed_message(tmp_path, erva):
    bag = str(tmp_path / 'rec')
    w, sent = _write(bag, n=320, close=False, max_bag_duration_s=2.0)   # 3.2 s: in file 1
    w.flush()
    for k in range(320, 330):                 # in the open chunk: lost by the "crash"
        w.write(STATE, b'lost', T0 + k * 10 * MS)
    crashed = str(tmp_path / 'crashed')
    shutil.copytree(bag, crashed)             # the directory as a SIGKILL leaves it
    assert read_metadata(crashed)['relative_file_paths'] == ['rec_0.mcap']   # at the split
    w.abort()

    before = open_bag(crashed)
    assert not before.complete and before.message_count == 320
    assert [f.complete for f in before.files] == [True, False]
    assert any('does not list rec_1.mcap' in w for w in before.warnings())
    assert [(m.topic, m.log_time_ns, m.data) for m in before.messages()] == sent

    out = erva('bag', 'repair', crashed, check=True).stdout
    assert 'rewrote rec_1.mcap' in out and 'recovered 320 messages on 2 topics' in out
    assert 'rec_1.mcap.orig' in out and 'rec_0.mcap.orig' not in out
    meta = read_metadata(crashed)
    assert meta['relative_file_paths'] == ['rec_0.mcap', 'rec_1.mcap']
    assert [f['message_count'] for f in meta['files']] == [201, 119]
    for name in meta['relative_file_paths']:
        summary, _, records = _read(os.path.join(crashed, name))
        assert summary is not None and records['erva_session'] == {'scenario': 'split'}
    with Reader(crashed) as reader:
        assert [(c.topic, t, bytes(d)) for c, t, d in reader.messages()] == sent
    after = open_bag(crashed)
    assert after.complete and after.warnings() == [] and after.message_count == 320
    assert 'were complete' in erva('bag', 'repair', crashed, check=True).stdout


def test_a_split_bag_without_metadata_yaml_is_read_and_repaired(tmp_path):
    bag = str(tmp_path / 'nometa')
    _, sent = _write(bag, n=500, max_bag_duration_s=1.0)
    os.remove(os.path.join(bag, 'metadata.yaml'))
    back = open_bag(bag)
    assert len(back.files) == 5 and back.message_count == 500
    assert back.warnings() == ['metadata.yaml is missing (ros2 bag play needs it): '
                               'run "erva bag repair"']
    assert [(m.topic, m.log_time_ns, m.data) for m in back.messages()] == sent
    result = repair_bag(bag)
    assert result['was_complete'] and result['messages'] == 500
    assert read_metadata(bag)['relative_file_paths'] == [f'nometa_{i}.mcap' for i in range(5)]
    # .mcap files of no one numbering are not taken for one bag.
    shutil.copy(os.path.join(bag, 'nometa_0.mcap'), os.path.join(bag, 'other.mcap'))
    os.remove(os.path.join(bag, 'metadata.yaml'))
    with pytest.raises(BagError, match='not the <bag>_<i>.mcap files of one bag'):
        open_bag(bag)


def test_messages_received_out_of_order_around_a_split_are_merged(tmp_path):
    bag = str(tmp_path / 'late')
    w = BagWriter(bag, max_bag_duration_s=1.0)
    w.add_topic(STATE, 'sensor_msgs/msg/JointState')
    times = [0, 500, 1000, 1200, 900, 1500]          # 900 ms arrives after the split
    for t in times:
        w.write(STATE, t.to_bytes(4, 'little'), T0 + t * MS)
    w.close()
    assert [len(_read(os.path.join(bag, n))[1]) for n in _files(bag)] == [3, 3]
    assert [m.log_time_ns for m in open_bag(bag).messages()] == \
        [T0 + t * MS for t in sorted(times)]


def _flushes(w, n, topics, k0=0):
    """Write ``n`` chunks of one message per topic, 0.1 s of log time apart, each flushed."""
    for k in range(k0, k0 + n):
        for i, topic in enumerate(topics):
            w.write(topic, b'x' * 64, T0 + k * 100 * MS + i)
        w.flush()


def _index_memory(tmp_path, name, max_bag_duration_s, n=2000):
    """Return the bytes a writer of 8 topics holds after ``n`` more flushes (tracemalloc)."""
    topics = [f'/erva/t{i}' for i in range(8)]
    w = BagWriter(str(tmp_path / name), max_bag_duration_s=max_bag_duration_s)
    for t in topics:
        w.add_topic(t, 'sensor_msgs/msg/JointState')
    _flushes(w, 200, topics)                   # past the first files
    gc.collect()
    tracemalloc.start()
    try:
        _flushes(w, n, topics, 200)
        gc.collect()
        held, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    w.close()
    return held, peak


def test_splitting_bounds_the_writers_memory(tmp_path):
    # One chunk index per flush (~1 KB with 8 channels) stays until its file is finished.
    one_file, _ = _index_memory(tmp_path, 'one', 0.0)
    split, split_peak = _index_memory(tmp_path, 'split', 10.0)    # 100 flushes per file
    assert one_file > 1_500_000                # 2000 flushes: the growth of issue 23
    assert split < 150_000 and split_peak < 250_000, (split, split_peak)


def _resplit(src, dest, seconds):
    """Copy the bag ``src`` into ``dest`` split every ``seconds`` (erva's reader and writer)."""
    bag = open_bag(src)
    custom = (bag.metadata_yaml or {}).get('custom_data') or {}
    with BagWriter(dest, session=bag.session, custom_data=custom,
                   max_bag_duration_s=seconds) as w:
        for t in bag.topics.values():
            w.add_topic(t.name, t.type, t.offered_qos, t.type_hash)
        for m in bag.messages():
            w.write(m.topic, m.data, m.log_time_ns, m.publish_time_ns, m.sequence)
    assert len(_files(dest)) > 2
    return dest


def _same(a, b, path=()):
    """Assert two nested results are equal (floats and arrays exactly), bags' paths aside."""
    if isinstance(a, dict):
        assert set(a) == set(b), path
        for k in a:
            if k not in ('path', 'name', 'source', 'bag', 'file', 'files'):
                _same(a[k], b[k], path + (k,))
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, path + (i,))
    elif isinstance(a, np.ndarray):
        assert np.array_equal(a, b, equal_nan=True), path
    elif isinstance(a, float) and np.isnan(a):
        assert isinstance(b, float) and np.isnan(b), path
    else:
        assert a == b, (path, a, b)


def test_report_identify_and_map_read_a_split_bag_as_the_whole(tmp_path, repo_root, erva):
    from dataclasses import asdict

    import road_helpers as rh

    from erva_ros.core.identify.bag import load_recording
    from erva_ros.core.roadmap.bag_drive import read_bag_drive
    from erva_ros.session.bag.bag_report import compute_report, load_session
    from erva_ros.session.run.report import jsonable

    sample = os.path.join(repo_root, 'bags', 'sample')        # a full-state session, 4 s
    split = _resplit(sample, str(tmp_path / 'sample'), 0.5)

    def report(path):
        return jsonable(compute_report(load_session(open_bag(path))))
    _same(report(sample), report(split))
    _same(asdict(load_recording(sample)), asdict(load_recording(split)))
    proc = erva('report', split, '--json', check=True)
    assert json.loads(proc.stdout)['samples'] == report(sample)['samples']
    info = erva('bag', 'info', split, check=True).stdout
    assert 'Files:             8 files\n' in info and 'sample_7.mcap  (' in info

    drive = rh.write_bag(str(tmp_path / 'drive'), rh.drive(rh.route(0), 10))
    split_drive = _resplit(drive, str(tmp_path / 'split_drive'), 1.0)
    _same(asdict(read_bag_drive(drive)), asdict(read_bag_drive(split_drive)))


@pytest.mark.ros
def test_erva_run_splits_its_bag_and_every_message_is_in_one_file(tmp_path, erva):
    run = erva('run', '--mode', 'lockstep', '--duration', '4', '--max-bag-duration', '1',
               '--record', tmp_path, '--json', timeout=400)
    assert run.returncode == 0, run.stdout + run.stderr
    summary = json.loads(run.stdout)
    [bag] = [os.path.join(tmp_path, d) for d in os.listdir(tmp_path)]
    names = _files(bag)
    assert len(names) >= 4, names                      # 4 s of sim time, 1 s per file
    meta = read_metadata(bag)
    assert meta['relative_file_paths'] == names
    counts, per_file = {}, []
    for name in names:                                 # the mcap package, file by file
        summary_n, messages, records = _read(os.path.join(bag, name))
        assert summary_n is not None and records['erva_session']['max_bag_duration_s'] == '1.0'
        per_file.append(len(messages))
        for topic, _, _ in messages:
            counts[topic] = counts.get(topic, 0) + 1
    assert per_file == [f['message_count'] for f in meta['files']]
    rec = summary['recording']
    assert rec['lost'] == 0 and rec['lost_in_transport'] == 0, rec
    for topic, c in rec['topics'].items():
        assert counts[topic] == c['recorded'] + c['foreign'] == c['published'], (topic, c)
    # Replayed as one session: a fresh controller reproduces every recorded command.
    again = erva('replay', bag, '--reevaluate', '--json', timeout=400)
    result = json.loads(again.stdout)
    assert again.returncode == 0 and result['identical'], result
    assert result['commands'] == counts['/erva/damping_cmd']
    report = json.loads(erva('report', bag, '--json', check=True).stdout)
    assert report['samples']['sprung_accel'] == counts['/erva/sprung_accel']


def test_split_options_are_checked_before_anything_starts(erva):
    for args, expected in ((('--max-bag-size', '100'), "'100': 0 (no limit) or at least 1024"),
                           (('--max-bag-duration', '-1'), "'-1' is not a number in [0,")):
        proc = erva('run', *args)
        assert proc.returncode == 2 and expected in proc.stderr, proc.stderr
        assert len(proc.stderr.strip().splitlines()[-1]) < 200
