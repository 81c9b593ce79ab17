"""`erva run --ecu virtual`: the whole hardware-in-the-loop loop, recorded like any session.

NMPC → ecu_bridge_node → CAN (loopback UDP) → `erva ecu-sim` (plant) → CAN → bridge →
state_estimator_node → NMPC, started and stopped by `erva run` as a user runs it.
"""

import json
import math
import os
import re

import pytest

from conftest import fifo_permitted, run_erva

pytestmark = pytest.mark.ros

DURATION = 3


def _group_gone(pgid):
    """Return True if no process is left in the process group ``pgid``."""
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return True
    return False


def _read_bag(bag_dir, wanted):
    """Count messages per topic with mcap-ros2-support's reader (not ours)."""
    from mcap_ros2.reader import read_ros2_messages
    mcaps = [f for f in os.listdir(bag_dir) if f.endswith('.mcap')]
    assert len(mcaps) == 1, os.listdir(bag_dir)
    counts = dict.fromkeys(wanted, 0)
    for msg in read_ros2_messages(os.path.join(bag_dir, mcaps[0]), topics=list(wanted)):
        assert msg.ros_msg.header.stamp.sec > 0
        counts[msg.channel.topic] += 1
    return counts


@pytest.fixture(scope='module')
def hil_run(tmp_path_factory):
    """Run the HIL loop once for the tests of this module: (summary, stderr, pids)."""
    bags = tmp_path_factory.mktemp('bags')
    proc = run_erva('run', '--ecu', 'virtual', '--duration', DURATION, '--json',
                    '--record', bags, timeout=240)
    assert proc.returncode == 0, proc.stderr
    pids = {n: int(p) for n, p in re.findall(r'(\w+) \(pid (\d+)\)', proc.stderr)}
    return json.loads(proc.stdout), proc.stderr, pids


def test_hil_loop_runs_at_50_hz_and_controls_like_the_plain_loop(hil_run, erva):
    s, err, _ = hil_run
    assert s['ok'] and not s['errors'], s['errors']
    assert s['scenario']['ecu'] == 'virtual' and s['scenario']['mode'] == 'realtime'
    # One command per ECU cycle t_0..t_150, each an NMPC solve with its preview: a loop
    # whose states never met their previews (or stalled) publishes passive or safe ones.
    n = round(DURATION / 0.02) + 1
    cmd, nmpc = s['commands'], s['nmpc']
    assert n - 5 <= cmd['for_samples'] <= cmd['received'] <= n, cmd
    assert abs(cmd['rate_hz'] - 50.0) < 2.5
    assert nmpc['solves'] >= n - 5 and nmpc['no_preview'] == 0, nmpc
    assert nmpc['state_timeouts'] == 0 and nmpc['safe_commands'] == 0
    assert s['plant']['steps'] == n - 1 and s['metrics']['samples'] == n - 1
    for key in ('sample_to_command_ms', 'monitor'):
        assert key in cmd
    assert 'state_to_command_ms' not in cmd          # no plant node to measure it
    # Comfort on the ECU's ground truth.  The ECU applies each command when it arrives
    # (a real actuator), not over the whole period as plant_sim_node does, so the run
    # depends on the loop's latency: measured 1.1-1.4x the offline NMPC (= a plain
    # `erva run` whose commands are all on time).  Passive damping is 2.4x worse.
    ref = {c: json.loads(erva('sim', '--duration', DURATION, '--controller', c, '--json',
                              check=True).stdout) for c in ('preview', 'passive')}
    m = s['metrics']
    assert all(math.isfinite(m[k]) for k in ('acc_2norm', 'acc_rms', 'power_w'))
    assert 0.6 < m['acc_2norm'] / ref['preview']['acc_2norm'] < 1.6, (m, ref['preview'])
    assert m['acc_2norm'] < 0.75 * ref['passive']['acc_2norm']
    assert 0 < m['power_w'] < 3 * ref['preview']['power_w']
    assert s['messages']['dropped_total'] == 0, s['messages']


def test_hil_block_reports_a_clean_link_latencies_and_estimation_error(hil_run):
    s = hil_run[0]
    hil = s['hil']
    for side in ('bridge', 'ecu'):
        for kind in ('crc', 'counter', 'length'):
            assert hil[side][f'dropped_{kind}'] == 0, (side, hil[side])
        assert hil[side]['bus_errors'] == 0
    assert hil['bridge']['command_timeouts'] == 0        # none during the scenario
    assert hil['bridge']['commands_received'] == s['commands']['received']
    assert hil['ecu']['overruns'] is not None and hil['ecu']['mode'] == 'CONTROLLED'
    for key in ('bridge_ros_to_can', 'bridge_can_to_ros', 'estimator'):
        lat = hil['latency_ms'][key]
        assert lat['samples'] > 50 and 0 < lat['p50'] <= lat['p99'] <= lat['max'], key
    # realtime_priority (config/live.yaml) reaches every process of the loop.
    fifo = fifo_permitted(20)
    sched = s['scheduling']
    assert set(sched) == {'nmpc_node', 'road_preview_node', 'ecu_sim', 'state_estimator_node',
                          'ecu_bridge_node: command', 'recorder'}, sched
    assert all(v == ('SCHED_FIFO 10' if n == 'recorder' else 'SCHED_FIFO 20') if fifo
               else v.startswith('unavailable') for n, v in sched.items()), sched
    est = hil['estimator']
    assert est['updates'] == s['messages']['published']['state']
    assert est['error']['matched'] > 100
    assert all(r < 0.3 for r in est['error']['relative_rms'].values()), est['error']


def test_hil_session_is_recorded_and_readable(hil_run, erva):
    s = hil_run[0]
    wanted = ('/erva/ecu/sprung_accel', '/erva/state', '/erva/damping_cmd',
              '/erva/ecu_sim/state')
    counts = _read_bag(s['bag'], wanted)
    assert all(counts[t] > 100 for t in wanted), counts
    published = s['messages']['published']
    assert counts['/erva/state'] == published['state'], counts
    assert s['recording']['lost'] == 0, s['recording']
    assert counts['/erva/ecu_sim/state'] == published['ecu_sim/state'], counts
    info = json.loads(erva('bag', 'info', s['bag'], '--json', check=True).stdout)
    assert info['complete'] and info['session']['ecu'] == 'virtual'
    assert {t['name'] for t in info['topics']} >= set(wanted)
    report = json.loads(erva('report', s['bag'], '--json', check=True).stdout)
    # The report's comfort is over every recorded sample (t_0 too), the summary's over
    # the scenario's steps: the same run, within a sample.
    assert report['comfort']['acc_2norm'] == pytest.approx(s['metrics']['acc_2norm'], rel=0.1)


def test_no_process_outlives_the_run(hil_run):
    _, err, pids = hil_run
    assert set(pids) == {'recorder_node', 'nmpc_node', 'ecu_sim', 'ecu_bridge_node',
                         'state_estimator_node', 'road_preview_node'}, err
    assert all(_group_gone(p) for p in pids.values()), pids


@pytest.mark.parametrize('how', ['option', 'live file'])
def test_virtual_ecu_refuses_lockstep_before_anything_starts(erva, tmp_path, how):
    args = ['--mode', 'lockstep']
    if how == 'live file':
        live = tmp_path / 'live.yaml'
        live.write_text('/**:\n  ros__parameters:\n    mode: lockstep\n')
        args = ['--live', str(live)]
    proc = erva('run', '--ecu', 'virtual', '--no-record', *args, timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert lines == ['erva run: error: --ecu virtual runs in real time only (the ECU keeps '
                     'wall-clock time), not with mode lockstep'], proc.stderr
    assert 'started' not in proc.stderr and not proc.stdout
