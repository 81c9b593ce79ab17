"""SampleScheduler (nmpc_node's scheduling, ROS-free) driven by a fake clock."""

import numpy as np
import pytest

from erva_ros.core.loop.sample_schedule import SampleScheduler
from erva_ros.core.loop.validation import MessageRejected, StampWindow

TS = 20_000_000          # 20 ms in ns
T0 = 1_700_000_000 * 10**9
X = np.zeros(6)
H = np.arange(11) * 1e-3


def scheduler(realtime=True, n_samples=10, lead=50_000_000, age=10**9):
    return SampleScheduler(TS, n_samples, 11, realtime, StampWindow(lead, age),
                           state_timeout_ns=3 * TS)


def test_realtime_solves_a_state_on_arrival_once_its_preview_is_there():
    s = scheduler()
    assert s.on_preview(T0, H, T0 + 1_000) is None        # no state yet
    job = s.on_state(T0, X, T0 + 2_000_000)
    assert job.stamp_ns == T0 and np.array_equal(job.preview, H)
    # Disarmed until the next tick: a second state in the same period waits for it.
    s.on_preview(T0 + TS, H, T0 + TS + 1_000)
    assert s.on_state(T0 + TS, X, T0 + TS + 2_000_000) is None
    job, safe = s.on_tick(T0 + TS + 3_000_000)
    assert job.stamp_ns == T0 + TS and safe is None
    assert s.count['missed_samples'] == 0


def test_a_state_waits_for_its_preview_then_a_tick_shifts_an_older_one():
    s = scheduler()
    s.on_preview(T0, H, T0)
    s.on_state(T0, X, T0 + 1)
    s.on_tick(T0 + TS)                                    # armed again
    assert s.on_state(T0 + TS, X, T0 + TS + 1) is None    # its preview is not here yet
    assert s.on_preview(T0 + TS, H, T0 + TS + 2).stamp_ns == T0 + TS
    s.on_tick(T0 + 2 * TS)
    assert s.on_state(T0 + 2 * TS, X, T0 + 2 * TS + 1) is None   # preview lost
    job, _ = s.on_tick(T0 + 3 * TS)
    assert job.stamp_ns == T0 + 2 * TS
    np.testing.assert_array_equal(job.preview, np.r_[H[1:], H[-1]])
    assert s.count['stale_previews'] == 1 and s.count['no_preview'] == 0


def test_superseded_and_missed_samples_are_counted():
    s = scheduler()
    s.on_preview(T0, H, T0)
    s.on_state(T0, X, T0 + 1)                              # solved
    for k in (1, 2, 3):                                    # busy: no tick in between
        s.on_preview(T0 + k * TS, H, T0 + k * TS)
        assert s.on_state(T0 + k * TS, X, T0 + k * TS + 1) is None
    job, _ = s.on_tick(T0 + 3 * TS + 2)
    assert job.stamp_ns == T0 + 3 * TS
    assert s.count['superseded_states'] == 2 and s.count['missed_samples'] == 2


def test_stamps_outside_the_window_or_off_the_grid_are_rejected_and_change_nothing():
    s = scheduler()
    s.on_preview(T0, H, T0)
    s.on_state(T0, X, T0 + 1)
    with pytest.raises(MessageRejected, match='in the future'):
        s.on_state(T0 + 3600 * 10**9, X, T0 + 2)         # one hour ahead
    with pytest.raises(MessageRejected, match='old'):
        s.on_state(T0 - 5 * 10**9, X, T0 + 3)
    with pytest.raises(MessageRejected, match='off the Ts grid'):
        s.on_state(T0 + TS // 2, X, T0 + TS)
    with pytest.raises(MessageRejected, match='in the future'):
        s.on_preview(T0 + 3600 * 10**9, H, T0 + 4)
    # The real next sample is still solved: the foreign ones left no trace.
    s.on_tick(T0 + TS)
    s.on_preview(T0 + TS, H, T0 + TS)
    assert s.on_state(T0 + TS, X, T0 + TS + 1).stamp_ns == T0 + TS
    assert s.count['out_of_order'] == 0 and not s.finished


def test_finished_needs_the_last_stamp_and_the_nodes_own_clock():
    # A state stamped as the last sample but arriving at the start (the window allows
    # 10 s of lead here) is solved, yet does not end the scenario: the clock disagrees.
    early = scheduler(n_samples=5, lead=10**10)
    early.on_preview(T0, H, T0)
    early.on_state(T0, X, T0)
    early.on_tick(T0 + 1)
    early.on_preview(T0 + 4 * TS, H, T0 + 2)
    assert early.on_state(T0 + 4 * TS, X, T0 + 3).stamp_ns == T0 + 4 * TS
    assert not early.finished
    # The real run: finished at its last sample, and nothing is taken after it.
    s = scheduler(n_samples=5)
    for k in range(5):
        t = T0 + k * TS
        s.on_tick(t)
        s.on_preview(t, H, t)
        assert s.on_state(t, X, t + 1).stamp_ns == t
    assert s.finished
    assert s.on_state(T0 + 5 * TS, X, T0 + 5 * TS) is None


def test_no_state_for_three_periods_gives_safe_stamps_on_the_grid_until_states_return():
    s = scheduler()
    s.on_preview(T0, H, T0)
    s.on_state(T0, X, T0)
    assert s.on_tick(T0 + 2 * TS) == (None, None)
    job, safe = s.on_tick(T0 + 3 * TS + 1)
    assert job is None and safe == T0 + 3 * TS and s.timed_out
    _, safe = s.on_tick(T0 + 4 * TS + 5)
    assert safe == T0 + 4 * TS and s.count['state_timeouts'] == 1
    s.on_preview(T0 + 5 * TS, H, T0 + 5 * TS)
    s.on_state(T0 + 5 * TS, X, T0 + 5 * TS + 1)
    assert not s.timed_out
    assert s.on_tick(T0 + 6 * TS)[1] is None


def test_each_sample_gets_one_command_also_when_its_state_comes_after_the_safe_one():
    # A sample that got the safe command (no state for 3 periods) gets no second command
    # when its late state arrives: one damping_cmd per stamp, or the plant refuses the
    # second while the bridge applies both.
    s = scheduler()
    s.on_preview(T0, H, T0)
    s.on_state(T0, X, T0)
    _, safe = s.on_tick(T0 + 3 * TS + 1)
    assert safe == T0 + 3 * TS
    # A tick late into the next period, then the next one on time in that same period.
    assert s.on_tick(T0 + 4 * TS + TS - 1)[1] == T0 + 4 * TS
    assert s.on_tick(T0 + 4 * TS + TS + 1)[1] == T0 + 5 * TS
    assert s.on_tick(T0 + 5 * TS + TS // 2) == (None, None)       # 5 answered already
    # The states come back in a burst, up to the sample the last safe command stood for.
    for k in (1, 2, 3, 4, 5):
        s.on_preview(T0 + k * TS, H, T0 + 5 * TS + TS // 2)
        assert s.on_state(T0 + k * TS, X, T0 + 5 * TS + TS // 2) is None
    assert not s.timed_out and s.count['superseded_states'] == 5
    assert s.on_tick(T0 + 6 * TS + 1) == (None, None)             # no second command
    s.on_preview(T0 + 6 * TS, H, T0 + 6 * TS + 2)
    job = s.on_state(T0 + 6 * TS, X, T0 + 6 * TS + 2)             # the next sample: solved
    assert job.stamp_ns == T0 + 6 * TS and s.count['missed_samples'] == 5


def test_a_last_sample_answered_by_the_safe_command_finishes_the_scenario():
    s = scheduler(n_samples=5)
    s.on_preview(T0, H, T0)
    s.on_state(T0, X, T0)
    assert s.on_tick(T0 + 4 * TS + 1)[1] == T0 + 4 * TS
    assert s.on_state(T0 + 4 * TS, X, T0 + 4 * TS + 3) is None and s.finished
    assert s.on_tick(T0 + 8 * TS) == (None, None)


def test_lockstep_solves_each_state_when_its_preview_is_there():
    s = scheduler(realtime=False)
    for k in range(4):
        t = k * TS
        if k % 2:        # state first: solved when its preview comes
            assert s.on_state(t, X, t) is None
            assert s.on_preview(t, H, t).stamp_ns == t
        else:            # preview first: solved when the state comes
            assert s.on_preview(t, H, t) is None
            assert s.on_state(t, X, t).stamp_ns == t
    assert s.count['missed_samples'] == 0 and s.count['stale_previews'] == 0
