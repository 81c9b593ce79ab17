"""The session monitor's streaming figures: those of all the messages, in fixed memory.

An Observations store (session/run/observations.py) folds each message into
session/run/monitor_stats.py as it arrives.  A synthetic HIL session -- foreign, repeated and
out-of-order stamps, a malformed message, commands before their state, an outage, a
stalled road, the ECU's truth -- is fed to it (rclpy's serialisation), and every figure is
compared with a small batch computation over the whole list of messages, here.  Then the
memory: 100,000 more samples on every topic leave it where it was.
"""

import gc
import math
import struct
import tracemalloc
from collections import Counter, defaultdict

import numpy as np
import pytest
from rclpy.serialization import serialize_message

from erva_ros.core import topics
from erva_ros.core.hil.topics import TRUE_STATE
from erva_ros.core.metrics import percentiles_ms
from erva_ros.core.wire import header_stamp_ns
from erva_ros.session.run import verdict
from erva_ros.session.run.monitor_stats import MAX_PENDING
from erva_ros.session.run.observations import Observations
import ros_msgs as msgs

TS = 0.02
TS_NS = 20_000_000
T0 = 1_000_000_000_000
N = 600
MS = 1_000_000
WINDOW_NS = (T0, T0 + 2 * N * TS_NS)
GAP_S = 0.06
WARMUP = 25
OUTAGE = range(200, 210)        # no state: the NMPC's safe commands, two per sample
STALL = range(300, 305)         # states reach the monitor late, after their commands
#: Two slow solves: the next commands queue behind each (sample: latency, ms).
QUEUED = {400: 95, 401: 78, 402: 60, 403: 43, 404: 26, 405: 9,
          450: 70, 451: 52, 452: 34, 453: 16}
ROAD_SKIPPED = (500, 501)
STATE, ACCEL, GEN = topics.STATE, topics.SPRUNG_ACCEL, topics.GENERATOR
HEIGHT, PREVIEW, CMD = topics.ROAD_HEIGHT, topics.ROAD_PREVIEW, topics.DAMPING_CMD


def _session(n=N, seed=3):
    """Return the messages (topic, rx_ns, stamp_ns, value) in their order of arrival.

    value: x (state, truth), z̈_s, (position, v, u) of the generator, the height, the
    preview, u of a command; None: a malformed message.
    """
    rng = np.random.default_rng(seed)
    x_true = rng.normal(scale=0.01, size=(n, 6))
    out = []
    for k in range(n):
        s = T0 + k * TS_NS
        if k not in ROAD_SKIPPED:
            out.append((HEIGHT, s + 200_000, s, 1e-3 * k))
            out.append((PREVIEW, s + 300_000, s, (1e-3 * k,) * 11))
        if k != 250:
            out.append((TRUE_STATE, s + 500_000, s, x_true[k]))
        estimate = x_true[k] + rng.normal(scale=1e-4, size=6)
        if k in STALL:
            out.append((STATE, T0 + STALL.stop * TS_NS + 500_000 + k, s, estimate))
        elif k not in OUTAGE:
            out.append((STATE, s + MS, s, estimate))
        u = 1000.0 + 10.0 * k
        if k in OUTAGE:
            out += [(CMD, s + 5 * MS, s, 900.0), (CMD, s + 6 * MS, s, 901.0)]
        elif k in QUEUED:
            out.append((CMD, s + MS + QUEUED[k] * MS, s, u))
        else:
            out.append((CMD, s + MS + int(rng.uniform(2, 6) * MS), s, u))
        if k != 150:
            out.append((ACCEL, s + 2 * MS, s, rng.normal()))
        out.append((GEN, s + 2 * MS, s, (0.0, 0.01 * (k % 7), u)))
        # Not the loop's: before or after the session's span, a repeated stamp, an older
        # stamp seen first, a malformed message.
        if k == 50:
            out += [(STATE, s, T0 - 5, estimate), (ACCEL, s + 3 * MS, s - 3 * TS_NS, 9.0),
                    (CMD, s, WINDOW_NS[1] + 1, 5.0), (TRUE_STATE, s + MS, s, estimate)]
        if k == 60:
            out += [(HEIGHT, s + MS, s - 3 * TS_NS + 7, 0.5), (GEN, s + MS, s, None),
                    (STATE, s + 3 * MS, WINDOW_NS[1] + 1, estimate)]
    return sorted(out, key=lambda m: m[1])      # stable: ties in the order made


def _bytes(topic, stamp, value):
    if value is None:
        return b'\x00\x01\x00\x00\x07'
    if topic in (STATE, TRUE_STATE):
        return serialize_message(msgs.state_msg(stamp, value, 'erva'))
    if topic == ACCEL:
        return serialize_message(msgs.accel_msg(stamp, value))
    if topic == GEN:
        return serialize_message(msgs.generator_msg(stamp, *value))
    if topic == HEIGHT:
        return serialize_message(msgs.road_height_msg(stamp, 0.1, value))
    if topic == PREVIEW:
        return serialize_message(msgs.preview_msg(stamp, list(value), TS_NS))
    return serialize_message(msgs.damping_msg(stamp, [value] * 10, TS_NS))


def _fed(session, **kw):
    obs = Observations(hil=True, window_ns=WINDOW_NS, ts=TS, command_gap_s=GAP_S, **kw)
    for topic, rx, stamp, value in session:
        obs.add(topic, rx, _bytes(topic, stamp, value))
    return obs


def _worst(pairs, t0):
    value, at = max(pairs, key=lambda p: (p[0], -p[1]))
    return f'{value * 1e3:.0f} ms at t = {(at - t0) * 1e-9:.2f} s'


def _gaps(times):
    return [((b - a) * 1e-9, a) for a, b in zip(times, times[1:])]


def _reference(session, n_steps):
    """Every figure from the whole list of messages, as the monitor computed them in one go."""
    lo, hi = WINDOW_NS
    newest, foreign, kept = {}, Counter(), defaultdict(list)
    for topic, rx, stamp, value in session:
        if (value is None or not lo <= stamp <= hi
                or (topic != CMD and stamp <= newest.get(topic, -1))):
            foreign[topic] += 1
            continue
        newest[topic] = stamp
        kept[topic].append((rx, stamp, value))
    states = {s: (rx, x) for rx, s, x in kept[STATE]}
    truth = {s: x for _, s, x in kept[TRUE_STATE]}
    accel = {s: a for _, s, a in kept[ACCEL]}
    power = {s: g[2] * g[1] * g[1] for _, s, g in kept[GEN]}
    heights = {s: h for _, s, h in kept[HEIGHT]}
    u = {}
    for _, s, value in kept[CMD]:
        u.setdefault(s, value)
    rows = sorted(accel)[:n_steps]
    a = np.array([accel[s] for s in rows])
    state_rx = sorted(rx for rx, _ in states.values())
    scheduled = [(rx, s) for rx, s, _ in kept[CMD] if s in states]
    rx_s = np.array([rx for rx, _ in scheduled], dtype=float) * 1e-9
    t0, s0 = state_rx[0], min(states)
    pauses = [g for g in _gaps(sorted(rx for rx, _, _ in kept[CMD])) if g[0] > GAP_S]
    paired = sorted(set(states) & set(truth))[WARMUP:]
    err = np.array([states[s][1] - truth[s] for s in paired])
    true = np.array([truth[s] for s in paired])
    return {
        'foreign': dict(foreign),
        'acc_2norm': math.sqrt(np.sum(a ** 2)), 'acc_rms': math.sqrt(np.mean(a ** 2)),
        'samples': len(rows),
        'realtime_factor': (len(state_rx) - 1) * TS / ((state_rx[-1] - state_rx[0]) * 1e-9),
        'commands': {'received': len(kept[CMD]), 'for_samples': len(scheduled),
                     'rate_hz': (len(rx_s) - 1) / (rx_s[-1] - rx_s[0]),
                     'sample_to_command_ms': percentiles_ms([(rx - s) * 1e-9
                                                             for rx, s in scheduled]),
                     'monitor': {'period_jitter_ms': percentiles_ms(np.abs(np.diff(rx_s) - TS)),
                                 'state_to_command_ms': percentiles_ms(
                                     [(rx - states[s][0]) * 1e-9 for rx, s in scheduled])}},
        'late': _worst([((rx - s) * 1e-9, s) for rx, s in scheduled], s0),
        'state_gap': _worst(_gaps(state_rx), t0),
        'road_gap': _worst(_gaps(sorted(heights)), s0),
        'pauses': (len(pauses), _worst(pauses, t0)),
        'error': {'matched': len(paired), 'rms': np.sqrt(np.mean(err ** 2, axis=0)),
                  'scale': np.sqrt(np.mean(true ** 2, axis=0))},
        'trajectory': {
            't': np.array([(s - s0) * 1e-9 for s in rows]),
            'x': np.array([states[s][1] if s in states else np.full(6, np.nan) for s in rows]),
            'u': np.array([u.get(s, np.nan) for s in rows]),
            'w': np.array([heights.get(s, np.nan) for s in rows]),
            'sprung_accel': a, 'power': np.array([power.get(s, np.nan) for s in rows])},
    }


def test_streaming_figures_are_those_of_all_the_messages():
    session = _session()
    ref = _reference(session, N)
    obs = _fed(session)
    s = obs.summary(TS, N, realtime=True)
    # What each kind of foreign message was counted as (the batch found the same).
    assert ref['foreign'] == {STATE: 2, ACCEL: 1, CMD: 1, TRUE_STATE: 1, HEIGHT: 1, GEN: 1}
    assert {t: n for t, n in s['messages']['foreign'].items() if n} == ref['foreign']
    m = s['metrics']
    assert (m['acc_2norm'], m['acc_rms'], m['samples'], m['realtime_factor']) == (
        ref['acc_2norm'], ref['acc_rms'], ref['samples'], ref['realtime_factor'])
    c = dict(s['commands'])
    del c['actuation']
    assert c == ref['commands']
    # The outage's safe commands are received, not for samples; the stalled states'
    # commands are, though they came first.
    assert ref['commands']['received'] == N + len(OUTAGE)
    assert ref['commands']['for_samples'] == N - len(OUTAGE)
    nmpc = {'deadline_misses': 1, 'state_timeouts': 1}
    got = verdict.warnings(obs, {'nmpc': nmpc, 'road': {'samples_skipped': 2}},
                           verdict.quality_limits({'max_command_gap_s': GAP_S}))
    assert got == [
        f'1 missed deadline (worst sample -> command {ref["late"]})',
        '1 state timeout: the controller sent passive commands (longest pause between '
        f'states {ref["state_gap"]})',
        f'2 road samples skipped by a late timer (widest gap {ref["road_gap"]})',
        f'{ref["pauses"][0]} pauses between commands over 60 ms (longest {ref["pauses"][1]})']
    assert ref['pauses'][0] == 2 and ref['late'].startswith('96 ms')
    error = s['hil']['estimator']['error']
    assert error['matched'] == ref['error']['matched'] == N - len(OUTAGE) - 1 - WARMUP
    np.testing.assert_allclose(list(error['rms'].values()), ref['error']['rms'], rtol=1e-12)
    np.testing.assert_allclose(list(error['relative_rms'].values()),
                               ref['error']['rms'] / ref['error']['scale'], rtol=1e-12)
    tr = obs.trajectory(N)
    assert set(tr) == set(ref['trajectory'])
    for key, want in ref['trajectory'].items():
        np.testing.assert_array_equal(tr[key], want, err_msg=key)
    assert s['trajectory'] == {'samples': N - 1, 'of': N - 1, 'cap': 180_000, 'complete': True}


def test_beyond_the_trajectory_cap_the_figures_come_from_the_sums():
    session = _session()
    n_steps = N - 50
    ref = _reference(session, n_steps)
    obs = _fed(session, n_steps=n_steps, trajectory_cap=100)
    s = obs.summary(TS, n_steps, realtime=True)
    m = s['metrics']
    assert m['samples'] == ref['samples'] == n_steps
    assert m['acc_2norm'] == pytest.approx(ref['acc_2norm'], rel=1e-13)
    assert m['acc_rms'] == pytest.approx(ref['acc_rms'], rel=1e-13)
    assert s['trajectory'] == {'samples': 100, 'of': N - 1, 'cap': 100, 'complete': False}
    tr = obs.trajectory(n_steps)
    for key, want in ref['trajectory'].items():
        np.testing.assert_array_equal(tr[key], want[:100], err_msg=key)
    c = dict(s['commands'])
    del c['actuation']
    assert c == _reference(session, N)['commands']


def test_a_command_waits_for_its_state_within_a_bounded_window():
    obs = Observations(window_ns=WINDOW_NS, ts=TS)
    for k in range(MAX_PENDING + 10):       # commands of samples whose states never come
        s = T0 + k * TS_NS
        obs.add(CMD, s + MS, _bytes(CMD, s, 1000.0))
    assert len(obs.streams.commands.pending) == MAX_PENDING
    s = T0 + (MAX_PENDING + 9) * TS_NS      # the newest one's state arrives: it counts
    obs.add(STATE, s + 2 * MS, _bytes(STATE, s, np.zeros(6)))
    assert obs.streams.commands.for_samples == 1
    assert obs.summary(TS, N, realtime=False)['commands'] == {
        'received': MAX_PENDING + 10, 'for_samples': 1}
    assert not obs.streams.commands.pending


def _restamp(template, stamp):
    """Return ``template`` (a message that starts with its stamp) stamped ``stamp``."""
    return template[:4] + struct.pack('<iI', *divmod(stamp, 1_000_000_000)) + template[12:]


@pytest.mark.slow
def test_memory_does_not_grow_with_the_session():
    x = np.full(6, 0.01)
    templates = {topic: _bytes(topic, 0, value) for topic, value in (
        (STATE, x), (TRUE_STATE, x), (ACCEL, 0.5), (GEN, (0.0, 0.1, 1000.0)),
        (HEIGHT, 0.01))}
    # A one-point preview and plan: the same figures, decoded faster.
    templates[PREVIEW] = serialize_message(msgs.preview_msg(0, [0.0], TS_NS))
    templates[CMD] = serialize_message(msgs.damping_msg(0, [1000.0], TS_NS))
    order = (HEIGHT, PREVIEW, TRUE_STATE, STATE, CMD, ACCEL, GEN)
    assert all(header_stamp_ns(_restamp(t, T0 + 7)) == T0 + 7 for t in templates.values())

    def feed(obs, k0, k1):
        for k in range(k0, k1):
            s = T0 + k * TS_NS
            for topic in order:
                obs.add(topic, s + MS, _restamp(templates[topic], s))
            if k % 1000 == 0:       # foreign ones now and then
                obs.add(STATE, s, _restamp(templates[STATE], s - TS_NS))
                obs.add(CMD, s, _restamp(templates[CMD], WINDOW_NS[0] - 1))

    tracemalloc.start()
    try:
        obs = Observations(hil=True, window_ns=(T0, T0 + 10 ** 18), ts=TS)
        feed(obs, 0, 10_000)
        gc.collect()
        first = tracemalloc.get_traced_memory()[0]
        feed(obs, 10_000, 110_000)
        gc.collect()
        grown = tracemalloc.get_traced_memory()[0] - first
    finally:
        tracemalloc.stop()
    s = obs.summary(TS, 110_000, realtime=True)
    assert s['commands']['for_samples'] == 110_000 and s['metrics']['samples'] == 110_000
    assert s['messages']['foreign'][STATE] == s['messages']['foreign'][CMD] == 110
    assert s['hil']['estimator']['error']['matched'] == 110_000 - WARMUP
    assert grown < 256 * 1024, f'the store grew by {grown} bytes over 100,000 samples'


def test_estimates_on_their_own_grid_pair_with_the_truth_of_their_cycle():
    # An ECU whose samples are off the estimator's grid (its clock not the estimator's):
    # the estimates are stamped a part of a period after the ECU's instants (0.5 ms on a
    # quiet machine, more on a busy one).  The error is still over every cycle, the same,
    # and the offset is measured: in the window the estimator places a cycle on its grid
    # with, [-Ts/4, 3Ts/4) (EstimatorLoop.stamp).
    from erva_ros.session.run.monitor_stats import SessionStreams
    rng = np.random.default_rng(3)
    truth = rng.normal(size=(60, 6))
    est = truth + rng.normal(scale=0.01, size=truth.shape)
    errors = {}
    for offset in (0, 500_000, 12_000_000, -4_000_000):
        s = SessionStreams(0.02)
        for k in range(60):
            t = 1_000_000_000 + k * 20_000_000
            if k % 2:       # either may come first
                s.add_truth(t, truth[k])
                s.add_state(t + offset, t + offset + 1000, est[k])
            else:
                s.add_state(t + offset, t + offset + 1000, est[k])
                s.add_truth(t, truth[k])
        errors[offset] = (s.error.matched, s.error.err2.copy())
        assert (s.error.offset_ns, s.error.offset_spread_ns) == (offset, 0)
    assert {m for m, _ in errors.values()} == {60}
    for offset in (500_000, 12_000_000, -4_000_000):
        np.testing.assert_array_equal(errors[0][1], errors[offset][1])
    # The deflection and its rate come after the state's coordinates.
    np.testing.assert_allclose(errors[0][1][6:], [
        np.sum(((est - truth)[:, 0] - (est - truth)[:, 2]) ** 2),
        np.sum(((est - truth)[:, 1] - (est - truth)[:, 3]) ** 2)], rtol=1e-12)
    # 3Ts/4 on is the next cycle's window: paired with that one, at -Ts/4.
    s = SessionStreams(0.02)
    s.add_truth(1_000_000_000, truth[0])
    s.add_state(1_000_000_000 + 15_000_000, 1_000_000_000, est[0])
    assert s.error.matched == 0
    s.add_truth(1_020_000_000, truth[1])
    assert s.error.matched == 1 and s.error.offset_ns == -5_000_000


def test_figures_timed_from_the_states_stamp_run_from_the_ecus_instant():
    # An ECU off the estimator's grid: its instants 3 ms before the stamps.  What was timed
    # from the stamp is shifted by the offset the pairs measure; the ECU's own figures not.
    from erva_ros.session.run import hil_summary
    from erva_ros.session.run.monitor_stats import PairedError

    def summary():
        t = {'p50': 1.0, 'p99': 2.0, 'max': 3.0, 'samples': 10}
        chain = {k: dict(t) for k in hil_summary.CHAIN}
        return {'hil': {'chain_ms': chain}, 'commands': {'sample_to_command_ms': dict(t)},
                'nmpc': {'latency_ms': dict(t)}}

    error = PairedError(0)
    for k in range(3):
        error.add(np.zeros(6), np.zeros(6), 3_000_000)
    s = summary()
    hil_summary.from_sample_instant(s, error, road_estimated=True)
    assert s['hil']['stamp_offset_ms'] == 3.0
    shifted = {'p50': 4.0, 'p99': 5.0, 'max': 6.0, 'samples': 10}
    for key in hil_summary.STAMPED_STAGES:
        assert s['hil']['chain_ms'][key] == shifted
    assert s['hil']['chain_ms']['sensors_on_can']['p50'] == 1.0       # the ECU's own
    assert s['commands']['sample_to_command_ms'] == s['nmpc']['latency_ms'] == shifted
    # Pairs at two offsets: unknown, so not shown; on the road grid nothing moves.
    error.add(np.zeros(6), np.zeros(6), 2_000_000)
    s = summary()
    hil_summary.from_sample_instant(s, error, road_estimated=True)
    assert s['hil']['stamp_offset_ms'] is None
    assert s['hil']['chain_ms']['state_published']['samples'] is None
    s = summary()
    hil_summary.from_sample_instant(s, error, road_estimated=False)
    assert s == {**summary(), 'hil': {**summary()['hil'], 'stamp_offset_ms': 0.0}}
