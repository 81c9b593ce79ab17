"""Which sample nmpc_node solves when: pairing states with previews, staleness, misses, timeouts.

No ROS inside: the node feeds it states, previews and timer ticks with the node's
clock (``now_ns``) and runs the :class:`Job` it returns; tests drive it with a fake
clock.

Realtime (``realtime=True``): the node ticks at 1/Ts, phase-aligned to the state stamps.
A state that arrives after its period's tick is solved at once (as soon as the preview
of the same sample is there): the scheduler is *armed* by each tick and disarmed by the
first state after it, so at most one early solve happens per period even if states come
faster.  A state that arrives while disarmed waits for the next tick, which solves the
newest state (with the newest preview shifted if its own never came).  Lock-step: each
state is solved as soon as the preview with the same stamp is there.

What it refuses or counts:

* a stamp outside the window around the node's clock (:class:`StampWindow`) or off the
  Ts grid of the first state is rejected (:class:`MessageRejected`): a foreign message
  can neither block the real states (by being "newer") nor end the scenario;
* a state not newer than the newest one (``out_of_order``);
* a state replaced before it was solved (``superseded_states``): by a newer state (the
  node was still busy), or by the safe command already published for its sample (a
  state that arrives after its sample timed out); and the samples between two solved
  ones (``missed_samples``);
* a preview older than the state, shifted to it (``stale_previews``), or none at all
  (``no_preview``: the job then has ``preview=None``);
* no state for ``state_timeout_ns``: each tick returns a safe stamp, the sample the
  passive command stands in for (``state_timeouts`` counts the outages).

Every sample gets at most one command: the stamps of the jobs and safe stamps together
strictly increase (the plant drops a command not newer than the last, the bag holds each
sample once).

The scenario is finished once the state of its last sample (``n_samples`` after the
first) has its command (solved, or the safe one when the state came after it) *and* the
node's own clock agrees that the scenario's time has passed -- never from a stamp alone.
"""

from collections import deque
from dataclasses import dataclass
from typing import Deque, Optional, Tuple

import numpy as np

from erva_ros.core.loop.validation import MessageRejected, StampWindow

#: A preview at most this many samples older than the state is shifted and used.
MAX_PREVIEW_AGE = 3


@dataclass
class Job:
    """One sample to solve: the state x(t_k) (stamp t_k) and its road preview (or None)."""

    stamp_ns: int
    x: np.ndarray
    preview: Optional[np.ndarray]
    rx_ns: int          # node clock when the state arrived


class SampleScheduler:
    """Decide which state the controller solves and when (see module doc)."""

    def __init__(self, ts_ns: int, n_samples: int, n_preview: int, realtime: bool,
                 window: StampWindow, state_timeout_ns: int):
        self.ts_ns = int(ts_ns)
        self.n_samples = int(n_samples)
        self.n_preview = int(n_preview)
        self.realtime = bool(realtime)
        self.window = window
        self.state_timeout_ns = int(state_timeout_ns)
        self.state: Optional[Tuple[int, np.ndarray, int]] = None   # (stamp, x, rx_ns)
        self.previews: Deque[Tuple[int, np.ndarray]] = deque(maxlen=2 * MAX_PREVIEW_AGE + 2)
        self.first_stamp: Optional[int] = None
        self.first_rx_ns: Optional[int] = None
        self.last_solved = -1
        self.answered = -1                      # newest stamp given a command (job or safe)
        self.armed = True
        self.awaiting: Optional[int] = None     # stamp of a state waiting for its preview
        self.timed_out = False
        self.finished = False
        self.count = {'out_of_order': 0, 'superseded_states': 0, 'missed_samples': 0,
                      'stale_previews': 0, 'no_preview': 0, 'state_timeouts': 0}

    def resume(self) -> None:
        """Start over after a pause (a lifecycle deactivate): the old state is not solved.

        Its sample passed long ago; a state timeout counts from the next state on.
        """
        self.state, self.awaiting, self.timed_out, self.armed = None, None, False, True

    # -- inputs ------------------------------------------------------------------------
    def _check_stamp(self, what: str, stamp: int, now_ns: int) -> None:
        self.window.check(what, stamp, now_ns)
        if self.first_stamp is not None and (stamp - self.first_stamp) % self.ts_ns:
            raise MessageRejected(f'{what} stamp {stamp} ns is off the Ts grid of the first '
                                  f'state ({self.first_stamp} ns)')

    def on_state(self, stamp: int, x: np.ndarray, now_ns: int) -> Optional[Job]:
        """Take a state x(t_k); return the job to solve now, if any (MessageRejected if bad)."""
        if self.finished:
            return None
        self._check_stamp('state', stamp, now_ns)
        if self.state is not None and stamp <= self.state[0]:
            self.count['out_of_order'] += 1
            return None
        if self.state is not None and self.state[0] > self.answered:
            self.count['superseded_states'] += 1
        self.state = (stamp, x, now_ns)
        if self.first_stamp is None:
            self.first_stamp, self.first_rx_ns = stamp, now_ns
        self.timed_out = False
        if stamp <= self.answered:
            # Late: its sample timed out and has the safe command already.  The states are
            # back (no more safe commands), but a second command for the sample would be
            # refused by the plant and recorded twice.
            self.count['superseded_states'] += 1
            self._check_finished(stamp, now_ns)
            return None
        if not self.realtime:
            return self._job_if_ready()
        if self.armed:
            # This period's tick came first: solve on arrival, once its preview is here.
            self.armed = False
            self.awaiting = stamp
            return self._job_if_ready()
        return None

    def on_preview(self, stamp: int, heights: np.ndarray, now_ns: int) -> Optional[Job]:
        """Take the preview stamped t_k; return the job to solve now, if any."""
        if self.finished:
            return None
        self._check_stamp('preview', stamp, now_ns)
        if self.previews and stamp <= self.previews[-1][0]:
            self.count['out_of_order'] += 1
            return None
        self.previews.append((stamp, np.asarray(heights)[:self.n_preview]))
        if not self.realtime or self.awaiting == stamp:
            return self._job_if_ready()
        return None

    def on_tick(self, now_ns: int) -> Tuple[Optional[Job], Optional[int]]:
        """Realtime tick: return (job to solve now, safe command's stamp); either may be None."""
        job = None
        if not self.finished and self.state is not None and self.state[0] > self.answered:
            # Arrived before this tick while disarmed, or its preview never came.
            job = self._job()
        # Re-armed every tick, also after solving here: a late period must not make every
        # following state wait for the next tick.
        self.armed = True
        safe = None
        if (not self.finished and self.state is not None
                and now_ns - self.state[2] > self.state_timeout_ns):
            if not self.timed_out:
                self.timed_out = True
                self.count['state_timeouts'] += 1
            # Stamped with the sample it stands in for (on the grid of the last state,
            # never ahead of the clock): the command of a newer state supersedes it; a
            # state of this sample that comes late is not solved (one command a sample).
            last = self.state[0]
            safe = last + max(1, (now_ns - last) // self.ts_ns) * self.ts_ns
            if safe <= self.answered:
                safe = None     # a late tick's sample: this one came in the same period
            else:
                self.answered = safe
        return job, safe

    # -- jobs --------------------------------------------------------------------------
    def _job_if_ready(self) -> Optional[Job]:
        if self.state is None or self.state[0] <= self.answered:
            return None
        if any(p_stamp == self.state[0] for p_stamp, _ in self.previews):
            return self._job()
        return None

    def _job(self) -> Job:
        stamp, x, rx_ns = self.state
        self.awaiting = None
        if self.last_solved >= 0 and stamp - self.last_solved > self.ts_ns:
            self.count['missed_samples'] += (stamp - self.last_solved) // self.ts_ns - 1
        self.last_solved = self.answered = stamp
        preview = self._preview_for(stamp)
        if preview is None:
            self.count['no_preview'] += 1
        self._check_finished(stamp, rx_ns)
        return Job(stamp, x, preview, rx_ns)

    def _check_finished(self, stamp: int, rx_ns: int) -> None:
        """Finish once the last sample (by the stamps) has its command."""
        if stamp >= self.first_stamp + (self.n_samples - 1) * self.ts_ns:
            # The node's clock must agree (a stamp alone, even inside the window, cannot
            # end the scenario early).  One period of slack: in lock-step the node's /clock
            # may lag the samples by one.
            self.finished = (rx_ns - self.first_rx_ns
                             >= (self.n_samples - 2) * self.ts_ns)

    def _preview_for(self, stamp: int) -> Optional[np.ndarray]:
        """Return the preview of sample ``stamp``: exact, else a recent one shifted, else None."""
        for p_stamp, heights in reversed(self.previews):
            if p_stamp == stamp:
                return heights
            if p_stamp < stamp:
                age = (stamp - p_stamp) // self.ts_ns
                if age > MAX_PREVIEW_AGE:
                    return None
                self.count['stale_previews'] += 1
                return np.r_[heights[age:], np.full(age, heights[-1])]
        return None


__all__ = ['Job', 'MAX_PREVIEW_AGE', 'SampleScheduler']
