"""Which damping the plant applies on [t_k, t_k + Ts): the command, its plan, or passive c_e0.

The NMPC publishes each command with its planned sequence (topics.py: points[j] =
plan at t0 + j·Ts), so a late or missing command does not leave the plant without a
sensible input.  For sample t_k, with the newest command stamped t0:

* t0 == t_k: the command itself (``command``);
* t0 < t_k, j = (t_k − t0)/Ts < len(plan) and t_k − t0 <= timeout: plan[j] (``plan``);
* otherwise, or before any command: the passive damping c_e0 (``passive``).

No ROS inside: used by plant_sim_node and testable on its own.
"""

from typing import Dict, Optional, Tuple

import numpy as np

SOURCES = ('command', 'plan', 'passive')


class CommandHold:
    """Hold the newest damping command and select u_k for each plant sample."""

    def __init__(self, ts_ns: int, c_e0: float, timeout_ns: int):
        self.ts_ns = int(ts_ns)
        self.c_e0 = float(c_e0)
        self.timeout_ns = int(timeout_ns)
        self.stamp_ns: Optional[int] = None
        self.plan: Optional[np.ndarray] = None
        self.counts: Dict[str, int] = {s: 0 for s in SOURCES}
        self.out_of_order = 0

    def update(self, stamp_ns: int, plan: np.ndarray) -> bool:
        """Keep a command if it is newer than the held one; return whether it was kept."""
        if self.stamp_ns is not None and stamp_ns <= self.stamp_ns:
            self.out_of_order += 1
            return False
        self.stamp_ns, self.plan = int(stamp_ns), np.asarray(plan, dtype=float)
        return True

    def select(self, t_ns: int) -> Tuple[float, str]:
        """Return (u in Ns/m, source) for the sample at ``t_ns`` and count the source."""
        u, source = self.c_e0, 'passive'
        if self.stamp_ns is not None:
            age = t_ns - self.stamp_ns
            if age == 0:
                u, source = float(self.plan[0]), 'command'
            elif 0 < age <= self.timeout_ns:
                j = int(round(age / self.ts_ns))
                if j < self.plan.size:
                    u, source = float(self.plan[j]), 'plan'
        self.counts[source] += 1
        return u, source


__all__ = ['SOURCES', 'CommandHold']
