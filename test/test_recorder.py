"""recorder_node over real DDS: what it records, how it stops, crashes and fails."""

import io
import json
import os
import resource
import signal
import socket
import subprocess
import sys
import time

from conftest import REPO, ros_env
import pytest
from recorder_helpers import DiagnosticsWatcher, wait_recorded
from rosbags.rosbag2 import Reader
from rosbags.typesys import get_typestore, Stores

from erva_ros.core import topics as contract

from ros_msgs import decoded
from erva_ros.core.bag.reader import open_bag
from erva_ros.core.bag.schemas import type_description_hash
from erva_ros.core.bag.session import recorder_ros_args

pytestmark = pytest.mark.ros
STORE = get_typestore(Stores.ROS2_JAZZY)
STARTED = []   # processes started by a test, killed if a failing test left them running


@pytest.fixture(autouse=True)
def no_stray_processes():
    yield
    while STARTED:
        proc = STARTED.pop()
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def start_recorder(bag_dir, metadata=None, params=(), node_name=None, preexec_fn=None):
    args = recorder_ros_args(bag_dir, metadata, node_name=node_name)
    for p in params:
        args += ['-p', p]
    proc = subprocess.Popen([sys.executable, '-m', 'erva_ros.nodes.recorder_node', *args],
                            env=ros_env(), cwd=REPO, text=True, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, preexec_fn=preexec_fn)
    STARTED.append(proc)
    return proc


def wait_for(path, proc, timeout=60.0):   # generous: Python starts slowly on a busy machine
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if os.path.exists(path):
            return
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    raise AssertionError(f'{path} did not appear')


def stop(proc, sig=signal.SIGINT, timeout=60):
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, err


def traffic(*args, timeout=600):
    """Run the contract traffic publisher; return its JSON result."""
    proc = subprocess.run([sys.executable, '-m', 'erva_ros.ros.traffic', 'contract', *args],
                          env=ros_env(), cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_records_the_contract_and_sigint_finishes_the_file(tmp_path):
    bag = str(tmp_path / 'session')
    meta = {'scenario': 'unit', 'controller': 'echo', 'seed': 3,
            'parameters': {'M_s': 250.0}}
    before_ns = time.time_ns()
    watcher = DiagnosticsWatcher()
    try:
        rec = start_recorder(bag, meta, params=['diagnostics_period_s:=0.2'])
        wait_for(bag, rec)
        result = traffic('--duration', '3', '--ack-timeout', '60')
        assert result['acked']
        # Stopped once it says it wrote all that, as erva run does (a busy machine may
        # keep it seconds behind the publisher).
        wait_recorded(watcher, result['published'])
        rc, err = stop(rec)
    finally:
        watcher.close()
    after_ns = time.time_ns()
    assert rc == 0, err
    published = result['published']
    with Reader(bag) as reader:   # rosbags validates metadata.yaml
        counts = {c.topic: c.msgcount for c in reader.connections}
        own_status = 0
        times = {}
        for conn, log_time, raw in reader.messages():
            msg = STORE.deserialize_cdr(raw, conn.msgtype)
            if conn.topic == '/diagnostics' and msg.status[0].name.endswith(': bag recorder'):
                own_status += 1
            times.setdefault(conn.topic, []).append(log_time)
    for topic, n in published.items():
        extra = own_status if topic == '/diagnostics' else 0
        assert counts[topic] == n + extra, (topic, counts[topic], n)
    assert own_status >= 2

    info = open_bag(bag)
    for topic in published:
        t = info.topics[topic]
        assert t.type == contract.TOPIC_TYPES[topic]
        assert t.type_hash == type_description_hash(t.type)
        assert t.offered_qos and t.offered_qos[0]['reliability'] == 'reliable'
        assert t.offered_qos[0]['durability'] == 'volatile'
    s = info.session
    assert (s['scenario'], s['controller'], s['seed']) == ('unit', 'echo', '3')
    assert json.loads(s['parameters']) == {'M_s': 250.0}
    assert s['host'] == socket.gethostname() and s['start_time'].endswith('Z')
    assert s['erva_ros_version'] and 'git_commit' in s
    # Both times kept: publish (source) time before log (receive) time, both on the system
    # clock of this test's run (another clock -- steady, simulated -- would be far off).
    seqs = []
    for m, msg in decoded(info, ['/erva/state']):
        stamp = msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec
        assert before_ns <= stamp <= m.publish_time_ns <= m.log_time_ns <= after_ns
        seqs.append(m.sequence)
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))   # no gap: nothing lost


def _written(watcher, name):
    """Return the newest ``written`` count the recorder ``name`` reported (0 before any)."""
    return max([int(v.get('written', 0)) for v in watcher.values(f'{name}: bag recorder')],
               default=0)


def test_sigterm_finishes_the_file(tmp_path):
    watcher = DiagnosticsWatcher()
    try:
        bag = str(tmp_path / 'term')
        rec = start_recorder(bag, params=['diagnostics_period_s:=0.2'], node_name='rec_term')
        wait_for(bag, rec)
        # Stopped once it says it has written two of its own statuses, however long that
        # takes on a busy machine.
        assert watcher.wait(lambda: _written(watcher, 'rec_term') >= 2), watcher.statuses[-3:]
        written = _written(watcher, 'rec_term')
        rc, err = stop(rec, signal.SIGTERM)
    finally:
        watcher.close()
    assert rc == 0, err
    with Reader(bag) as reader:
        assert reader.message_count >= written >= 2   # everything it said it wrote
        # (and /parameter_events, recorded by default: each node announces its parameters
        # there as it declares them)
        assert {c.topic for c in reader.connections} - {'/parameter_events'} == \
            {'/diagnostics'}


def _messages_on_disk(data):
    """Count the messages in the complete records of an MCAP file cut anywhere (mcap's reader)."""
    from mcap.exceptions import EndOfFile
    from mcap.records import Message
    from mcap.stream_reader import StreamReader
    n = 0
    try:
        for record in StreamReader(io.BytesIO(data), validate_crcs=True).records:
            n += isinstance(record, Message)
    except EndOfFile:        # the chunk being written when the process died
        pass
    return n


def test_sigkill_then_repair_keeps_everything_flushed(tmp_path, erva):
    bag = str(tmp_path / 'killed')
    rec = start_recorder(bag, {'scenario': 'kill'}, params=['flush_period_s:=0.2'])
    mcap = os.path.join(bag, os.path.basename(bag) + '_0.mcap')
    wait_for(mcap, rec)     # the file, not the directory: it is opened just after
    pub = subprocess.Popen([sys.executable, '-m', 'erva_ros.ros.traffic', 'contract',
                            '--duration', '60', '--ack-timeout', '0.2'], env=ros_env(),
                           cwd=REPO, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    STARTED.append(pub)
    # Killed once a good part is on disk, however slowly a loaded machine got there: the
    # chunks (768 KiB by default) are flushed every 0.2 s, far before they are full.
    end = time.monotonic() + 120
    while time.monotonic() < end and os.path.getsize(mcap) < 60_000:
        assert pub.poll() is None, pub.communicate()
        time.sleep(0.05)
    assert os.path.getsize(mcap) >= 60_000, 'the recorder did not flush while recording'
    # Frozen first, so that what is on disk at the kill can be read: SIGKILL then loses
    # exactly what the recorder had not handed to the OS.
    os.kill(rec.pid, signal.SIGSTOP)
    on_disk = _messages_on_disk(open(mcap, 'rb').read())
    rec.kill()
    rec.communicate(timeout=30)
    pub.kill()
    pub.communicate(timeout=60)
    assert not os.path.exists(os.path.join(bag, 'metadata.yaml'))
    out = erva('bag', 'repair', bag, check=True).stdout
    assert 'recovered' in out
    with Reader(bag) as reader:
        assert reader.message_count == on_disk > 100      # every flushed message, no more
    repaired = open_bag(bag)
    assert repaired.complete and repaired.session['scenario'] == 'kill'
    seqs = [m.sequence for m in repaired.messages(['/erva/state'])]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))   # a gap-free prefix


def _limit_file_size():
    resource.setrlimit(resource.RLIMIT_FSIZE, (48 * 1024, 48 * 1024))


def test_full_disk_is_an_error_diagnostic_and_the_loop_runs_on(tmp_path, erva):
    watcher = DiagnosticsWatcher()
    try:
        bag = str(tmp_path / 'full')
        rec = start_recorder(bag, params=['flush_period_s:=0.1'], preexec_fn=_limit_file_size)
        wait_for(bag, rec)
        result = traffic('--duration', '3')
        # The write fails at the first flush past 48 KiB; stopped once that is reported.
        assert watcher.wait(lambda: watcher.errors('recorder')), watcher.statuses[-3:]
        rc, err = stop(rec)
        errors = watcher.errors('recorder')
    finally:
        watcher.close()
    assert rc == 1
    assert result['acked'] and result['published']['/erva/state'] == 150   # loop unaffected
    lines = [ln for ln in err.splitlines() if 'ERROR' in ln]
    assert len(lines) == 1 and 'File too large' in lines[0], err
    assert 'the control loop is not affected' in lines[0]
    assert errors and 'File too large' in errors[-1].message
    erva('bag', 'repair', bag, check=True)
    assert 0 < open_bag(bag).message_count < sum(result['published'].values())


def test_unusable_bag_dir_is_an_error_diagnostic(tmp_path):
    watcher = DiagnosticsWatcher()
    try:
        (tmp_path / 'exists').mkdir()
        (tmp_path / 'file').write_text('x')
        a = start_recorder(str(tmp_path / 'exists'), node_name='rec_exists')
        b = start_recorder(str(tmp_path / 'file' / 'bag'), node_name='rec_file')
        watcher.wait(lambda: watcher.errors('rec_exists') and watcher.errors('rec_file'))
        (rc_a, err_a), (rc_b, err_b) = stop(a), stop(b)
        found = {'exists': watcher.errors('rec_exists'), 'file': watcher.errors('rec_file')}
    finally:
        watcher.close()
    assert rc_a == rc_b == 1
    assert 'already exists' in found['exists'][-1].message
    assert 'cannot create bag directory' in found['file'][-1].message
    for err in (err_a, err_b):
        assert len([ln for ln in err.splitlines() if 'ERROR' in ln]) == 1, err


def test_bad_parameters_stop_the_node_with_one_line(tmp_path):
    cases = {'compression:=gzip': 'compression', 'flush_period_s:=0.0': 'flush_period_s',
             'session_metadata:="[1, 2]"': 'session_metadata'}
    procs = [(start_recorder(str(tmp_path / f'b{i}'), params=[p], node_name=f'r{i}'), word)
             for i, (p, word) in enumerate(cases.items())]
    procs.append((subprocess.Popen([sys.executable, '-m', 'erva_ros.nodes.recorder_node'],
                                   env=ros_env(), text=True, stdout=subprocess.PIPE,
                                   stderr=subprocess.PIPE), 'bag_dir'))
    STARTED.extend(p for p, _ in procs)
    for proc, word in procs:
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 2, err
        assert len(err.strip().splitlines()) == 1 and word in err, err
