"""`erva run` in real time, as a user runs it: recording, a node killed mid-run, signals."""

import json
import os
import re
import shutil
import signal
import time

import pytest
import yaml

from conftest import fifo_permitted, sim_delay_args
from run_helpers import (bag_counts, bag_messages, run_with_node_killed, run_with_node_stopped,
                         SampleWatch, start_run as _start)
from run_helpers import wait_connected as _wait_connected

pytestmark = pytest.mark.ros   # every test here starts DDS


def _gone(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_erva_run_realtime_records_and_summarises(tmp_path, erva):
    proc = _start('--duration', 2, '--record', tmp_path, '--json')
    out, err = proc.communicate(timeout=180)
    assert proc.returncode == 0, err
    s = json.loads(out)
    assert s['ok'] and not s['errors']
    assert s['scenario']['controller'] == 'preview' and s['scenario']['mode'] == 'realtime'
    assert s['metrics']['samples'] == 100 and s['metrics']['acc_2norm'] > 0
    assert s['metrics']['power_w'] > 0
    cmd = s['commands']
    # One command per state, t_0..t_100, except where a loaded machine made the NMPC
    # skip to the newest state (counted as missed samples).  The rate itself is a
    # benchmark figure (erva bench --live), not a pass/fail one.
    assert cmd['for_samples'] + s['nmpc']['missed_samples'] == 101
    assert s['nmpc']['missed_samples'] == s['nmpc']['superseded_states']
    assert cmd['rate_hz'] > 0
    # Timing figures are there (their values depend on the machine's load: erva bench).
    assert cmd['sample_to_command_ms']['samples'] == cmd['for_samples']
    for key in ('period_jitter_ms', 'state_to_command_ms'):
        assert cmd[key]['samples'] > 0 and cmd[key]['p50'] >= 0
    # No figure is impossible: a command comes after its sample.
    assert cmd['sample_to_command_ms']['p50'] >= 0
    plant = s['plant']
    assert plant['u_from_command'] + plant['u_from_plan'] + plant['u_from_passive'] == 100
    if plant['u_from_command'] == 100 and s['nmpc']['missed_samples'] == 0:
        # Every command in time (the usual case): the real-time loop is the offline one
        # (a late solve publishes its own plan, so lateness alone changes nothing).
        sim = json.loads(erva('sim', '--duration', 2, *sim_delay_args(), '--json',
                              check=True).stdout)
        assert s['metrics']['acc_2norm'] == pytest.approx(sim['acc_2norm'], rel=1e-9)
        assert s['metrics']['power_w'] == pytest.approx(sim['power_w'], rel=1e-6)
    assert s['nmpc']['solve_ms']['samples'] == cmd['for_samples']
    assert s['messages']['dropped_total'] == 0
    assert all(n['stopped_cleanly'] for n in s['nodes'].values()), s['nodes']
    # realtime_priority 20 (config/live.yaml): every loop node got SCHED_FIFO, or says why not.
    # The recorder runs 10 levels below the loop: above other work, below the loop.
    sched = s['scheduling']
    assert set(sched) == {'nmpc_node', 'plant_sim_node', 'road_preview_node', 'recorder'}, sched
    fifo = fifo_permitted(20)
    for node, got in sched.items():
        want = 'SCHED_FIFO 10' if node == 'recorder' else 'SCHED_FIFO 20'
        assert got == want if fifo else got.startswith('unavailable'), (node, got)
    # The bag holds exactly what the nodes published (read by the mcap reader, not ours),
    # and erva run says so.
    bag = s['bag']
    assert os.path.dirname(bag) == str(tmp_path)
    assert re.fullmatch(r'\d{8}T\d{6}Z_paper', os.path.basename(bag))
    counts = bag_counts(bag, decode=True)
    published = s['messages']['published']
    # A road timer that fell behind by whole periods skips samples (counted; the plant
    # steps across the gap); the last one is never skipped, so the plant always ends.
    skipped = s['road']['samples_skipped']
    assert published['state'] == published['road/preview'] + skipped == 101
    assert (plant['road_gaps'] > 0) == (skipped > 0) and plant['road_gaps'] <= skipped
    assert published['sprung_accel'] == published['generator'] == 100
    for topic, n in published.items():
        assert counts[f'/erva/{topic}'] == n, (topic, counts)
    rec = s['recording']
    assert rec['lost'] == 0 and rec['lost_in_transport'] == 0 and not rec['diagnostics_missing']
    # The summary's figures agree with the bag's own account of the session (erva report
    # reads only the bag: messages, their stamps and the DDS publish / receive times).
    report = json.loads(erva('report', bag, '--json', check=True).stdout)
    assert report['comfort']['acc_2norm'] == pytest.approx(s['metrics']['acc_2norm'], rel=1e-9)
    assert report['samples']['sprung_accel'] == s['metrics']['samples']
    for key in ('latency_publish_ms', 'latency_log_ms'):     # command after its sample
        lat = report['timing'][key]
        assert lat['samples'] == cmd['for_samples'] and 0 < lat['p50'] <= lat['p99'], lat
    # nmpc_node's prediction: one per command (the monitor does not count it).
    assert {t: c['recorded'] for t, c in rec['topics'].items()} == {
        **{f'/erva/{t}': n for t, n in published.items()},
        '/erva/prediction': published['damping_cmd']}
    # The summary also counts the bag as erva bag info does: the loop's topics and
    # /diagnostics; and the bag keeps the params file every node read (not its path).
    info = json.loads(erva('bag', 'info', bag, '--json', check=True).stdout)
    in_info = {t['name']: t['count'] for t in info['topics']}
    others = {t: n for t, n in in_info.items() if t not in rec['topics']}
    # (/parameter_events holds what the nodes announced after the recorder matched them:
    # it may be none.)
    assert set(others) == {'/diagnostics', '/parameter_events'}
    assert {t: n for t, n in in_info.items() if n} == counts      # the mcap reader's
    assert rec['in_bag'] == {'messages': sum(counts.values()), 'topics': len(in_info),
                             'other_topics': others}
    assert rec['in_bag']['messages'] == info['message_count'] == \
        sum(c['recorded'] for c in rec['topics'].values()) + sum(others.values())
    params = yaml.safe_load(info['session']['params_yaml'])
    assert params['/**']['ros__parameters']['session_id'] == info['session']['session_id']
    assert params['/**/nmpc_node']['ros__parameters']['controller'] == 'preview'
    assert 'params_file' not in info['session']
    # The bag marks the loop's first sample (metadata.yaml): the stamp of its first road
    # height and state as the mcap reader reads them, after the bring-up.  `bag info`
    # shows it; `bag play --start-offset loop` starts there: every sample, and of the
    # statuses only those logged from then on.
    meta = yaml.safe_load(open(os.path.join(bag, 'metadata.yaml'), encoding='utf-8'))
    t0 = int(meta['rosbag2_bagfile_information']['custom_data']['erva_loop_start'])
    msgs = bag_messages(bag, ['/erva/road/height', '/erva/state', '/diagnostics'])
    first = {t: next(stamp for topic, _, stamp in msgs if topic == t)
             for t in ('/erva/road/height', '/erva/state')}
    assert first == {'/erva/road/height': t0, '/erva/state': t0}
    info = json.loads(erva('bag', 'info', bag, '--json', check=True).stdout)
    assert info['loop_start_ns'] == t0 and info['loop_offset_s'] > 0
    assert info['loop_offset_s'] == pytest.approx((t0 - info['start_ns']) * 1e-9, abs=1e-9)
    play = json.loads(erva('bag', 'play', bag, '--start-offset', 'loop', '--rate', '20',
                           '--topics', '/erva/road/height', '/diagnostics', '--json',
                           check=True).stdout)
    assert play['start_offset_s'] == info['loop_offset_s']
    start = info['start_ns'] + round(info['loop_offset_s'] * 1e9)
    diagnostics = [log for topic, log, _ in msgs if topic == '/diagnostics']
    assert play['published'] == {'/erva/road/height': published['road/height'],
                                 '/diagnostics': sum(log >= start for log in diagnostics)}
    assert play['published']['/diagnostics'] < len(diagnostics)     # the bring-up's: cut


def test_killed_nmpc_plant_holds_plan_then_passive_and_run_fails(tmp_path):
    # killed well into the run, on any machine
    code, s, err, pids = run_with_node_killed('nmpc_node', 30, '--duration', 3, '--no-record')
    assert code == 1, err
    assert any(e.startswith('nmpc_node died (exit status -9)') for e in s['errors']), s['errors']
    assert 'nmpc_node died' in err and 'the run goes on without it' in err
    plant = s['plant']
    # The run went on to the end: after the kill (at sample 30 or a little later) the
    # plant used the last plan (N - 1 = 9 samples), then passive damping for the rest of
    # the 150 steps, and reported both.
    assert plant['steps'] == 150
    assert plant['u_from_command'] + plant['u_from_plan'] + plant['u_from_passive'] == 150
    assert plant['u_from_plan'] >= 9
    assert plant['u_from_passive'] >= 1
    events = [(e['level'], e['message']) for e in s['events'] if e['node'] == 'plant_sim_node']
    last_plan = max(i for i, (lvl, m) in enumerate(events) if lvl == 'WARN' and 'plan' in m)
    assert events[last_plan + 1] == ('ERROR', 'no command and plan used up: passive damping c_e0')
    assert s['nodes']['plant_sim_node']['stopped_cleanly']
    assert s['nodes']['nmpc_node']['died']
    assert all(_gone(p) for p in pids.values())
    # The node logs are kept for a failed run; this one failed on purpose.
    assert os.path.isfile(os.path.join(s['session_dir'], 'nmpc_node.log'))
    shutil.rmtree(s['session_dir'])


def test_a_road_timer_behind_skips_samples_counts_them_and_the_run_still_ends(tmp_path):
    # The road node (the real-time time master) stopped for 15 periods mid-run: it then
    # publishes the newest passed sample, counts the ones it missed, and the plant steps
    # across the gap; nothing is lost and the run ends (its last sample is never skipped).
    code, s, err = run_with_node_stopped('road_preview_node', tmp_path, 4, 0.6, 0.3)
    assert code == 0, err
    assert s['ok'] and not s['errors'], s['errors']
    # Not real time, and said so: a WARN line with the count and the widest gap.
    skipped = s['road']['samples_skipped']
    assert any(w.startswith(f'{skipped} road samples skipped by a late timer (widest gap ')
               for w in s['warnings']), s['warnings']
    skipped, plant = s['road']['samples_skipped'], s['plant']
    published = s['messages']['published']
    assert skipped >= 1 and 1 <= plant['road_gaps'] <= skipped, (s['road'], plant)
    assert published['road/preview'] + skipped == published['state'] == 201
    assert s['road']['samples_published'] == published['road/preview']
    assert plant['steps'] == 200 and s['metrics']['samples'] == 200
    # Every sample solved or counted missed (the stall's safe commands are stamped on
    # samples whose states the plant bridged later: missed, not solved).
    nm = s['nmpc']
    assert nm['solve_ms']['samples'] + nm['missed_samples'] == 201, nm
    counts = bag_counts(s['bag'], decode=True)
    for topic, n in published.items():
        assert counts[f'/erva/{topic}'] == n, (topic, counts)


def test_strict_fails_a_run_that_was_not_real_time_and_its_bag_says_so(tmp_path, erva):
    code, s, err = run_with_node_stopped('road_preview_node', tmp_path, 3, 0.6, 0.3,
                                         '--strict')
    assert code == 1 and not s['ok'], err
    assert s['warnings'] and s['errors'] == [f'{w} (--strict)' for w in s['warnings']]
    assert s['recording']['lost'] == 0           # recorded whole: only the verdict failed
    info = json.loads(erva('bag', 'info', s['bag'], '--json', check=True).stdout)
    assert [w for w in info['warnings'] if 'cut short' in w] == [
        f'the session was cut short: {s["errors"][0]}']


@pytest.mark.parametrize('sig, code', [(signal.SIGINT, 130), (signal.SIGTERM, 143),
                                       (signal.SIGKILL, -9)])
def test_signals_stop_every_process(sig, code):
    watch = SampleWatch()
    proc = _start('--duration', 60, '--no-record')
    try:
        pids = _wait_connected(proc)
        assert set(pids) == {'nmpc_node', 'plant_sim_node', 'road_preview_node'}
        argv = open(f'/proc/{pids["nmpc_node"]}/cmdline').read().split('\0')
        params_file = argv[argv.index('--params-file') + 1]
        watch.wait(50, proc=proc)        # a second of samples ran: a summary to print
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == code, err
        if sig != signal.SIGKILL:
            assert f'interrupted by {signal.Signals(sig).name}' in out
            assert 'comfort' in out                     # the summary of what ran
        # No stray process: each node (and its process group) is gone; after SIGKILL of
        # erva run the kernel's parent-death signal stops the nodes.
        end = time.monotonic() + 60      # generous: only a failure waits this long
        while time.monotonic() < end and not all(_gone(p) for p in pids.values()):
            time.sleep(0.1)
        assert all(_gone(p) for p in pids.values()), pids
        if sig == signal.SIGKILL:
            # Nobody left to clean up: the next run removes the directory of a dead run.
            from erva_ros.session.run.session_dirs import remove_stale_session_dirs
            session_dir = os.path.dirname(params_file)
            assert os.path.isdir(session_dir)
            assert session_dir in remove_stale_session_dirs(os.path.dirname(session_dir))
            assert not os.path.exists(session_dir)
    finally:
        watch.close()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)


def test_an_extra_reader_that_comes_late_still_gets_sample_0():
    # --extra-readers 1: the road (the real-time time master) waits for one reader of the
    # user's on road/height and road/preview.  The reader is created only once erva run
    # says what it waits for (after 10 s): without the wait the run would be over.
    import rclpy
    from geometry_msgs.msg import PointStamped
    from rclpy.executors import SingleThreadedExecutor
    from trajectory_msgs.msg import JointTrajectory

    from erva_ros.ros import qos as ros_qos
    proc = _start('--duration', 1, '--no-record', '--json', '--extra-readers', 1)
    context = rclpy.Context()
    try:
        for line in proc.stderr:
            assert 'connected in' not in line, line
            if 'still connecting' in line:
                break
        assert 'road/height has 2 of 3 subscribers' in line, line
        rclpy.init(context=context)
        node = rclpy.create_node('extra_reader', context=context)
        distances = []
        node.create_subscription(PointStamped, '/erva/road/height',
                                 lambda m: distances.append(m.point.x), ros_qos.control_qos())
        node.create_subscription(JointTrajectory, '/erva/road/preview', lambda m: None,
                                 ros_qos.control_qos())
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        end = time.monotonic() + 240
        while proc.poll() is None and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        out, err = proc.communicate(timeout=60)
    finally:
        rclpy.try_shutdown(context=context)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    s = json.loads(out)
    assert proc.returncode == 0 and s['ok'], (s['errors'], err[-1500:])
    assert distances and distances[0] == 0.0, distances[:3]      # sample 0, first
    assert s['messages']['published']['road/height'] == 51
