"""Bridge and simulated ECU on real python-can buses with real frames: round trip and faults.

Every test uses python-can's ``virtual`` bus (in this process) or the loopback UDP
bus, real E2E-protected frames and the real cores; time is passed explicitly where
the test checks timing rules, so nothing depends on this machine's load.
"""

import contextlib
import itertools
import math
import socket
import threading
import time

import can
import pytest

from erva_ros.core.hil.bridge import BridgeConfig, BridgeCore, ERROR, OK, WARN
from erva_ros.core.hil.codec import (Chassis, Command, CommandMode, E2EReceiver, EcuCodec, EcuMode,
                                     Generator, Kind, Status)
from erva_ros.core.hil.ecu_sim import EcuSimConfig, EcuSimCore, run_realtime, SensorNoise
from erva_ros.core.model.hardware import GeneratorHardware
from erva_ros.core.hil.transport import free_udp_ports, open_bus
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import paper_params

_channels = itertools.count()
HW = GeneratorHardware()
C_E0 = paper_params().c_e0


@pytest.fixture(scope='module')
def codec():
    return EcuCodec()


@pytest.fixture
def channel():
    return f'virtual:erva_test_{next(_channels)}'


def _bus(spec):
    return open_bus(spec)


def _drain(bus, codec, kinds=(Kind.COMMAND,)):
    """Return the decoded frames waiting on ``bus`` (real E2E checks)."""
    rx = E2EReceiver(codec, kinds, timeout_s=10.0)
    out = []
    while True:
        msg = bus.recv(0.05)
        if msg is None:
            return out, rx
        kind, status, payload = rx.accept(msg, time.monotonic())
        out.append((kind, status, payload))


def _bridge(codec, spec, clock=time.monotonic, **cfg):
    core = BridgeCore(codec, HW, BridgeConfig(c_e_safe=C_E0, **cfg), lambda: open_bus(spec),
                      clock=clock)
    assert core.open(now=-10.0)          # tests with explicit times start at 0
    return core


def test_round_trip_bridge_to_simulated_ecu_and_back(codec, channel):
    # Real threads on a real bus: what is checked holds however this machine schedules
    # them.  Timeouts are not what this test is about (tested with explicit times below):
    # both sides get one no stall of the test's threads can reach.
    ecu = EcuSimCore(make_model(paper_params()), HW, codec, lambda: open_bus(channel),
                     lambda t: 1e-3 * math.sin(2 * math.pi * 1.7 * t),
                     EcuSimConfig(c_e_safe=C_E0, command_timeout_s=60.0), SensorNoise.none())
    bridge = _bridge(codec, channel, command_timeout_s=60.0)
    samples, frames, stop = [], [], threading.Event()
    ecu_thread = threading.Thread(target=run_realtime, args=(ecu, 0.8, samples.append))

    def reader():
        while not stop.is_set():
            f = bridge.receive(0.01)
            if f is not None:
                frames.append(f)

    rx_thread = threading.Thread(target=reader)
    ecu_thread.start()
    rx_thread.start()
    while ecu_thread.is_alive():                  # the NMPC's role: a command every Ts
        bridge.submit([15000.0] * 10)
        bridge.tick()
        time.sleep(0.02)
    ecu_thread.join()
    stop.set()
    rx_thread.join()
    while True:                                   # what the reader had not taken yet
        f = bridge.receive(0.2)
        if f is None:
            break
        frames.append(f)
    try:
        summary = ecu.summary()
        # Commands arrived at all (a stalled test thread may send fewer than 40).
        assert summary['commands_applied'] >= 1 and summary['command_timeouts'] == 0
        rejected = ('bad_crc', 'repeated', 'skipped', 'wrong_length')
        assert sum(summary[f'rx_{k}'] for k in rejected) == 0
        assert ecu.mode is EcuMode.CONTROLLED
        # The ECU applies the duty the bridge computed: c_e within the duty resolution.
        assert HW.c_e_from_duty(ecu.duty) == pytest.approx(15000.0, abs=HW.c_e_full * 1e-4)
        kinds = {f.kind for f in frames}
        assert kinds == {Kind.STATUS, Kind.CHASSIS, Kind.GENERATOR}
        rx = bridge.rx_counts()
        assert rx['accepted'] == len(frames) and rx['bad_crc'] == rx['skipped'] == 0
        # Every cycle the ECU sent arrived (a cycle a stall made it skip was not sent),
        # each chassis frame with a true ECU sample (noise-free: DBC resolution only).
        sent = [s for s in samples if s.sent_at is not None]
        assert summary['frames_sent'] == 3 * len(sent) == len(frames)
        truth = [(s.sprung_accel, s.x[0] - s.x[2]) for s in sent]
        chassis = [f.payload for f in frames if f.kind is Kind.CHASSIS]
        assert len(chassis) == len(sent)
        for c, (a, d) in zip(chassis, truth):
            assert abs(c.sprung_accel - a) <= 6e-4 and abs(c.deflection - d) <= 6e-6
        # Frames sharing a stamp are one ECU cycle: each kind once, received within Ts/2
        # of the stamp.  A cycle whose frames a stall spread over more than Ts/2 is split
        # into incomplete cycles, each counted by the bridge.
        by_stamp = {}
        for f in frames:
            by_stamp.setdefault(f.stamp, []).append(f)
        for group in by_stamp.values():
            assert len({f.kind for f in group}) == len(group)
            assert all(0 <= f.rx_time - f.stamp <= 0.5 * 0.02 for f in group)
        ended = sum(len(f.cycles) for f in frames)
        assert bridge.counts['ecu_cycles'] == ended
        assert bridge.counts['incomplete_cycles'] == sum(
            1 for f in frames for c in f.cycles if not c.complete)
        assert ended in (len(by_stamp), len(by_stamp) - 1)     # the last may be open
        status = [f.payload for f in frames if f.kind is Kind.STATUS]
        assert [s.mode for s in status] == [s.mode for s in sent]
        assert all(s.c_e_applied == pytest.approx(15000.0, abs=4.0) for s in status
                   if s.mode is EcuMode.CONTROLLED)
    finally:
        bridge.close()
        ecu.close()


def test_stale_command_sends_safe_passive_and_raises_error(codec, channel):
    ecu_bus = _bus(channel)
    bridge = _bridge(codec, channel)
    try:
        bridge.tick(now=0.0)                                # no command yet
        assert bridge.diagnostics(now=0.0)[0].level == WARN
        plan = [12000.0, 13000.0, 14000.0, 15000.0]
        assert bridge.submit(plan, now=0.1) == 'sent'
        bridge.tick(now=0.12)                               # frame sent 20 ms ago: fine
        bridge.tick(now=0.131)                              # NMPC late: plan point k = 1
        assert bridge.diagnostics(now=0.131)[0].level == OK
        bridge.tick(now=0.165)                              # 65 ms > 3 periods: stale
        diag = bridge.diagnostics(now=0.165)[0]
        assert diag.level == ERROR and 'safe passive' in diag.message
        bridge.tick(now=0.175)                              # 10 ms after the last: wait
        bridge.tick(now=0.185)                              # one period later: safe again
        assert bridge.submit([11000.0], now=0.2) == 'sent'  # the NMPC is back
        assert bridge.diagnostics(now=0.2)[0].level == OK
        frames, rx = _drain(ecu_bus, codec)
        sent = [(p.mode, round(p.c_e)) for _, _, p in frames]
        assert sent == [(CommandMode.SAFE_PASSIVE, C_E0), (CommandMode.CONTROLLED, 12000),
                        (CommandMode.PLANNED, 13000), (CommandMode.SAFE_PASSIVE, C_E0),
                        (CommandMode.SAFE_PASSIVE, C_E0), (CommandMode.CONTROLLED, 11000)]
        assert all(status.accepted for _, status, _ in frames)   # counters in sequence
        duty0 = frames[0][2].duty
        assert duty0 == pytest.approx(HW.duty_from_c_e(C_E0), abs=1e-4)
        c = bridge.counts
        assert (c['command_timeouts'], c['safe_frames_sent'], c['plan_frames_sent']) == (1, 3, 1)
    finally:
        bridge.close()
        ecu_bus.shutdown()


def test_out_of_range_commands_are_clamped_and_nonfinite_rejected(codec, channel):
    ecu_bus = _bus(channel)
    bridge = _bridge(codec, channel)
    try:
        assert bridge.submit([1e5], now=0.0) == 'clamped'
        assert bridge.submit([-3000.0], now=0.02) == 'clamped'
        assert bridge.submit([math.nan], now=0.04) == 'rejected'
        assert bridge.submit([], now=0.05) == 'rejected'
        assert bridge.submit([math.inf, 1.0], now=0.06) == 'rejected'
        frames, _ = _drain(ecu_bus, codec)
        got = [(round(p.c_e), round(p.duty, 4)) for _, _, p in frames]
        assert got == [(22800, 0.95), (0, 0.0)]
        assert bridge.counts['commands_clamped'] == 2
        assert bridge.counts['commands_rejected'] == 3
        assert bridge.command_age(now=0.06) == pytest.approx(0.04)  # rejected: not fresh
    finally:
        bridge.close()
        ecu_bus.shutdown()


def test_bad_sensor_frames_are_dropped_and_counted(codec, channel):
    ecu_bus = _bus(channel)
    bridge = _bridge(codec, channel)
    tx = codec.sender(Kind.CHASSIS)
    try:
        def send(msg):
            ecu_bus.send(msg)
            return bridge.receive(0.5)

        good = codec.encode(Kind.CHASSIS, Chassis(0.25, 0.002), tx)
        assert send(good).payload.sprung_accel == pytest.approx(0.25)
        assert send(good) is None                                   # repeated counter
        corrupt = codec.encode(Kind.CHASSIS, Chassis(0.3, 0.002), tx)
        data = bytearray(corrupt.data)
        data[2] ^= 0x01
        assert send(can.Message(arbitration_id=corrupt.arbitration_id, data=data,
                                is_extended_id=False)) is None    # bad CRC
        short = codec.encode(Kind.CHASSIS, Chassis(0.3, 0.002), tx)
        assert send(can.Message(arbitration_id=short.arbitration_id, data=short.data[:6],
                                is_extended_id=False)) is None    # wrong length
        codec.encode(Kind.CHASSIS, Chassis(0.3, 0.002), tx)       # lost on the bus
        jump = codec.encode(Kind.CHASSIS, Chassis(0.35, 0.002), tx)
        assert send(jump) is None                                  # counter skipped
        ok = send(codec.encode(Kind.CHASSIS, Chassis(0.4, 0.002), tx))
        assert ok is not None and ok.payload.sprung_accel == pytest.approx(0.4)
        assert send(can.Message(arbitration_id=0x7FF, data=bytes(8),
                                is_extended_id=False)) is None    # not ours
        c = bridge.rx_counts()
        assert {k: c[k] for k in ('accepted', 'repeated', 'bad_crc', 'wrong_length',
                                  'skipped', 'unknown_id')} == {
            'accepted': 2, 'repeated': 1, 'bad_crc': 1, 'wrong_length': 1, 'skipped': 1,
            'unknown_id': 1}
        bus_diag = bridge.diagnostics()[1]
        assert bus_diag.level == WARN and '4 frames rejected' in bus_diag.message
    finally:
        bridge.close()
        ecu_bus.shutdown()


def _ecu(codec, channel, **cfg):
    return EcuSimCore(make_model(paper_params()), HW, codec, lambda: open_bus(channel),
                      lambda t: 0.0, EcuSimConfig(c_e_safe=C_E0, **cfg), SensorNoise.none())


def _command(codec, tx, at, c_e=None, duty=None, mode=CommandMode.CONTROLLED, saturate=True):
    """Return a command frame received at time ``at`` (s, on the ECU's clock)."""
    duty = HW.duty_from_c_e(c_e) if duty is None else duty
    msg = codec.encode(Kind.COMMAND, Command(duty, c_e or 0.0, mode), tx, saturate=saturate)
    msg.timestamp = at
    return msg


# The bridge side of these tests keeps the frames' timestamps (preserve_timestamps), so
# the ECU's latch and timeout rules run on an exact, made-up clock starting at T0.
T0 = 1000.0


@contextlib.contextmanager
def _ecu_started(codec, channel):
    """Yield (the bridge's side of the bus, an ECU started at T0, a command sender)."""
    bridge_bus = can.Bus(interface='virtual', channel=channel.split(':', 1)[1],
                         preserve_timestamps=True)
    ecu = _ecu(codec, channel)
    ecu.start(T0)
    try:
        yield bridge_bus, ecu, codec.sender(Kind.COMMAND)
    finally:
        ecu.close()
        bridge_bus.shutdown()


def test_ecu_applies_valid_commands_and_falls_back_after_the_timeout(codec, channel):
    with _ecu_started(codec, channel) as (bridge_bus, ecu, tx):
        bridge_bus.send(_command(codec, tx, T0 + 0.0105, 20000.0))
        ecu.run_cycle()                                   # applied at the 11 ms latch
        ecu.run_cycle()
        assert ecu.mode is EcuMode.CONTROLLED
        assert HW.c_e_from_duty(ecu.duty) == pytest.approx(20000.0, abs=3.0)
        ecu.run_cycle()                                   # 60 ms: 49.5 ms after it
        assert ecu.mode is EcuMode.CONTROLLED
        ecu.run_cycle()                                   # 71 ms latch: 60.5 ms > 60 ms
        assert ecu.mode is EcuMode.SAFE_TIMEOUT
        assert HW.c_e_from_duty(ecu.duty) == pytest.approx(C_E0)
        assert ecu.counts['command_timeouts'] == 1
        frames, _ = _drain(bridge_bus, codec, (Kind.STATUS,))
        status = [p for k, _, p in frames if k is Kind.STATUS]
        assert [s.mode for s in status] == [
            EcuMode.INIT, EcuMode.CONTROLLED, EcuMode.CONTROLLED, EcuMode.CONTROLLED,
            EcuMode.SAFE_TIMEOUT]
        assert status[-1].cmd_timeouts == 1
        # The cycle's mean damping tells the estimator what really acted:
        # 11 ms of c_e0 then 9 ms of 20 kNs/m; in the last cycle 11 ms then c_e0.
        assert status[1].c_e_mean == pytest.approx((11 * C_E0 + 9 * 20000.0) / 20, abs=4)
        assert status[4].c_e_mean == pytest.approx((11 * 20000.0 + 9 * C_E0) / 20, abs=4)


def test_a_timeout_ended_within_its_cycle_is_in_the_mode_log(codec, channel):
    # A timeout that the next command ends before the sample is invisible in the status
    # (it tells the mode at t_k), so the mode record logs it at its latch instant.
    with _ecu_started(codec, channel) as (bridge_bus, ecu, tx):
        bridge_bus.send(_command(codec, tx, T0 + 0.0105, 20000.0))
        for _ in range(3):
            ecu.run_cycle()
        # Timeout at the 71 ms latch (60.5 ms after the command), the next one at 75 ms.
        bridge_bus.send(_command(codec, tx, T0 + 0.0745, 15000.0))
        ecu.run_cycle()
        assert ecu.mode is EcuMode.CONTROLLED and ecu.counts['command_timeouts'] == 1
        changes = [c.split(':') for c in ecu.mode_changes().split(',')]
        assert [(int(k), m) for k, m, _ in changes] == [
            (0, 'INIT'), (1, 'CONTROLLED'), (4, 'SAFE_TIMEOUT'), (4, 'CONTROLLED')]
        assert [float(c_e) for _, _, c_e in changes] == pytest.approx(
            [C_E0, 20000.0, C_E0, 15000.0], abs=3.0)
        frames, _ = _drain(bridge_bus, codec, (Kind.STATUS,))
        status = [p for k, _, p in frames if k is Kind.STATUS]
        assert EcuMode.SAFE_TIMEOUT not in [s.mode for s in status]
        assert status[-1].cmd_timeouts == 1
        # 4 ms of c_e0 in the cycle's mean: 11 ms of 20 kNs/m, 4 of c_e0, 5 of 15 kNs/m.
        assert status[-1].c_e_mean == pytest.approx((11 * 20000.0 + 4 * C_E0 + 5 * 15000.0)
                                                    / 20, abs=4)


def test_the_mode_log_counts_what_it_cannot_hold(codec, channel):
    from erva_ros.core.hil.ecu_sim import MODE_LOG_SIZE
    with _ecu_started(codec, channel) as (bridge_bus, ecu, tx):
        # Alternate CONTROLLED and SAFE_REQUESTED every cycle: one change per cycle.
        for k in range(MODE_LOG_SIZE + 10):
            mode = CommandMode.CONTROLLED if k % 2 == 0 else CommandMode.SAFE_PASSIVE
            bridge_bus.send(_command(codec, tx, T0 + 0.02 * k + 0.005, 15000.0, mode=mode))
            ecu.run_cycle()
        logged = ecu.mode_changes().split(',')
        assert len(logged) == MODE_LOG_SIZE and logged[0] == '0:INIT:10000'
        # INIT, then one change per cycle: MODE_LOG_SIZE + 10 changes after it.
        assert ecu.counts['mode_changes_unlogged'] == MODE_LOG_SIZE + 10 - (MODE_LOG_SIZE - 1)


def test_ecu_drops_corrupt_and_out_of_sequence_commands_and_clamps_duty(codec, channel):
    with _ecu_started(codec, channel) as (bridge_bus, ecu, tx):
        corrupt = _command(codec, tx, T0 + 0.005, 15000.0)
        data = bytearray(corrupt.data)
        data[3] ^= 0x40
        bridge_bus.send(can.Message(timestamp=T0 + 0.005, arbitration_id=0x100, data=data,
                                    is_extended_id=False))
        ecu.run_cycle()
        assert ecu.mode is EcuMode.INIT and ecu.counts['commands_applied'] == 0
        bridge_bus.send(_command(codec, tx, T0 + 0.025, duty=1.5, saturate=False))  # good CRC
        ecu.run_cycle()
        assert ecu.duty == HW.duty_max and ecu.counts['duty_out_of_range'] == 1
        tx.counter = (tx.counter + 3) % 15                                   # counter jump
        bridge_bus.send(_command(codec, tx, T0 + 0.045, 5000.0))
        ecu.run_cycle()
        assert ecu.duty == HW.duty_max                   # the jumped frame was not applied
        bridge_bus.send(_command(codec, tx, T0 + 0.065, 5000.0))   # next in sequence
        ecu.run_cycle()
        assert HW.c_e_from_duty(ecu.duty) == pytest.approx(5000.0, abs=3.0)
        summary = ecu.summary()
        assert (summary['rx_bad_crc'], summary['rx_skipped']) == (1, 1)
        frames, _ = _drain(bridge_bus, codec, (Kind.STATUS,))
        status = [p for k, _, p in frames if k is Kind.STATUS]
        assert status[-1].cmd_rejected == 2                # reported to the bridge


def test_bus_loss_is_reported_and_retried_without_crashing(codec):
    bridge_port, ecu_port = free_udp_ports(2)
    ecu_bus = open_bus(f'udp:{ecu_port}:{bridge_port}')
    bridge = _bridge(codec, f'udp:{bridge_port}:{ecu_port}', bus_retry_s=0.5)
    blocker = None
    try:
        assert bridge.submit([12000.0], now=0.0) == 'sent'
        assert ecu_bus.recv(1.0) is not None
        # The interface goes away: the bus is closed under the bridge and its address is
        # taken, so re-opening fails until it is released.
        bridge.bus.shutdown()
        blocker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        blocker.bind(('127.0.0.1', bridge_port))
        assert bridge.submit([12000.0], now=0.01) == 'not_sent'
        assert bridge.receive(0.01) is None
        c = bridge.counts
        assert (c['send_errors'], c['bus_losses']) == (1, 1)
        diag = bridge.diagnostics(now=0.01)[1]
        assert diag.level == ERROR and 'bus lost' in diag.message
        bridge.tick(now=0.02)                                # retry at once: fails
        bridge.tick(now=0.1)                                 # not yet: bus_retry_s
        bridge.tick(now=0.53)                                # second attempt: fails
        assert (c['bus_open_attempts'], c['bus_open_failures']) == (3, 2)
        assert 'cannot open bus' in bridge.diagnostics(now=0.6)[1].message
        assert bridge.submit([12000.0], now=0.7) == 'not_sent'
        assert c['frames_not_sent'] >= 2
        blocker.close()
        blocker = None
        bridge.tick(now=0.9)                                 # not yet
        assert not bridge.bus_up
        bridge.tick(now=1.2)                                 # the interface is back
        assert bridge.bus_up and c['reconnects'] == 1
        assert bridge.diagnostics(now=1.2)[1].level == OK
        assert bridge.submit([13000.0], now=1.21) == 'sent'
        frames, _ = _drain(ecu_bus, codec)
        assert frames and round(frames[-1][2].c_e) == 13000
        # A loss seen by the reader thread (recv fails) is handled the same way.
        bridge.bus.shutdown()
        assert bridge.receive(0.01) is None
        assert c['bus_losses'] == 2 and not bridge.bus_up
    finally:
        if blocker is not None:
            blocker.close()
        bridge.close()
        ecu_bus.shutdown()


def test_a_full_transmit_queue_drops_the_frame_but_keeps_the_bus(codec, channel):
    # The ECU side stops reading and its receive queue (1 frame) stays full: python-can's
    # virtual bus then fails the send after the timeout, like ENOBUFS on SocketCAN.
    ecu_bus = can.Bus(interface='virtual', channel=channel.split(':', 1)[1], rx_queue_size=1)
    bridge = _bridge(codec, channel)
    try:
        assert bridge.submit([12000.0], now=0.0) == 'sent'
        assert bridge.submit([12500.0], now=0.02) == 'not_sent'
        c = bridge.counts
        assert (c['send_errors'], c['bus_losses']) == (1, 0) and bridge.bus_up
        assert 'frame dropped' in bridge.diagnostics(now=0.02)[1].error
        assert ecu_bus.recv(0.1) is not None                 # the ECU reads again
        assert bridge.submit([13000.0], now=0.04) == 'sent'
        frames, _ = _drain(ecu_bus, codec)
        assert [round(p.c_e) for _, _, p in frames] == [13000]
    finally:
        bridge.close()
        ecu_bus.shutdown()


def test_ecu_status_heartbeat_and_silence(codec, channel):
    ecu_bus = _bus(channel)
    # The bridge's clock is the test's: a stall of this process between two lines must
    # not count as the ECU's silence.
    now = [0.0]
    bridge = _bridge(codec, channel, clock=lambda: now[0], sensor_timeout_s=0.06)
    try:
        assert bridge.diagnostics()[2].level == ERROR             # nothing heard yet
        tx = codec.sender(Kind.STATUS)
        ecu_bus.send(codec.encode(Kind.STATUS, Status(EcuMode.SAFE_TIMEOUT, C_E0, C_E0, 0, 4),
                                  tx))
        assert bridge.receive(0.5).kind is Kind.STATUS
        d = bridge.diagnostics()[2]
        assert d.level == WARN and 'SAFE_TIMEOUT' in d.message
        assert d.ecu_cmd_timeouts_mod256 == 4
        now[0] = 0.05                                             # not yet silent
        bridge.tick()
        assert bridge.diagnostics()[2].level == WARN
        now[0] = 0.08
        bridge.tick()
        d = bridge.diagnostics()[2]
        assert d.level == ERROR and 'ECU silent' in d.message
        assert bridge.counts['ecu_silences'] == 1
    finally:
        bridge.close()
        ecu_bus.shutdown()


def test_each_ecu_cycle_is_handed_out_once_whole_even_with_a_lost_frame(codec, channel):
    # What ecu_bridge_node publishes as ecu/measurements: one EcuCycle per ECU cycle, with
    # the cycle's stamp and payloads; a lost frame's kind is absent.  The frames carry
    # made-up receive times (a stall of this process between two sends must not split a
    # cycle by the Ts/2 rule).
    ecu_bus = can.Bus(interface='virtual', channel=channel.split(':', 1)[1],
                      preserve_timestamps=True)
    now = [100.0]
    bridge = BridgeCore(codec, HW, BridgeConfig(c_e_safe=C_E0), lambda: open_bus(channel),
                        clock=lambda: now[0])
    assert bridge.open()
    tx = {k: codec.sender(k) for k in (Kind.STATUS, Kind.CHASSIS, Kind.GENERATOR)}
    payloads = {Kind.STATUS: Status(EcuMode.CONTROLLED, 15000.0, 14000.0, 0, 0),
                Kind.CHASSIS: Chassis(0.25, 0.002), Kind.GENERATOR: Generator(3.0, 1.5, 10.0)}
    try:
        def send(kind, after=0.0):
            msg = codec.encode(kind, payloads[kind], tx[kind])
            msg.timestamp = now[0] + after          # received `after` s into the cycle
            ecu_bus.send(msg)
            return bridge.receive(0.5)

        frames = [send(k, 1e-4 * i) for i, k in enumerate(
            (Kind.STATUS, Kind.CHASSIS, Kind.GENERATOR))]
        assert [len(f.cycles) for f in frames] == [0, 0, 1]
        cyc = frames[2].cycles[0]
        assert cyc.complete and cyc.stamp == frames[0].stamp == frames[2].stamp
        assert cyc.payloads == {f.kind: f.payload for f in frames}
        assert cyc.rx_time == frames[2].rx_time
        assert bridge.expire(now=now[0] + 1.0) is None            # nothing left open
        # The next cycle loses its chassis frame: it ends, without it, at the next
        # cycle's first frame...
        now[0] += 0.02
        first, gen = send(Kind.STATUS), send(Kind.GENERATOR, 2e-4)
        nxt = send(Kind.STATUS, 0.02)
        assert first.cycles == () and gen.cycles == ()
        (lost,) = nxt.cycles
        assert not lost.complete and set(lost.payloads) == {Kind.STATUS, Kind.GENERATOR}
        assert lost.stamp == first.stamp == gen.stamp != nxt.stamp
        # ... or Ts/2 after its first frame (the bridge node's Ts/4 watchdog check), once.
        assert bridge.expire(now=now[0] + 0.009) is None
        late = bridge.expire(now=now[0] + 0.011)
        assert late is not None and set(late.payloads) == {Kind.STATUS}
        assert late.stamp == nxt.stamp and bridge.expire(now=now[0] + 1.0) is None
        assert (bridge.counts['ecu_cycles'], bridge.counts['incomplete_cycles']) == (3, 2)
    finally:
        bridge.close()
        ecu_bus.shutdown()


def test_cycle_assembler_alone():
    from erva_ros.core.hil.ecu_cycles import CycleAssembler
    st, ch, gen = Kind.STATUS, Kind.CHASSIS, Kind.GENERATOR
    cycles = CycleAssembler(0.02)
    # Any order; the stamp is the first frame's receive time; complete at the third.
    assert cycles.add(gen, 'g0', 10.0001, 5.0) == (10.0001, ())
    assert cycles.add(st, 's0', 10.0002, 5.0) == (10.0001, ())
    stamp, (done,) = cycles.add(ch, 'c0', 10.0003, 5.0)
    assert stamp == done.stamp == 10.0001 and done.complete and done.rx_time == 10.0003
    assert done.payloads == {gen: 'g0', st: 's0', ch: 'c0'}
    # A kind repeating ends the open cycle; so does a frame more than Ts/2 after its stamp.
    cycles.add(st, 's1', 10.02, 5.02)
    stamp, (lost,) = cycles.add(st, 's2', 10.021, 5.021)
    assert stamp == 10.021 and lost.payloads == {st: 's1'} and not lost.complete
    stamp, (lost,) = cycles.add(ch, 'c2', 10.0311, 5.0311)
    assert stamp == 10.0311 and lost.payloads == {st: 's2'}
    # Expiry: Ts/2 after the open cycle began on the caller's clock, once.
    assert cycles.expire(5.0311 + 0.01) is None
    late = cycles.expire(5.0311 + 0.0101)
    assert late.payloads == {ch: 'c2'} and cycles.expire(9.0) is None
    cycles.add(st, 's3', 10.06, 5.06)
    cycles.reset()                                  # a re-opened bus: the cycle is gone
    assert cycles.expire(9.0) is None
    assert cycles.counts == {'ecu_cycles': 4, 'incomplete_cycles': 3}


def test_ecu_heartbeat_counts_each_silence_once():
    from erva_ros.core.hil.ecu_cycles import EcuHeartbeat
    hb = EcuHeartbeat(timeout_s=0.06)
    assert not hb.ever_heard and hb.silent(0.0)
    hb.check(1.0)
    assert hb.counts['ecu_silences'] == 0           # never heard: not a silence (yet)
    hb.heard(Kind.CHASSIS, 'c', 1.0)
    hb.check(1.059)
    assert not hb.silent(1.059) and hb.counts['ecu_silences'] == 0
    for t in (1.061, 1.2, 1.5):
        hb.check(t)
    assert hb.silent(1.061) and hb.counts['ecu_silences'] == 1
    hb.heard(Kind.STATUS, 's', 2.0)
    hb.check(2.1)
    assert hb.counts['ecu_silences'] == 2 and hb.last == {Kind.CHASSIS: 'c', Kind.STATUS: 's'}


def test_bus_link_retries_at_its_pace_and_counts(codec, channel):
    from erva_ros.core.hil.bus_link import BusLink
    attempts = []

    def factory():
        attempts.append(1)
        if len(attempts) <= 2:
            raise OSError('no such device')
        return open_bus(channel)

    link = BusLink(factory, retry_s=0.5)
    try:
        assert not link.open(0.0) and 'cannot open bus: no such device' in link.error
        for t in (0.1, 0.49, 0.5, 0.9, 1.0):
            link.retry(t)
        assert link.up and len(attempts) == 3 and link.error == ''
        assert link.counts == {'frames_not_sent': 0, 'send_errors': 0, 'bus_losses': 0,
                               'bus_open_attempts': 3, 'bus_open_failures': 2,
                               'reconnects': 0}
        bus = link.bus
        link.lost(bus, OSError('gone'))
        link.lost(bus, OSError('gone'))             # the other thread saw it too: once
        assert not link.up and link.counts['bus_losses'] == 1 and link.error == 'bus lost: gone'
        assert not link.send(can.Message(arbitration_id=1, data=b''))
        link.retry(1.4)                             # 0.4 s after the last attempt: not yet
        assert not link.up
        link.retry(1.5)
        assert link.up and link.counts['reconnects'] == 1 and link.counts['frames_not_sent'] == 1
    finally:
        link.close()


def test_bridge_counters_read_as_one_mapping_written_in_their_unit(codec, channel):
    bridge = _bridge(codec, channel)
    try:
        units = (bridge.watchdog, bridge.link, bridge.cycles, bridge.heartbeat)
        names = [n for u in units for n in u.counts]
        assert sorted(bridge.counts) == sorted(names) and len(set(names)) == len(names)
        bridge.counts['commands_rejected'] += 1     # as a caller may count a refusal
        bridge.watchdog.reject()
        assert bridge.watchdog.counts['commands_rejected'] == 2
        assert dict(bridge.counts)['commands_rejected'] == 2
        with pytest.raises(TypeError):
            del bridge.counts['frames_sent']
        with pytest.raises(KeyError):
            bridge.counts['no_such_counter']
    finally:
        bridge.close()


def _road(t):
    return 1e-3 * math.sin(2 * math.pi * 1.7 * (t - T0))


def _ecu_on_road(codec, channel):
    return EcuSimCore(make_model(paper_params()), HW, codec, lambda: open_bus(channel), _road,
                      EcuSimConfig(c_e_safe=C_E0), SensorNoise.none())


def test_ecu_integrated_ahead_equals_integrated_at_the_sample(codec):
    # The ECU integrates each cycle ahead (prepare) and sends at the sample instant. A
    # command that arrives after the preparation (inside the cycle) makes it integrate
    # again: bit for bit the plant of an ECU that integrated only at the sample.
    names = [f'erva_ahead_{next(_channels)}' for _ in range(2)]
    buses = [can.Bus(interface='virtual', channel=n, preserve_timestamps=True) for n in names]
    ahead, late = (_ecu_on_road(codec, f'virtual:{n}') for n in names)
    txs = [codec.sender(Kind.COMMAND) for _ in names]
    try:
        for ecu in (ahead, late):
            ecu.start(T0)
        got = {id(ahead): [], id(late): []}
        for k in range(8):
            t_k = T0 + 0.02 * k
            # The NMPC's answer 6.5 ms after each sample; in cycles 3 and 5 a second one
            # lands after the ahead-of-time integration (17 ms = Ts - prepare_lead_s).
            arrivals = [(t_k + 0.0065, 12000.0 + 1000.0 * k)]
            if k in (3, 5):
                arrivals.append((t_k + 0.0185, 5000.0))
            for bus, tx in zip(buses, txs):
                bus.send(_command(codec, tx, *arrivals[0]))
            ahead.prepare()
            for bus, tx in zip(buses, txs):
                for at, c_e in arrivals[1:]:
                    bus.send(_command(codec, tx, at, c_e))
            for ecu in (ahead, late):
                s = ecu.run_cycle()
                got[id(ecu)].append((s.x.tolist(), s.c_e, s.c_e_mean, s.harvested_j,
                                     s.command_latched, s.mode))
        assert got[id(ahead)] == got[id(late)]
        assert ahead.counts['recomputed'] == 2 and late.counts['recomputed'] == 0
        # The first command of each cycle is applied at the next 1 ms latch: 7 ms.
        assert [round(v[4] - T0 - 0.02 * k, 6) for k, v in enumerate(got[id(ahead)])] == [
            0.007] * 8
        assert ahead.counts['commands_applied'] == 10
        assert ahead.mode_changes() == '0:INIT:10000,1:CONTROLLED:12000'
    finally:
        for ecu in (ahead, late):
            ecu.close()
        for bus in buses:
            bus.shutdown()


def test_known_road_is_the_road_node_grid_and_counts_mismatches():
    from erva_ros.core.hil.road_buffer import KnownRoad
    from erva_ros.core.road.profiles import make_road

    road = make_road('paper', 4.0, ts=0.02, seed=3)
    known = KnownRoad(road.height, road.speed_mps, 0.02)
    origin = 1_700_000_000_000_000_000
    k0 = 7                                  # the first message the ECU sees: sample 7
    known.anchor(origin + k0 * 20_000_000, road.distance(k0 * 0.02))
    assert known.origin_ns == origin
    for k in range(k0, k0 + 50):            # what road_preview_node publishes
        assert known.check(origin + k * 20_000_000, road.height(k * 0.02))
    assert not known.check(origin + 60 * 20_000_000, road.height(61 * 0.02))
    assert not known.check(origin + 60 * 20_000_000 + 1000, road.height(60 * 0.02))
    assert (known.checked, known.mismatches) == (52, 2)
    # Between samples: linear, as the estimator sees the road; on them: the exact values.
    t10 = (origin + 10 * 20_000_000) * 1e-9
    assert known.height(t10) == road.height(0.2)
    w10, w11 = road.height(0.2), road.height(0.22)
    # (epoch seconds as floats are 0.2 us coarse: 1e-5 of a period)
    assert known.height(t10 + 0.005) == pytest.approx(w10 + 0.25 * (w11 - w10), abs=1e-8)


def test_bridge_refuses_commands_that_arrive_stale_and_records_its_timeouts(codec, channel):
    ecu_bus = _bus(channel)
    bridge = _bridge(codec, channel)
    try:
        assert bridge.submit([12000.0] * 5, now=0.0, age_s=0.006) == 'sent'
        # Queued by DDS while a link was down: older than the 3-period timeout.
        assert bridge.submit([15000.0] * 5, now=0.01, age_s=0.0601) == 'stale'
        assert bridge.submit([15000.0] * 5, now=0.01, age_s=math.nan) == 'stale'
        assert bridge.counts['commands_stale'] == 2
        for t in (0.02, 0.03, 0.06, 0.065):     # plan frames at 30 and 60 ms, safe at 65 ms
            bridge.tick(now=t)
        assert bridge.command_state == 'timeout'
        assert bridge.timeouts_worst == {'plan_frames': 2, 'command_age_s': 0.065}
        cmd = bridge.diagnostics(now=0.065)[0]
        assert (cmd.commands_stale, cmd.timeout_plan_frames_max,
                cmd.timeout_age_ms_max) == (2, 2, 65.0)
        frames, _ = _drain(ecu_bus, codec)
        assert [round(p.c_e) for _, _, p in frames] == [12000, 12000, 12000, C_E0]
    finally:
        bridge.close()
        ecu_bus.shutdown()
