"""The HIL loop with real processes: `erva ecu-sim`, ecu_bridge_node, state_estimator_node.

The test process plays road_preview_node and the NMPC (a skyhook law answering every
/erva/state at once) over real DDS (local discovery, this run's domain); the ECU and
the bridge talk CAN over loopback UDP.
"""

import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from conftest import REPO, ros_env
from erva_ros.core.model.params import paper_params
from erva_ros.ros import qos as ros_qos

pytestmark = pytest.mark.ros

PARAMS = os.path.join(REPO, 'config', 'erva_paper.yaml')


class Driver:
    """Road source, stand-in NMPC and observer, in this process.

    As the nodes do, it answers each state and publishes the road in threads of their
    own: on a loaded machine an executor serving the observed topics too falls behind
    the loop (its answers then come too late for the bridge, stale).
    """

    def __init__(self, namespace='/erva', road=True):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import AccelStamped, PointStamped
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory

        from erva_ros.core import topics
        from erva_ros.core.hil import topics as hil_topics
        from erva_ros.core.road.profiles import make_road
        from erva_ros.ros.rt_subscription import RealtimeSubscription

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(args=[], context=self.context,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node('hil_test_driver', namespace=namespace,
                                      context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        qos = ros_qos.control_qos()
        # Its readers keep everything: a stall of this (test) process must not make it miss
        # messages the checks below count.
        deep = ros_qos.control_qos(depth=10_000)
        self.road = make_road('paper', 60.0, seed=0)
        self.pub_road = self.node.create_publisher(PointStamped, topics.ROAD_HEIGHT, qos)
        self.pub_cmd = self.node.create_publisher(JointTrajectory, topics.DAMPING_CMD, qos)
        self.state_sub = RealtimeSubscription(self.node, JointState, topics.STATE, deep,
                                              self._on_state)
        self.node.create_subscription(JointState, hil_topics.TRUE_STATE, self._on_truth, deep)
        self.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diag, deep,
                                      raw=True)
        # The road on a 50 Hz grid of sample instants, as road_preview_node publishes it.
        self.t0_ns = time.time_ns()
        self._stop = threading.Event()
        self._road_thread = threading.Thread(target=self._road_loop, daemon=True)
        self.answer = True
        self.answers = 0                # damping_cmd published
        self.est, self.truth = {}, {}
        # What the bridge publishes, by stamp: the four per-frame topics and the cycle.
        self.ecu = {t: {} for t in (hil_topics.ECU_DAMPING_APPLIED, hil_topics.ECU_SPRUNG_ACCEL,
                                    hil_topics.ECU_SUSPENSION, hil_topics.ECU_GENERATOR)}
        self.measurements = {}          # stamp -> [position lists]
        for topic in self.ecu:
            self.node.create_subscription(
                AccelStamped if topic == hil_topics.ECU_SPRUNG_ACCEL else JointState, topic,
                lambda msg, topic=topic: self._on_ecu(topic, msg), deep)
        self.node.create_subscription(JointState, hil_topics.ECU_MEASUREMENTS,
                                      self._on_measurements, deep)
        self.pub_meas = self.node.create_publisher(JointState, hil_topics.ECU_MEASUREMENTS, qos)
        self.diag_log = []            # (time, name, level, message, values)
        self.state_sub.start()
        if road:
            self.start_road()

    def start_road(self):
        """Start publishing the road (at once unless ``Driver(road=False)``)."""
        self._road_thread.start()

    def _road_loop(self):
        from ros_msgs import road_height_msg
        last = -1
        while not self._stop.is_set():
            k = (time.time_ns() - self.t0_ns) // 20_000_000       # the newest instant passed
            if k > last:
                last = k
                self.pub_road.publish(road_height_msg(self.t0_ns + k * 20_000_000, 0.0,
                                                      self.road.height(k * 0.02)))
            self._stop.wait(0.02 - (time.time_ns() - self.t0_ns) % 20_000_000 * 1e-9)

    def _on_state(self, msg, info=None):
        from ros_msgs import damping_msg, parse_state
        stamp, x = parse_state(msg, 'erva')
        self.est[stamp] = x
        if self.answer:
            u = 20000.0 if x[1] * (x[1] - x[3]) > 0 else 0.0
            self.pub_cmd.publish(damping_msg(stamp, [u] * 10, 20_000_000))
            self.answers += 1

    def _on_ecu(self, topic, msg):
        from ros_msgs import time_to_ns
        self.ecu[topic][time_to_ns(msg.header.stamp)] = msg

    def _on_measurements(self, msg):
        from ros_msgs import time_to_ns
        self.measurements.setdefault(time_to_ns(msg.header.stamp), []).append(
            (list(msg.name), list(msg.position)))

    def _on_truth(self, msg):
        from ros_msgs import parse_state
        stamp, x = parse_state(msg, 'erva')
        self.truth[stamp] = x

    def _on_diag(self, data):
        # The key/values as published (the reports' wire form, erva_ros/core/reports.py).
        from erva_ros.core.contract import decode_diagnostics
        for st in decode_diagnostics(data)[1]:
            self.diag_log.append((time.monotonic(), st.name, st.level, st.message, st.values))

    def spin(self, seconds, until=lambda: False):
        end = time.monotonic() + seconds
        while time.monotonic() < end and not until():
            self.executor.spin_once(timeout_sec=0.01)

    def take_the_rest(self, quiet_s=0.5, limit_s=60.0):
        """Serve callbacks until none came for ``quiet_s`` (the publishers have exited)."""
        last = end = time.monotonic()
        end += limit_s
        while time.monotonic() - last < quiet_s and time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.05)
            n = (len(self.diag_log), len(self.est), len(self.truth), len(self.measurements))
            if n != getattr(self, '_seen', None):
                self._seen, last = n, time.monotonic()

    def last(self, suffix):
        for entry in reversed(self.diag_log):
            if entry[1].endswith(suffix):
                return entry
        return (0.0, suffix, -1, '', {})

    def level(self, suffix):
        return self.last(suffix)[2]

    def close(self):
        self._stop.set()
        if self._road_thread.ident is not None:
            self._road_thread.join()
        self.state_sub.destroy()
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)


def _start(specs, tmp_path):
    procs = []
    for s in specs:
        env = ros_env()
        env.update({k: v for k, v in s.env.items() if k not in ('ROS_DOMAIN_ID',)})
        env['ROS_DOMAIN_ID'] = ros_env()['ROS_DOMAIN_ID']
        out = open(tmp_path / f'{s.name}.log', 'w')
        procs.append(subprocess.Popen(s.argv, env=env, stdout=out, stderr=subprocess.STDOUT,
                                      cwd=REPO))
    return procs


def _stop(procs):
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    for p in procs:
        try:
            p.wait(15)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def test_hil_loop_estimates_the_state_and_goes_safe_when_the_nmpc_stops(tmp_path):
    from erva_ros.session.hil.hil_processes import hil_process_specs

    # The road comes from this process as it arrives (not a session road known ahead), on
    # its grid of sample instants; the ECU samples on that grid and the estimator stamps
    # its cycles with those instants, as in `erva run`.
    # The ECU runs until this test stops it: the scenario takes what this machine needs.
    specs = hil_process_specs(PARAMS, duration_s=0.0, env=ros_env(), road='ros',
                              stamp_on_road_grid=True)
    driver = Driver()
    procs = _start(specs, tmp_path)
    logs = {s.name: tmp_path / f'{s.name}.log' for s in specs}
    # The waits end as soon as what they wait for happened; their limits only bound a
    # broken run (a loaded machine may take seconds to start and discover).
    try:
        driver.spin(60.0, until=lambda: len(driver.est) > 100)
        assert len(driver.est) > 100, {n: p.read_text()[-500:] for n, p in logs.items()}
        driver.spin(30.0, until=lambda: driver.level('ecu_bridge_node: command') == 0)
        assert driver.level('ecu_bridge_node: command') == 0          # OK: forwarding
        # Every answer from here on reaches the bridge (it has matched this publisher);
        # one before it had may not (discovery).
        answers_before = driver.answers
        # The NMPC stops answering: the bridge sends the safe passive command and raises
        # an ERROR; the ECU reports it applies the passive damping.
        driver.answer = False
        driver.spin(30.0, until=lambda: driver.level('ecu_bridge_node: command') == 2)
        cmd = driver.last('ecu_bridge_node: command')
        assert cmd[2] == 2 and 'safe passive' in cmd[3], cmd
        driver.spin(30.0, until=lambda: driver.last('ecu_bridge_node: ecu')[4].get(
            'ecu_mode') == 'SAFE_REQUESTED')      # (its status period: 0.5 s)
        ecu = driver.last('ecu_bridge_node: ecu')
        assert ecu[4]['ecu_mode'] == 'SAFE_REQUESTED', ecu
        assert float(ecu[4]['c_e_applied_ns_per_m']) == pytest.approx(10000.0, abs=2.0)
        driver.answer = True                  # the NMPC is back (it answers the next state)
        driver.spin(30.0, until=lambda: driver.level('ecu_bridge_node: command') == 0)
        assert driver.level('ecu_bridge_node: command') == 0
        n = len(driver.est)
        driver.spin(30.0, until=lambda: len(driver.est) > n + 100)     # controlled again
        # Stop the ECU (it reports finished), then the bridge and the estimator; take
        # their final statuses.
        _stop(procs[:1])
        _stop(procs[1:])
        driver.take_the_rest()
    finally:
        _stop(procs)
        driver.close()
    assert [p.returncode for p in procs] == [0, 0, 0], {n: p.read_text()[-800:]
                                                        for n, p in logs.items()}
    summary = json.loads(logs['ecu_sim'].read_text()[logs['ecu_sim'].read_text().index('{'):])
    assert summary['commands_applied'] > 0
    rejected = ('bad_crc', 'repeated', 'skipped', 'wrong_length')
    assert sum(summary[f'rx_{k}'] for k in rejected) == 0
    bus = driver.last('ecu_bridge_node: can bus')[4]
    assert (bus['bad_crc'], bus['skipped'], bus['repeated']) == ('0', '0', '0')
    cmd = {k: v for k, v in driver.last('ecu_bridge_node: command')[4].items()}
    assert int(cmd['command_timeouts']) >= 1 and int(cmd['safe_frames_sent']) >= 1
    # Every command the bridge got is counted: accepted, stale (older than 3 periods on
    # arrival: a stall) or malformed.
    took = sum(int(cmd[k]) for k in ('commands_received', 'commands_stale',
                                     'commands_rejected'))
    assert driver.answers - answers_before <= took <= driver.answers, (took, driver.answers)
    # Each accepted command was sent at once, with its latency measured (after 25).
    assert int(cmd['ros_to_can_ms_samples']) == max(0, int(cmd['commands_received']) - 25)
    est = driver.last('state_estimator_node')[4]
    # (Counted as published; this process got them all but those sent before it matched.)
    assert int(est['updates']) == int(est['published:/erva/state']) >= len(driver.est)
    assert int(est['latency_ms_samples']) == max(0, int(est['updates']) - 25)
    # Estimated vs true state, of the same sample instants (after the filter's start).
    pairs = [(x, driver.truth[t]) for t, x in sorted(driver.est.items())[25:]
             if t in driver.truth]
    assert pairs
    errs = [x - true for x, true in pairs]
    truth = [true for _, true in pairs]
    rel = np.sqrt(np.mean(np.square(errs), 0)) / np.sqrt(np.mean(np.square(truth), 0))
    assert np.all(rel < 0.3), rel
    assert driver.last('ecu_sim')[4]['finished'] == 'true'
    # Exactly one ecu/measurements per ECU cycle, with the stamp and the values of the
    # cycle's four per-frame messages.
    from erva_ros.core.hil import topics as hil_topics
    assert all(len(v) == 1 for v in driver.measurements.values())
    published = int(cmd['published:/erva/ecu/measurements'])
    assert 0 < len(driver.measurements) <= published
    # (Each cycle since this process matched the bridge's ecu/measurements writer.)
    stamps = {t for t in set.intersection(*(set(d) for d in driver.ecu.values()))
              if t >= min(driver.measurements)}
    assert stamps and stamps <= set(driver.measurements)
    v_max = 0.0
    l_gen = paper_params().l
    for stamp in sorted(stamps):
        names, values = driver.measurements[stamp][0]
        assert names == list(hil_topics.MEASUREMENT_NAMES)
        applied = driver.ecu[hil_topics.ECU_DAMPING_APPLIED][stamp].position
        gen = driver.ecu[hil_topics.ECU_GENERATOR][stamp]
        # The rotor speed as measured (rad/s); the generator topic carries v_gen = l·phi'.
        assert values[:4] + values[5:] == [
            applied[0], applied[1], driver.ecu[hil_topics.ECU_SPRUNG_ACCEL][stamp].accel.linear.z,
            driver.ecu[hil_topics.ECU_SUSPENSION][stamp].position[0], gen.effort[0]], stamp
        assert values[4] * l_gen == pytest.approx(gen.velocity[0], rel=1e-12, abs=1e-15)
        v_max = max(v_max, abs(gen.velocity[0]))
    assert v_max > 0
    # A cycle whose frames a stall spread over more than Ts/2 is 'incomplete' (published
    # with NaN): the estimator counts each such message it took.
    link = driver.last('ecu_bridge_node: ecu')[4]
    took = sum(int(est[k]) for k in ('updates', 'rejected', 'late_or_repeated'))
    assert int(est['rejected']) == 0 and took <= published
    assert int(est['incomplete']) <= int(link['incomplete_cycles'])
    if took == published:                       # none replaced in its queue by a stall
        # Each incomplete cycle it took was used (counted incomplete) or was not newer
        # than the last: a stalled cycle's late frame makes a fragment stamped on the
        # grid instant just used (late_or_repeated).
        assert (int(link['incomplete_cycles'])
                <= int(est['incomplete']) + int(est['late_or_repeated'])), (est, link)


def test_estimator_takes_one_message_per_cycle_and_rejects_bad_ones(tmp_path):
    from erva_ros.core.hil import topics as hil_topics
    from erva_ros.session.hil.hil_processes import hil_process_specs
    from ros_msgs import ns_to_time
    from sensor_msgs.msg import JointState

    specs = [s for s in hil_process_specs(PARAMS, env=ros_env())
             if s.name == 'state_estimator_node']
    driver = Driver()
    driver.answer = False
    procs = _start(specs, tmp_path)
    log = tmp_path / 'state_estimator_node.log'
    names = list(hil_topics.MEASUREMENT_NAMES)
    good = [12000.0, 11500.0, 0.3, 0.002, 0.05, 40.0]
    nan = float('nan')
    try:
        driver.spin(30.0, until=lambda: driver.pub_meas.get_subscription_count() >= 1)
        assert driver.pub_meas.get_subscription_count() >= 1, log.read_text()[-800:]
        stamp = None

        def send(values, names=names, velocity=(), same_stamp=False, state=False):
            """Publish one cycle's message; with ``state``, wait for the state it gives.

            (Waiting there keeps the estimator's queue of 10 from overflowing, whatever
            a stall of it: at most 9 messages without a state follow one another.)
            """
            nonlocal stamp
            # One ECU cycle after the last (not the wall clock): waiting for the base line
            # below must not look like a gap that restarts the filter.
            if stamp is None:
                stamp = time.time_ns()
            elif not same_stamp:
                stamp += 20_000_000
            m = JointState(name=list(names), position=[float(v) for v in values],
                           velocity=list(velocity))
            m.header.stamp = ns_to_time(stamp)
            n = len(driver.est)
            driver.pub_meas.publish(m)
            driver.spin(30.0 if state else 0.02, until=lambda: state and len(driver.est) > n)
            assert not state or len(driver.est) == n + 1, log.read_text()[-800:]

        # Until the estimator's reader has matched this publisher: then a base line, once
        # every message already sent is processed (its thread may still hold some) and
        # its count is on /diagnostics: two statuses in a row agreeing with the states seen.
        for _ in range(500):
            send(good)
            if driver.est:
                break
        previous, end = None, time.monotonic() + 30.0
        while time.monotonic() < end:
            driver.spin(0.6)                           # > the 0.5 s diagnostics period
            updates = driver.last('state_estimator_node')[4].get('updates')
            if updates is not None and updates == previous == str(len(driver.est)):
                break
            previous = updates
        n0 = len(driver.est)
        base = {k: int(v) for k, v in driver.last('state_estimator_node')[4].items()
                if k in ('updates', 'incomplete', 'rejected', 'late_or_repeated', 'restarts')}
        assert base['updates'] == n0 and base['rejected'] == 0, base
        for _ in range(20):
            send(good, state=True)
        send(good[:2] + [nan, nan] + good[4:], state=True)     # chassis frame lost
        send([nan, nan] + good[2:], state=True)                # status frame lost
        send(good, state=True)
        send(good, same_stamp=True)                        # repeated
        bad = [good[:2] + [nan, 0.002] + good[4:],         # NaN in part of a frame
               good[:2] + [1e3] + good[3:],                # absurd acceleration
               good[:3] + [float('inf')] + good[4:],       # infinite deflection
               [-5.0] + good[1:],                          # negative c_e
               good[:5]]                                   # wrong size
        for values in bad:
            send(values)
        send(good, names=names[::-1])                      # wrong names
        send(good, velocity=[0.0] * 6)                     # fields it does not use
        send(good, state=True)
        driver.spin(30.0, until=lambda: driver.last('state_estimator_node')[4].get(
            'updates') == str(n0 + 24))
    finally:
        _stop(procs)
        driver.close()
    values = driver.last('state_estimator_node')[4]
    delta = {k: int(values[k]) - v for k, v in base.items()}
    assert delta == {'updates': 24, 'incomplete': 2, 'rejected': 7, 'late_or_repeated': 1,
                     'restarts': 0}, (values, log.read_text()[-800:])
    assert len(driver.est) == n0 + 24
    assert all(np.all(np.isfinite(x)) for x in driver.est.values())


def test_on_the_road_grid_no_state_goes_out_before_the_first_road_sample(tmp_path):
    # With stamp_on_road_grid a cycle before the road's first sample has no grid: a state
    # stamped off it would make the NMPC take that grid and refuse every later state.
    # Such a cycle waits Ts/4 for the road, then is counted (before_road) and not
    # published; once the road runs, states are on its grid.
    from erva_ros.core.hil import topics as hil_topics
    from erva_ros.session.hil.hil_processes import hil_process_specs
    from ros_msgs import ns_to_time
    from sensor_msgs.msg import JointState

    specs = [s for s in hil_process_specs(PARAMS, env=ros_env(), stamp_on_road_grid=True)
             if s.name == 'state_estimator_node']
    driver = Driver(road=False)
    driver.answer = False
    procs = _start(specs, tmp_path)
    log = tmp_path / 'state_estimator_node.log'
    good = [12000.0, 11500.0, 0.3, 0.002, 0.05, 40.0]

    def send():
        m = JointState(name=list(hil_topics.MEASUREMENT_NAMES), position=good)
        m.header.stamp = ns_to_time(time.time_ns())
        driver.pub_meas.publish(m)
        driver.spin(0.05)

    def count(key):
        return int(driver.last('state_estimator_node')[4].get(key, 0))

    try:
        end = time.monotonic() + 60.0
        while count('before_road') < 3 and time.monotonic() < end:
            send()
        assert count('before_road') >= 3, log.read_text()[-800:]
        assert not driver.est and count('updates') == 0
        assert driver.last('state_estimator_node')[3].startswith('no road height yet')
        driver.start_road()
        end = time.monotonic() + 60.0
        while len(driver.est) < 3 and time.monotonic() < end:
            send()
        assert len(driver.est) >= 3, log.read_text()[-800:]
    finally:
        _stop(procs)
        driver.close()
    assert all((stamp - driver.t0_ns) % 20_000_000 == 0 for stamp in driver.est), (
        driver.t0_ns, sorted(driver.est)[:3])


def test_measurements_are_parsed_and_checked():
    from erva_ros.core.contract import decode_measurements, MessageRejected
    from erva_ros.core.hil.topics import MEASUREMENT_NAMES
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    def message(values, names=MEASUREMENT_NAMES):
        msg = JointState(name=list(names), position=values)
        msg.header.stamp.sec, msg.header.stamp.nanosec = 12, 340_000_000
        return serialize_message(msg)

    def parse_measurements(data):
        try:
            m = decode_measurements(data)
        except MessageRejected:
            return None
        return m.stamp_ns, (m.c_e, m.c_e_mean, m.sprung_accel, m.deflection, m.speed)

    def parse(values, names=MEASUREMENT_NAMES):
        got = parse_measurements(message(values, names))
        if got is not None:
            assert got[0] == 12_340_000_000
            return got[1]

    assert parse([1e4, 9e3, 0.3, 0.002, 0.5, 40.0]) == (
        1e4, 9e3, 0.3, 0.002, 0.5)                          # rotor speed, rad/s, as sent
    good = message([1e4, 9e3, 0.3, 0.002, 0.5, 40.0])
    assert parse_measurements(good[:-20]) is None                 # truncated CDR
    assert parse_measurements(b'\x00\x00' + good[2:]) is None    # big-endian header
    got = parse([1e4, 9e3, float('nan'), float('nan'), 0.5, 40.0])
    assert np.isnan(got[2]) and np.isnan(got[3]) and got[4] == 0.5
    assert parse([1e4, 9e3, 0.3, float('nan'), 0.5, 40.0]) is None
    assert parse([1e4, 9e3, 0.3, 0.002, 2000.0, 40.0]) is None         # 2000 rad/s
    assert parse([1e4, 9e3, 0.3, 0.002, 0.5, 2e6]) is None             # absurd force
    assert parse([1e4, 9e3, 0.3, 0.002, 0.5, 40.0], MEASUREMENT_NAMES[:5] + ('x',)) is None


def _node(name, *ros_args, timeout=60):
    return subprocess.run([sys.executable, '-m', f'erva_ros.nodes.{name}', '--ros-args',
                           '--params-file', PARAMS, *ros_args],
                          capture_output=True, text=True, env=ros_env(), cwd=REPO,
                          timeout=timeout)


@pytest.mark.parametrize('name, arg, message', [
    ('ecu_bridge_node', 'bus:=can0', "bus 'can0': expected socketcan:IFACE"),
    ('ecu_bridge_node', 'duty_max:=1.5', "'duty_max' = 1.5 is out of range"),
    ('ecu_bridge_node', 'command_timeout_periods:=0', "'command_timeout_periods' = 0"),
    ('ecu_bridge_node', 'can_log:=/nonexistent/bus.blf',
     "can_log '/nonexistent/bus.blf': directory /nonexistent does not exist"),
    ('ecu_bridge_node', 'can_log:=bus.txt', "can_log 'bus.txt': the file must end in .blf"),
    ('state_estimator_node', 'r_speed:=0.0', "'r_speed' = 0.0 is out of range"),
])
def test_bad_parameters_stop_the_node_with_one_line(name, arg, message):
    proc = _node(name, '-p', arg)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], proc.stderr


def test_hil_yaml_sections_apply_in_a_namespace(tmp_path, erva):
    # config/hil.yaml's /**/<node> sections reach a node started with -r __ns:=/erva
    # (a bare 'ecu_bridge_node:' key would be silently ignored there).
    text = open(os.path.join(REPO, 'config', 'hil.yaml')).read()
    bad = tmp_path / 'hil.yaml'
    bad.write_text(text.replace('duty_max: 0.95 ', 'duty_max: 1.5 '))
    proc = _node('ecu_bridge_node', '-r', '__ns:=/erva', '--params-file', str(bad))
    assert proc.returncode == 2 and "'duty_max' = 1.5 is out of range" in proc.stderr
    sim = erva('ecu-sim', '--bus', 'udp:40001:40002', '--hil-config', str(bad))
    assert sim.returncode == 2
    assert len(sim.stderr.strip().splitlines()) == 1 and "'duty_max' = 1.5" in sim.stderr


def test_bridge_survives_an_unopenable_bus_and_stops_cleanly():
    env = ros_env()
    p = subprocess.Popen([sys.executable, '-m', 'erva_ros.nodes.ecu_bridge_node', '--ros-args',
                          '--params-file', PARAMS, '-p', 'bus:=socketcan:erva_no_such_if'],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                         cwd=REPO)
    lines = []
    reader = threading.Thread(target=lambda: lines.extend(p.stdout), daemon=True)
    reader.start()
    try:
        # Up and running (not still importing: SIGINT then would be a KeyboardInterrupt)
        # once it says it cannot open the bus; it must go on retrying.
        end = time.monotonic() + 120.0
        while time.monotonic() < end and not any('cannot open bus' in x for x in lines):
            time.sleep(0.05)
        assert p.poll() is None, ''.join(lines)       # still running, retrying
    finally:
        p.send_signal(signal.SIGINT)
        p.wait(timeout=30)
        reader.join(timeout=10)
    out = ''.join(lines)
    assert p.returncode == 0, out
    assert 'cannot open bus' in out and 'Traceback' not in out


def test_ecu_sim_cli(erva):
    from erva_ros.core.hil.transport import free_udp_ports

    bad = erva('ecu-sim', '--bus', 'can0', timeout=60)
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines() == [
        "erva ecu-sim: error: bus 'can0': expected socketcan:IFACE, virtual:NAME or "
        'udp:LOCAL_PORT:PEER_PORT']
    nobus = erva('ecu-sim', '--bus', 'socketcan:erva_no_such_if', timeout=60)
    assert nobus.returncode == 2 and len(nobus.stderr.strip().splitlines()) == 1
    assert 'cannot open bus' in nobus.stderr
    nosession = erva('ecu-sim', '--bus', 'udp:40001:40002', '--road', 'session', timeout=60)
    assert nosession.returncode == 2 and nosession.stderr.strip().splitlines() == [
        'erva ecu-sim: error: --road session needs --params FILE (the session params file '
        'of `erva run`)']
    a, b = free_udp_ports(2)
    run = erva('ecu-sim', '--bus', f'udp:{a}:{b}', '--road', 'sine', '--duration', '0.5',
               '--json', timeout=60)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    # No bridge: the ECU stays in its start-up mode with the passive damping.
    assert out['cycles'] == 25 and out['commands_applied'] == 0 and out['power_w'] > 0
    # Three frames per cycle sent (cycle 0 too), unless a stall of this busy machine made
    # the ECU skip sending a late cycle (an overrun: integrated, not sent).
    sent = out['latency_ms']['sample_to_can']['samples']
    assert out['frames_sent'] == 3 * sent and (sent == 26 or out['overruns'] > 0), out
    assert out['mode_changes'] == '0:INIT:10000' and out['recomputed'] == 0
    assert out['latency_ms']['sample_to_applied']['samples'] == 0   # no command came


@pytest.mark.slow
def test_bench_hil_reports_every_latency(erva):
    run = erva('bench-hil', '--duration', '3', '--json', timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    out = json.loads(run.stdout)
    # It reports every figure; how many samples a 3 s run gives depends on the machine's
    # load (its figures are benchmarks), so: some.
    for key in ('bridge_ros_to_can', 'bridge_can_to_ros', 'estimator', 'sensor_to_state'):
        stats = out['latency_ms'][key]
        assert stats['samples'] > 0 and 0 < stats['p50'] <= stats['p99'] <= stats['max'], key
    assert out['errors'] == [] and out['matched'] > 0


def test_bench_hil_cores_and_bad_options(erva):
    run = erva('bench-hil', '--cores', '--samples', '50', '--json', timeout=120)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    for key in ('bridge_ros_to_can', 'bridge_can_to_ros', 'estimator_cycle'):
        assert out[key]['samples'] == 50 and 0 < out[key]['p50'] <= out[key]['max']
    bad = erva('bench-hil', '--estimator-eval', '--controllers', 'nmpc9', timeout=60)
    assert bad.returncode == 2 and bad.stderr.strip().splitlines() == [
        "erva bench-hil: error: --controllers: unknown 'nmpc9'; choose from passive, "
        'skyhook, no_preview, preview, preview_long']
