"""A message from outside the loop cannot stop or steer it (`erva run`).

One valid ``/erva/state`` stamped an hour ahead, published by another process on the
domain, would end nmpc_node's scenario if stamps were trusted.  Every input stamp is
checked against a window around the receiving node's clock: the foreign state is
rejected and counted, the monitor counts it as foreign, and the loop runs as if it had
never been sent -- in lock-step exactly as `erva sim`.
"""

import json
import subprocess
import sys
import time

import pytest

from conftest import REPO, ros_env, sim_delay_args
from erva_ros.ros import qos as ros_qos
from run_helpers import SampleWatch

pytestmark = pytest.mark.ros

HOUR_NS = 3600 * 10**9


def _inject_state(proc, lockstep, stamp_ns_of, after_samples=10):
    """Publish one valid JointState on /erva/state once the loop has run ``after_samples``.

    In lock-step the watch is one of the state's readers the run waits for (it may
    otherwise end before the watch is matched); either way the foreign writer waits for
    the loop's readers of it (nmpc, monitor) before it publishes.
    """
    from rclpy.duration import Duration
    from sensor_msgs.msg import JointState

    from ros_msgs import state_msg

    watch = SampleWatch(state_reader=lockstep)
    try:
        pub = watch.node.create_publisher(JointState, '/erva/state', ros_qos.control_qos())
        watch.wait(after_samples, proc=proc)
        readers = 2 + (1 if lockstep else 0)           # nmpc, monitor (and the watch)
        watch.spin_until(lambda: pub.get_subscription_count() >= readers,
                         lambda: f'{pub.get_subscription_count()} of {readers} readers of '
                         f'the foreign state', proc=proc)
        pub.publish(state_msg(stamp_ns_of(), [1e-3, 0.0, 0.0, 0.0, 0.0, 0.0], 'erva'))
        assert pub.wait_for_all_acked(Duration(seconds=30))
    finally:
        watch.close()


def _run_with_foreign_state(mode, duration, stamp_ns_of):
    lockstep = mode == 'lockstep'
    proc = subprocess.Popen(
        [sys.executable, '-m', 'erva_ros.cli', 'run', '--mode', mode, '--duration',
         str(duration), '--no-record', '--json', *(['--extra-readers', '1'] if lockstep else [])],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ros_env(), cwd=REPO)
    try:
        _inject_state(proc, lockstep, stamp_ns_of)
        out, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, json.loads(out), err


def test_lockstep_a_future_stamped_foreign_state_changes_nothing(erva):
    # Simulated time starts at 0: a stamp an hour ahead is far outside the window.
    code, s, err = _run_with_foreign_state('lockstep', 3, lambda: HOUR_NS)
    assert code == 0 and s['ok'], (s['errors'], err[-1500:])
    assert s['messages']['rejected']['state'] == 1
    assert s['messages']['foreign']['state'] == 1
    assert s['nmpc']['missed_samples'] == 0 and s['commands']['for_samples'] == 151
    # The loop is exactly the offline one: the foreign state left no trace.
    sim = json.loads(erva('sim', '--duration', 3, *sim_delay_args(), '--json', check=True).stdout)
    assert s['metrics']['acc_2norm'] == pytest.approx(sim['acc_2norm'], rel=1e-9)
    assert s['metrics']['power_w'] == pytest.approx(sim['power_w'], rel=1e-6)


def test_realtime_a_future_stamped_foreign_state_is_rejected_and_reported():
    code, s, err = _run_with_foreign_state('realtime', 4, lambda: time.time_ns() + HOUR_NS)
    assert code == 0 and s['ok'], (s['errors'], err[-1500:])
    assert s['messages']['rejected']['state'] == 1
    assert s['messages']['foreign']['state'] == 1
    nm = s['nmpc']
    # Every sample's state reached the controller (a busy controller may still skip to
    # the newest one: superseded, counted apart), and it ran to the scenario's end.
    assert s['commands']['for_samples'] + nm['missed_samples'] == 201
    assert nm['missed_samples'] == nm['superseded_states']
    assert nm['state_timeouts'] == 0 and nm['out_of_order'] == 0
    # The summary's figures are the loop's own: one state per sample (its pace is a
    # benchmark figure: erva bench --live).
    assert s['metrics']['samples'] == 200


def test_lockstep_a_reader_already_there_cannot_stand_in_for_the_monitor(erva, tmp_path):
    # A `ros2 topic echo /erva/state` before the run counts as one of the plant's
    # readers; with no settling time only the named reader (the monitor) tells the plant
    # that the monitor is matched and will get the first states.
    import rclpy
    from sensor_msgs.msg import JointState

    live = tmp_path / 'live.yaml'
    live.write_text("/**:\n  ros__parameters:\n    start_delay_s: 0.0\n")
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        echo = rclpy.create_node('foreign_echo', context=context)
        echo.create_subscription(JointState, '/erva/state', lambda msg: None,
                                 ros_qos.control_qos())
        run = erva('run', '--mode', 'lockstep', '--duration', '1', '--no-record', '--json',
                   '--live', str(live), timeout=400)
    finally:
        rclpy.try_shutdown(context=context)
    assert run.returncode == 0, run.stdout + run.stderr
    s = json.loads(run.stdout)
    assert not any(s['messages']['dropped'].values()), s['messages']
    assert s['messages']['received']['state'] == 51, s['messages']
