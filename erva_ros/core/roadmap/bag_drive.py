"""A drive from a recorded HIL session bag: the ECU's measurements and the distance travelled.

Read with :mod:`erva_ros.core.bag.reader`, decoded by :mod:`erva_ros.core.contract`:

* ``<ns>/ecu/measurements`` (sensor_msgs/JointState, erva_ros/core/hil/topics.py): per ECU
  cycle the damping applied and its cycle mean, z̈_s, the deflection, φ̇ and κ·i;
* the distance along the route, from ``<ns>/road/estimate`` (the vehicle's odometry,
  ``pose.pose.position.x``) when the session has it, else ``<ns>/road/height``
  (``point.x``: the road node's distance, exact in simulation).

Cycles are placed on the Ts grid of the first measurement's stamp; a missing cycle is a
row of NaN (the estimator predicts through it), a repeated one is dropped (counted).
"""

from dataclasses import dataclass
import math
from typing import Callable, Dict, Mapping, Optional

import numpy as np

from erva_ros.core import contract, topics
from erva_ros.core.bag import BagError
from erva_ros.core.bag.reader import open_bag
from erva_ros.core.bag.session import stored_parameters
from erva_ros.core.hil import topics as hil_topics
from erva_ros.core.roadmap import MapError
from erva_ros.core.roadmap.drive import DriveRecord

ROAD_ESTIMATE = topics.ROAD_ESTIMATE
_MEAS_ROWS = ('sprung_accel', 'suspension', 'generator_speed', 'f_gen')


@dataclass
class BagDrive:
    """A drive read from a bag, and what reading it found."""

    record: DriveRecord
    ts: float
    distance_topic: str
    missing_cycles: int
    repeated_cycles: int
    malformed: int


def route_of_live(live: Mapping) -> str:
    """Return the route name of a session's live parameters (road, seed, class, speed).

    Every generated road depends on the speed (a time profile, or ISO's spatial grid), so
    the speed is part of the route.
    """
    speed = float(live.get('speed_mps', 0.0))
    if live.get('road_file'):
        base = str(live['road_file']).replace('\\', '/').rsplit('/', 1)[-1]
        return f'file:{base}@{speed:g}m/s'
    road = str(live.get('road', ''))
    extra = f'-{live.get("road_class")}' if road == 'iso8608' else ''
    if road == 'bump':
        extra = (f'-{live.get("bump_height_m")}m-{live.get("bump_length_m")}m-'
                 f'{live.get("bump_start_s")}s')
    return f'{road}{extra}:seed={live.get("seed")}@{speed:g}m/s'


def _session_live(session: Dict[str, str]) -> Optional[Dict]:
    live = stored_parameters(session).get('live')
    return live if isinstance(live, dict) and 'road' in live else None


def _topic(bag, name: str) -> Optional[str]:
    """Return the bag's topic for contract ``name``: /erva/<name>, else the one ending so."""
    full = f'{topics.NAMESPACE}/{name}'
    if full in bag.topics:
        return full
    ends = [t for t in bag.topics if t.endswith('/' + name)]
    return ends[0] if len(ends) == 1 else None


def read_bag_drive(path: str, ts: Optional[float] = None,
                   warn: Optional[Callable[[str], None]] = None) -> BagDrive:
    """Return the drive recorded in the bag at ``path``; MapError/BagError (one line) if none.

    ``warn`` is told what is wrong with the bag's files (:func:`open_bag`).
    """
    bag = open_bag(path, warn)
    meas_topic = _topic(bag, hil_topics.ECU_MEASUREMENTS)
    if meas_topic is None:
        raise MapError(f'{path}: no {hil_topics.ECU_MEASUREMENTS} topic: not a HIL session '
                       f'(record one with erva run --ecu virtual)')
    dist_topic = _topic(bag, ROAD_ESTIMATE) or _topic(bag, topics.ROAD_HEIGHT)
    if dist_topic is None:
        raise MapError(f'{path}: neither {ROAD_ESTIMATE} nor {topics.ROAD_HEIGHT}: no '
                       'distance along the route')
    live = _session_live(bag.session)
    if ts is None:
        ts = float(live.get('ts', 0.02)) if live else 0.02
    route = route_of_live(live) if live else ''
    malformed = 0
    stamps, rows = [], []
    dist_t, dist_s = [], []
    try:
        for m in bag.messages([meas_topic, dist_topic]):
            try:
                if m.topic == meas_topic:
                    j = contract.decode_joints(m.data)
                    names = hil_topics.MEASUREMENT_NAMES
                    if j.names != names or len(j.position) != len(names):
                        malformed += 1
                        continue
                    stamps.append(j.stamp_ns)
                    rows.append(j.position)
                else:
                    decode = (contract.decode_road_estimate if dist_topic.endswith(ROAD_ESTIMATE)
                              else contract.decode_road_height)
                    d = decode(m.data)
                    dist_t.append(d.stamp_ns)
                    dist_s.append(d.distance_m)
            except contract.CdrError:
                malformed += 1
    except BagError:
        raise
    if len(stamps) < 2 or len(dist_t) < 2:
        raise MapError(f'{path}: {len(stamps)} ECU cycles and {len(dist_t)} distance samples: '
                       'too few for a drive')
    return _assemble(path, np.array(stamps), np.array(rows, dtype=float), np.array(dist_t),
                     np.array(dist_s, dtype=float), ts, route, dist_topic, malformed)


def _assemble(path, stamps, rows, dist_t, dist_s, ts, route, dist_topic, malformed) -> BagDrive:
    order = np.argsort(stamps, kind='stable')
    stamps, rows = stamps[order], rows[order]
    dorder = np.argsort(dist_t, kind='stable')
    dist_t, dist_s = dist_t[dorder] * 1e-9, dist_s[dorder]
    t0 = stamps[0]
    k = np.round((stamps - t0) * 1e-9 / ts).astype(int)
    first = np.ones(k.size, dtype=bool)
    first[1:] = k[1:] != k[:-1]
    repeated = int((~first).sum())
    k, rows = k[first], rows[first]
    n = int(k[-1]) + 1
    t = t0 * 1e-9 + ts * np.arange(n)
    inside = (t >= dist_t[0] - ts / 2) & (t <= dist_t[-1] + ts / 2)
    if inside.sum() < 2:
        raise MapError(f'{path}: the ECU cycles and the distance samples do not overlap in time')
    table = np.full((n, len(hil_topics.MEASUREMENT_NAMES)), np.nan)
    table[k] = rows
    idx = {name: i for i, name in enumerate(hil_topics.MEASUREMENT_NAMES)}
    y = np.full((n, 5), np.nan)
    for j, name in enumerate(_MEAS_ROWS):
        y[:, j] = table[:, idx[name]]
    lo, hi = int(np.argmax(inside)), int(n - np.argmax(inside[::-1]))
    sl = slice(lo, hi)
    distance = np.interp(t[sl], dist_t, dist_s)
    speed = (distance[-1] - distance[0]) / (t[sl][-1] - t[sl][0]) if hi - lo > 1 else math.nan
    rec = DriveRecord(t[sl], distance, y[sl], table[sl, idx['c_e']], table[sl, idx['c_e_mean']],
                      path, route, float(speed))
    return BagDrive(rec, ts, dist_topic, int(n - k.size), repeated, malformed)


__all__ = ['ROAD_ESTIMATE', 'BagDrive', 'route_of_live', 'read_bag_drive']
