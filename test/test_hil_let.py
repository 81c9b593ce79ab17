"""Logical execution time in the HIL loop: the ECU applies each command at t_k + d.

The bridge names the cycle in each command frame (CMD_CYCLE, E2E-protected) and sends
the plan's next values ahead (PLANNED); the simulated ECU applies, at t_k + d on its own
clock, the newest frame received for cycle k by then.  A frame received after its
instant is late: counted, never applied -- the late rule of plant_sim_node
(core/loop/command_hold.py), which the ECU matches cycle by cycle.  Real frames on
python-can's virtual bus; their receive times are made up (a clock starting at T0), so
nothing depends on this machine's load.
"""

import itertools
import math

import can
import numpy as np
import pytest

from erva_ros.core.hil.bridge import BridgeConfig, BridgeCore
from erva_ros.core.hil.codec import (Command, CommandMode, cycle_of, CYCLE_MODULO, E2EReceiver,
                                     EcuCodec, EcuMode, Kind, unwrap_cycle)
from erva_ros.core.hil.e2e import E2EStatus
from erva_ros.core.hil.ecu_sim import EcuSimConfig, EcuSimCore, SensorNoise
from erva_ros.core.model.hardware import GeneratorHardware
from erva_ros.core.hil.transport import open_bus
from erva_ros.core.loop.command_hold import CommandHold
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import paper_params
from erva_ros.core.model.plant import PlantSimulator

HW = GeneratorHardware()
C_E0 = paper_params().c_e0
TS, D = 0.02, 0.010
TS_NS, D_NS = 20_000_000, 10_000_000
T0 = 1000.0                       # the ECU's cycle 0 (epoch s): cycle number 50000
T0_NS = 1_000_000_000_000
K0 = 50_000
_channels = itertools.count()


@pytest.fixture(scope='module')
def codec():
    return EcuCodec()


def _road(t):
    return 1e-3 * math.sin(2 * math.pi * 1.7 * (t - T0))


class _Ecu:
    """An ECU with d = 10 ms started at T0, and a sender that stamps frames' arrivals."""

    def __init__(self, codec, road=lambda t: 0.0, **cfg):
        name = f'erva_let_{next(_channels)}'
        self.codec = codec
        self.bus = can.Bus(interface='virtual', channel=name, preserve_timestamps=True)
        self.core = EcuSimCore(make_model(paper_params()), HW, codec,
                               lambda: open_bus(f'virtual:{name}'), road,
                               EcuSimConfig(c_e_safe=C_E0, command_delay_s=D, **cfg),
                               SensorNoise.none())
        self.tx = codec.sender(Kind.COMMAND)
        self.core.start(T0)

    def send(self, at, c_e, k, mode=CommandMode.CONTROLLED):
        """Send the frame for cycle k (index from T0), received at ``at`` (s after T0)."""
        cycle = 0 if mode is CommandMode.SAFE_PASSIVE else (K0 + k) % CYCLE_MODULO
        msg = self.codec.encode(Kind.COMMAND, Command(HW.duty_from_c_e(c_e), c_e, mode, cycle),
                                self.tx)
        msg.timestamp = T0 + at
        self.bus.send(msg)

    def resend(self, msg, at):
        """Send a frame the bridge made, received at ``at`` (s after T0)."""
        msg.timestamp = T0 + at
        self.bus.send(msg)

    def close(self):
        self.core.close()
        self.bus.shutdown()


@pytest.fixture
def ecu(codec):
    e = _Ecu(codec)
    yield e
    e.close()


def _wire(codec, c_e):
    """Return c_e as the ECU applies it: through the frame's duty."""
    msg = codec.encode(Kind.COMMAND, Command(HW.duty_from_c_e(c_e), c_e, CommandMode.CONTROLLED),
                       codec.sender(Kind.COMMAND))
    return HW.c_e_from_duty(HW.clamp_duty(codec.decode(Kind.COMMAND, msg.data).duty)[0])


def test_the_cycle_signal_round_trips_and_is_e2e_protected(codec):
    for mode, cycle in ((CommandMode.CONTROLLED, 0), (CommandMode.PLANNED, 137),
                        (CommandMode.CONTROLLED, 255)):
        rx = E2EReceiver(codec, [Kind.COMMAND], timeout_s=0.06)
        msg = codec.encode(Kind.COMMAND, Command(0.5, 12000.0, mode, cycle),
                           codec.sender(Kind.COMMAND))
        _, status, got = rx.accept(msg, 0.0)
        assert status is E2EStatus.INITIAL and (got.mode, got.cycle) == (mode, cycle)
        assert msg.data[6] == cycle and msg.data[7] == 0     # CMD_CYCLE: byte 6
        for bit in range(8):                                  # the CRC covers it
            data = bytearray(msg.data)
            data[6] ^= 1 << bit
            checker = codec.checker(Kind.COMMAND, 0.06)
            assert checker.check(bytes(data), 0.0) is E2EStatus.BAD_CRC
    # The cycle of a sample instant, and back from its 8 bits near the ECU's own cycle.
    assert cycle_of(T0_NS, TS_NS) == K0 and cycle_of(T0_NS + 9_999_999, TS_NS) == K0
    assert cycle_of(T0_NS + 10_000_000, TS_NS) == K0 + 1
    for k in (K0 - 128, K0 - 1, K0, K0 + 3, K0 + 127):
        assert unwrap_cycle(k % CYCLE_MODULO, K0) == k


def test_each_command_acts_at_its_cycle_instant_as_the_shared_model(codec):
    # Commands arrive 6.5 ms after their sample; each acts at t_k + 10 ms: the cycle is
    # PlantSimulator.step_delayed's (plant_sim_node's) to rounding.
    e = _Ecu(codec, _road)
    ref = PlantSimulator(make_model(paper_params()), TS)
    acting = HW.c_e_from_duty(HW.duty_from_c_e(C_E0))
    try:
        for k in range(8):
            u = 12000.0 + 1000.0 * k
            e.send(TS * k + 0.0065, u, k)
            e.core.prepare()
            s = e.core.run_cycle()
            ref.step_delayed(acting, _wire(codec, u), D, _road(T0 + TS * k),
                             _road(T0 + TS * (k + 1)))
            acting = _wire(codec, u)
            np.testing.assert_allclose(s.x, ref.x, rtol=0, atol=1e-12)
            assert s.harvested_j == pytest.approx(ref.harvested_j, rel=1e-12)
            assert s.command_latched == pytest.approx(T0 + TS * k + D, abs=1e-9)
            # The cycle's mean damping: 10 ms of the previous command, 10 of this one.
            assert s.c_e_mean == pytest.approx((acting + (HW.c_e_from_duty(
                HW.duty_from_c_e(C_E0)) if k == 0 else _wire(codec, u - 1000.0))) / 2)
        c = e.core.counts
        assert (c['u_from_command'], c['late_commands'], c['command_timeouts']) == (8, 0, 0)
        assert e.core.first_late_cycle is None
        s = e.core.arrival.summary()
        assert s['samples'] == 8 and s['p50'] == pytest.approx(6.5, abs=1e-6)
        assert e.core.arrival.quantile(0.999) == pytest.approx(0.0065, abs=1e-9)
    finally:
        e.close()


def test_a_late_command_never_acts_its_predecessors_plan_does(ecu):
    ecu.send(0.006, 12000.0, 0)
    ecu.send(0.006, 13000.0, 1, CommandMode.PLANNED)      # command 0's plan for cycle 1
    ecu.core.run_cycle()
    ecu.send(TS + 0.0105, 15000.0, 1)                      # 0.5 ms after t_1 + d: late
    s = ecu.core.run_cycle()
    assert s.c_e == pytest.approx(13000.0, abs=3)          # the plan acted, not 15000
    ecu.send(2 * TS + 0.004, 16000.0, 2, CommandMode.PLANNED)
    ecu.send(2 * TS + 0.0099, 17000.0, 2)                  # the newest by t_2 + d wins
    s = ecu.core.run_cycle()
    assert s.c_e == pytest.approx(17000.0, abs=3)
    c = ecu.core.counts
    assert (c['late_commands'], c['u_from_command'], c['u_from_plan']) == (1, 2, 1)
    assert ecu.core.first_late_cycle == 1 and ecu.core.arrival.summary()['samples'] == 3
    # No frame for cycle 3 at its instant: passive c_e0, a timeout (the plan ran out).
    s = ecu.core.run_cycle()
    assert s.mode is EcuMode.SAFE_TIMEOUT and s.c_e == pytest.approx(C_E0)
    assert (c['u_from_passive'], c['command_timeouts']) == (1, 1)
    # The same cycle's c_e: 10 ms of 17 kNs/m, then c_e0.
    assert s.c_e_mean == pytest.approx((17000.0 + C_E0) / 2, abs=3)
    assert ecu.core.mode_changes().split(',')[-1].startswith('4:SAFE_TIMEOUT')


def test_safe_frames_act_at_once_and_cancel_the_plan(ecu):
    ecu.send(0.006, 12000.0, 0)
    ecu.send(0.006, 13000.0, 1, CommandMode.PLANNED)
    ecu.send(0.0125, C_E0, 0, CommandMode.SAFE_PASSIVE)   # after the command acted
    s = ecu.core.run_cycle()
    # 10 ms of c_e0 (INIT), 3 of 12 kNs/m, the safe command from the 13 ms latch on.
    assert s.mode is EcuMode.SAFE_REQUESTED
    assert s.c_e_mean == pytest.approx((17 * C_E0 + 3 * _wire(ecu.codec, 12000.0)) / 20)
    s = ecu.core.run_cycle()                               # the plan for cycle 1: cancelled
    assert s.mode is EcuMode.SAFE_REQUESTED and s.c_e == pytest.approx(C_E0)
    assert ecu.core.counts['u_from_plan'] == 0 and ecu.core.counts['u_from_passive'] == 1


def test_the_receive_timeout_still_guards_the_ecu(ecu):
    # Frames for cycles far ahead keep coming in no more: 60 ms after the last one the
    # ECU is passive at once, and what it held for later cycles is gone.
    ecu.send(0.006, 12000.0, 0)
    for j in (1, 2, 3, 4):
        ecu.send(0.006, 12000.0 + 100 * j, j, CommandMode.PLANNED)
    modes = [ecu.core.run_cycle().mode for _ in range(5)]
    assert modes[:3] == [EcuMode.CONTROLLED] * 3 and modes[3:] == [EcuMode.SAFE_TIMEOUT] * 2
    assert ecu.core.counts['command_timeouts'] == 1
    assert ecu.core.counts['u_from_plan'] == 2       # cycles 1, 2; 3 and 4 never acted


def test_the_actuation_instant_is_timed_on_the_ecus_clock(ecu):
    assert ecu.core.act_due == pytest.approx(T0 + D)
    lag = ecu.core.actuate(now=lambda: T0 + D + 0.00013)
    assert lag == pytest.approx(0.00013) and ecu.core.act_due is None   # taken once
    ecu.core.run_cycle()
    assert ecu.core.act_due == pytest.approx(T0 + TS + D)
    assert ecu.core.actuation.summary()['samples'] == 1


def test_the_bridge_names_the_cycle_sends_the_plan_ahead_and_refuses_old_stamps(codec):
    name = f'erva_let_{next(_channels)}'
    reader = can.Bus(interface='virtual', channel=name)
    bridge = BridgeCore(codec, HW, BridgeConfig(c_e_safe=C_E0, command_delay_s=D),
                        lambda: open_bus(f'virtual:{name}'))
    try:
        assert bridge.open(now=0.0)
        plan = [12000.0, 13000.0, 14000.0, 15000.0, 16000.0, 17000.0]
        stamp = T0_NS + 7 * TS_NS
        assert bridge.submit(plan, now=0.0, age_s=0.006, stamp_ns=stamp) == 'sent'
        assert bridge.submit(plan, now=0.001, stamp_ns=stamp) == 'stale'   # not newer
        assert bridge.submit(plan, now=0.001) == 'stale'                   # no stamp
        for t in (0.005, 0.031, 0.052):      # fresh: no plan frames from the watchdog
            bridge.tick(now=t)
        rx = E2EReceiver(codec, [Kind.COMMAND], timeout_s=1.0)
        got = []
        while (msg := reader.recv(0.05)) is not None:
            _, status, p = rx.accept(msg, 0.0)
            assert status.accepted
            got.append((p.mode, p.cycle, round(p.c_e)))
        # Points up to the 3-period timeout after the sample go out as PLANNED.
        assert got == [(CommandMode.CONTROLLED, (K0 + 7) % 256, 12000),
                       (CommandMode.PLANNED, (K0 + 8) % 256, 13000),
                       (CommandMode.PLANNED, (K0 + 9) % 256, 14000),
                       (CommandMode.PLANNED, (K0 + 10) % 256, 15000)]
        assert (bridge.counts['commands_stale'], bridge.counts['plan_frames_sent']) == (2, 3)
        bridge.watchdog.reject(wrong_delay=True)
        cmd = bridge.diagnostics(now=0.06)[0]
        assert (cmd.commands_wrong_delay, cmd.commands_rejected) == (1, 1)
    finally:
        bridge.close()
        reader.shutdown()


def test_bridge_and_ecu_follow_the_plants_late_rule_cycle_by_cycle(codec):
    # The bridge's frames, received at made-up times: 6 ms after the sample, 10.5 ms for
    # the late commands (after t_k + d), none for the missing ones.  The damping acting
    # from each t_k + d is the one plant_sim_node's CommandHold selects for the same
    # arrivals (3-period timeout, as the bridge's): the command, the newest plan received
    # in time, or passive -- to the duty's resolution.
    late, missing, n = {3, 7, 14}, {8, 10, 11, 15}, 20
    arrival = {k: 0.0105 if k in late else 0.004 if k == 12 else 0.006 for k in range(n)}
    name = f'erva_let_{next(_channels)}'
    reader = can.Bus(interface='virtual', channel=name)
    bridge = BridgeCore(codec, HW, BridgeConfig(c_e_safe=C_E0, command_delay_s=D),
                        lambda: open_bus(f'virtual:{name}'))
    ecu = _Ecu(codec)
    hold = CommandHold(TS_NS, C_E0, 3 * TS_NS)
    try:
        assert bridge.open(now=0.0)
        ecu_u, plant_u = [], []
        for k in range(n):
            plan = [8000.0 + 500.0 * k + 100.0 * j for j in range(6)]
            stamp, rx = T0_NS + k * TS_NS, T0 + k * TS + arrival[k]
            if k not in missing:
                assert bridge.submit(plan, now=k * TS, stamp_ns=stamp) == 'sent'
                while (msg := reader.recv(0.05)) is not None:
                    ecu.resend(msg, k * TS + arrival[k])
                hold.update(stamp, [_wire(codec, u) for u in plan], int(round(rx * 1e9)))
            ecu_u.append(ecu.core.run_cycle().c_e)
            plant_u.append(hold.select(stamp, stamp + D_NS)[0])
        np.testing.assert_allclose(ecu_u, plant_u, rtol=0, atol=1e-6)
        c = ecu.core.counts
        assert c['late_commands'] == hold.late == len(late)
        assert c['u_from_command'] == hold.counts['command'] == n - len(late) - len(missing)
        assert c['u_from_plan'] == hold.counts['plan'] and c['command_timeouts'] == 0
        assert ecu.core.first_late_cycle == 3
    finally:
        ecu.close()
        bridge.close()
        reader.shutdown()


def test_the_hil_bench_prints_arrival_p999_late_commands_and_actuation_jitter():
    from erva_ros.session.bench.benchmark import bench_result, format_bench

    def t(p50, p99, mx, n):
        return {'p50': p50, 'p99': p99, 'max': mx, 'samples': n}

    act = {'command_delay_ms': 10.0, 'late': 3, 'late_pct': 0.1,
           'arrival_ms': t(6.1, 8.2, 11.5, 3000), 'smallest_delay_ms': 9.5,
           'actuation_jitter_ms': t(0.05, 0.12, 0.4, 3000)}
    summary = {'commands': {'actuation': act, 'rate_hz': 50.0},
               'nmpc': {}, 'scenario': {'ts': TS, 'controller': 'preview', 'duration_s': 60.0},
               'hil': {}, 'plant': {'arrival_p999_ms': 9.43, 'cmd_jitter_ms': t(1, 2, 3, 9)},
               'metrics': {'samples': 3000}, 'messages': {'dropped_total': 0,
                                                          'rejected_total': 0},
               'errors': []}
    r = bench_result(summary, busy=2)
    text = format_bench(r)
    assert r['actuation']['arrival_p999_ms'] == 9.43
    assert ('sample -> command at the ECU p50 6.100  p99 8.200  p99.9 9.430  max 11.500 ms  '
            '(3000 samples)') in text
    assert 'late 3 (0.1 %); smallest d with 99.9 % on time: 9.5 ms' in text
    assert 'actuation - (t_k + d)       p50 0.050  p99 0.120  max 0.400 ms  (3000' in text
    assert '2 busy processes' in text and 'load average' in text


def test_the_hil_bench_at_d_0_has_no_late_rule_and_no_actuation_target():
    from erva_ros.session.bench.benchmark import bench_result, format_bench

    arrival = {'p50': 5.4, 'p99': 7.9, 'max': 12.8, 'samples': 2998}
    act = {'command_delay_ms': 0.0, 'late': 0, 'late_pct': 0.0, 'arrival_ms': arrival,
           'smallest_delay_ms': 10.3, 'actuation_jitter_ms': None}
    summary = {'commands': {'actuation': act, 'rate_hz': 50.0},
               'nmpc': {'deadline_misses': 0},
               'scenario': {'ts': TS, 'controller': 'preview', 'duration_s': 60.0},
               'hil': {}, 'plant': {'arrival_p999_ms': 10.27, 'cmd_jitter_ms': arrival},
               'metrics': {'samples': 3000}, 'messages': {'dropped_total': 0,
                                                          'rejected_total': 0},
               'errors': []}
    r = bench_result(summary)
    text = format_bench(r)
    assert r['actuation']['late'] is None
    assert not {'late_commands_pct', 'actuation_jitter_p99_ms'} & set(r['targets'])
    assert 'commands act at arrival (d = 0: no fixed instant, no late rule); smallest d ' \
           'with 99.9 % on time: 10.3 ms' in text
    assert 'p99.9 10.270' in text and 'actuation' not in text
