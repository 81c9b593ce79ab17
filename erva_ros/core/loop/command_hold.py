"""Which damping acts from t_k + d: the command, its plan, or passive c_e0 (the late rule).

The NMPC publishes each command with its planned sequence (core/contract.py Command:
plan[j] acts at t0 + d + j·Ts), so a late or missing command does not leave the plant
without a sensible input.  The rule, one for the plant and the ECU, and the one the
OCP's timing assumes: at the instant t_k + d the actuator applies the newest command
*received by its deadline*, its plan entry for t_k.  With that command stamped t0:

* t0 == t_k: the command itself (``command``);
* t0 < t_k, j = (t_k − t0)/Ts < len(plan) and t_k − t0 <= timeout: plan[j] (``plan``);
* otherwise, or before any command: the passive damping c_e0 (``passive``).

A command received after its own deadline is **late**: it never acts (no command acts
off its instant), counted; its plan still serves the later instants it reaches in time.
The deadline is t_k + d (a command must be there when it acts); with d = 0 the plant's
historic rule, before the next sample's road height (``deadline_ns`` None: any time).

No ROS inside: used by plant_sim_node and testable on its own.
"""

from typing import Dict, List, Optional, Tuple

import numpy as np

SOURCES = ('command', 'plan', 'passive')
#: Commands kept: the newest few by stamp (a late one's predecessor must still be there).
KEEP = 4


class CommandHold:
    """Hold the newest damping commands with their reception times; select u_k (module doc)."""

    def __init__(self, ts_ns: int, c_e0: float, timeout_ns: int):
        self.ts_ns = int(ts_ns)
        self.c_e0 = float(c_e0)
        self.timeout_ns = int(timeout_ns)
        self._held: List[Tuple[int, int, np.ndarray]] = []   # (stamp, rx, plan), by stamp
        self.counts: Dict[str, int] = {s: 0 for s in SOURCES}
        self.out_of_order = 0
        self.late = 0

    @property
    def stamp_ns(self) -> Optional[int]:
        """Return the newest held command's stamp (None before any)."""
        return self._held[-1][0] if self._held else None

    def update(self, stamp_ns: int, plan: np.ndarray, rx_ns: int = 0) -> bool:
        """Keep a command newer than every held one; return whether it was kept."""
        if self._held and stamp_ns <= self._held[-1][0]:
            self.out_of_order += 1
            return False
        self._held.append((int(stamp_ns), int(rx_ns), np.asarray(plan, dtype=float)))
        del self._held[:-KEEP]
        return True

    def select(self, t_ns: int, deadline_ns: Optional[int] = None) -> Tuple[float, str]:
        """Return (u in Ns/m, source) acting from sample ``t_ns`` on, and count the source.

        Only commands received by ``deadline_ns`` count (None: all); the command stamped
        ``t_ns`` received later is counted late.
        """
        u, source = self.c_e0, 'passive'
        for stamp, rx, plan in reversed(self._held):
            if stamp > t_ns:
                continue
            if deadline_ns is not None and rx > deadline_ns:
                if stamp == t_ns:
                    self.late += 1
                continue
            age = t_ns - stamp
            if age == 0:
                u, source = float(plan[0]), 'command'
            elif age <= self.timeout_ns:
                j = int(round(age / self.ts_ns))
                if j < plan.size:
                    u, source = float(plan[j]), 'plan'
            break
        self.counts[source] += 1
        return u, source


__all__ = ['SOURCES', 'CommandHold']
