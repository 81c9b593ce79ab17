"""What-if replay: the road recorded in a session drives an offline closed loop of another law.

`erva replay BAG --drive-plant --controller C`: nothing is published; the road recorded at
the tyre (``road/height``) becomes a recorded road, a fresh controller runs the offline
closed loop on it, and the run is written as a new session bag.
"""

import dataclasses
from typing import Dict, Optional

import numpy as np

from erva_ros.core import contract as wire, topics as contract
from erva_ros.core.bag import BagError
from erva_ros.core.bag.reader import Bag
from erva_ros.core.bag.session import session_metadata
from erva_ros.core.controllers import make_controller
from erva_ros.core.road.profiles import make_road
from erva_ros.session.bag.bag_report import guess_namespace
from erva_ros.session.bag.offline_bag import run_and_record


def recorded_road(bag: Bag, namespace: Optional[str] = None):
    """Return (times s, heights m) of the road recorded at the tyre in ``bag``."""
    ns = namespace or guess_namespace(bag)
    topic = f'{ns}/{contract.ROAD_HEIGHT}'
    if topic not in bag.topics:
        raise BagError(f'{bag.path}: no {topic} in the bag, so no road to drive the plant')
    stamps, heights = [], []
    for m in bag.messages([topic]):
        row = wire.decode_road_height(m.data)
        stamps.append(row.stamp_ns)
        heights.append(row.height_m)
    if len(stamps) < 2:
        raise BagError(f'{bag.path}: {topic} has {len(stamps)} sample(s); need at least 2')
    order = np.argsort(stamps, kind='stable')
    t = (np.asarray(stamps, dtype=np.int64)[order] - stamps[order[0]]) * 1e-9
    h = np.asarray(heights, dtype=float)[order]
    keep = np.concatenate([[True], np.diff(t) > 0])   # drop repeated stamps
    return t[keep], h[keep]


def drive_plant(bag: Bag, out_bag_dir: str, controller_name: str, model, settings,
                session_extra: Optional[Dict] = None, duration_s: Optional[float] = None):
    """Run ``controller_name`` on ``model`` over the road recorded in ``bag``; record it.

    Returns (ClosedLoopResult, metadata of the new bag).  The preview is the recorded
    road itself (what the tyre met), so a preview controller sees the road perfectly.
    The run ends at the last recorded road sample (one control period before the end
    of the recorded session), since each step needs the road at both of its ends.
    """
    times, heights = recorded_road(bag)
    # A step from t_k needs w(t_k + Ts): the last recorded sample ends the run.
    length = float(times[-1])
    duration = length if duration_s is None else min(float(duration_s), length)
    road = make_road('recorded', duration, ts=settings.ts, times=times, heights=heights,
                     name=f'recorded({bag.path})')
    controller = make_controller(controller_name, model, settings)
    session = session_metadata(
        f'what-if:{bag.session.get("scenario", "recorded")}',
        parameters={'erva': dataclasses.asdict(model.params),
                    'controller': dataclasses.asdict(settings)},
        seed=bag.session.get('seed') or None, controller=controller_name,
        extra={'source': 'offline closed loop (what-if replay)', 'based_on': bag.path,
               'based_on_controller': bag.session.get('controller', ''),
               **(session_extra or {})})
    return run_and_record(out_bag_dir, model, controller, road, duration, session=session)


__all__ = ['recorded_road', 'drive_plant']
