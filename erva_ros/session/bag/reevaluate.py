"""Re-evaluation: feed a session's recorded states and previews to a fresh controller.

For every recorded damping command (``damping_cmd.header.stamp`` = stamp of the state
it answers) the state with that stamp and the preview the controller had -- the one
with the same stamp, else the newest one stamped before it -- are given, in order, to
a freshly reset controller of the recorded model (:meth:`Controller.compute`, x = [z_s,
ż_s, z_us, ż_us(, z_d, ż_d)], t = k·Ts).  With the same software and settings a
deterministic controller reproduces the recorded plans; a difference means the session
was not reproducible (other parameters, solver changes, or data the controller saw but
the bag lacks).
"""

import bisect
from dataclasses import dataclass
import json
from typing import Callable, List, Optional

import numpy as np

from erva_ros.core.bag import BagError
from erva_ros.core.controllers.settings import validate_settings
from erva_ros.core.model.params import ParamError, validate_erva
from erva_ros.core.settings.controller import NUMERIC_SPECS
from erva_ros.session.bag.bag_report import SessionData


@dataclass
class Reevaluation:
    """Recorded and recomputed plans, one row per command (Ns/m)."""

    stamps_ns: np.ndarray
    recorded: List[np.ndarray]
    recomputed: List[np.ndarray]
    statuses: List[str]

    def max_abs_difference(self) -> float:
        """Return the largest |recorded − recomputed| over all plan entries (Ns/m)."""
        worst = 0.0
        for a, b in zip(self.recorded, self.recomputed):
            n = min(a.size, b.size)
            if a.size != b.size:
                return float('inf')
            worst = max(worst, float(np.max(np.abs(a[:n] - b[:n]))) if n else 0.0)
        return worst


def reevaluate(data: SessionData, controller, max_commands: Optional[int] = None,
               progress: Optional[Callable[[int, int], None]] = None) -> Reevaluation:
    """Recompute the recorded commands of ``data`` (the first ``max_commands``).

    ``controller`` must be built for the recorded model (``data.model``); ``progress``
    gets (done, total) after each command.
    """
    state_stamps = data.state.stamp_ns.tolist()
    if not data.cmd.n:
        raise BagError(f'{data.bag.path}: no damping commands to re-evaluate')
    states = {s: i for i, s in enumerate(state_stamps)}
    order = np.argsort(data.preview_stamp_ns, kind='stable')
    pstamps = data.preview_stamp_ns[order].tolist()
    t0 = int(data.t0_ns)
    ts = controller.ts
    controller.reset()
    out = Reevaluation(data.cmd.stamp_ns.copy(), [], [], [])
    stamps = data.cmd.stamp_ns.tolist()[:max_commands]
    if progress is not None:
        progress(0, len(stamps))
    for j, stamp in enumerate(stamps):
        i = states.get(stamp)
        if i is None:
            raise BagError(f'command stamped {stamp} answers no recorded state')
        k = bisect.bisect_right(pstamps, stamp) - 1
        if k < 0:
            raise BagError(f'no preview recorded before the state stamped {stamp}')
        t = round((stamp - t0) * 1e-9 / ts) * ts
        res = controller.compute(data.x(i), data.previews[order[k]], t)
        out.recorded.append(np.asarray(data.plans[j], dtype=float))
        out.recomputed.append(np.asarray(res.plan, dtype=float))
        out.statuses.append(res.status)
        if progress is not None:
            progress(j + 1, len(stamps))
    return out


def controller_from_session(bag, controller: Optional[str] = None):
    """Return (ERVA params, controller settings) stored in ``bag``'s session metadata.

    The ``parameters`` record holds ``erva`` (paper Table I values) and ``controller``
    (the nmpc_node settings).  The wall-clock budget is lifted to its maximum, as the
    lock-step nmpc_node does: re-evaluation checks the solver's answers, not timing.
    """
    text = bag.session.get('parameters')
    if not text:
        raise BagError(f'{bag.path}: the session metadata has no parameters to rebuild the '
                       'controller from')
    try:
        stored = json.loads(text)
        params = validate_erva(stored['erva'], source='session parameters')
        values = dict(stored['controller'])
        if controller:
            values['controller'] = controller
        values['time_budget_s'] = NUMERIC_SPECS['time_budget_s'].hi
        settings = validate_settings(values, source='session parameters')
    except (ValueError, KeyError, TypeError, ParamError) as exc:
        raise BagError(f'{bag.path}: session parameters unusable ({exc})') from None
    return params, settings


def summarize(result: Reevaluation, tolerance: float = 1e-6) -> dict:
    """Return counts of reproduced commands and the largest difference (Ns/m)."""
    same = sum(1 for a, b in zip(result.recorded, result.recomputed)
               if a.size == b.size and (a.size == 0 or np.max(np.abs(a - b)) <= tolerance))
    statuses = {s: result.statuses.count(s) for s in sorted(set(result.statuses))}
    return {'commands': len(result.recorded), 'reproduced': same,
            'max_abs_difference': result.max_abs_difference(), 'tolerance': tolerance,
            'statuses': statuses, 'identical': same == len(result.recorded)}


__all__ = ['Reevaluation', 'reevaluate', 'controller_from_session', 'summarize']
