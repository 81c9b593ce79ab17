"""A session bag as identification data (:class:`erva_ros.core.identify.fit.Recording`).

Read with the project's bag reader and decoded by the contract's decoders
(:mod:`erva_ros.core.contract`, no ROS needed).  Two kinds:

* **HIL** (`erva run --ecu ...`, or a vehicle): ``<ns>/ecu/measurements`` -- the ECU's
  c_e now and its cycle mean, z̈_s, z_s − z_us and φ̇ -- and the road height at the
  tyre.  A measurement's stamp is the CAN receive time of its cycle, just after the
  sample instant: it belongs to the road sample t_k with stamp − t_k in [−Ts/4, 3Ts/4)
  (the estimator's rule).
* **full state** (plant_sim_node, `erva sim` bags): ``<ns>/state``, ``<ns>/sprung_accel``
  and ``<ns>/generator`` (the applied u_k = effort / velocity; ``damping_cmd`` where the
  generator stands still), held over each cycle.

The road: ``<ns>/road/height`` by default, the height a rig's actuator or the road model
produced, known at each sample.  Without preview on a vehicle there is no such truth:
give the topic of a road estimate (``road_topic``) -- the fit then takes that estimate
as the road, and its error biases k_t and M_us first.
"""

from typing import Callable, Dict, List, Optional, Tuple

import numpy as np

from erva_ros.core import contract as wire, topics as contract
from erva_ros.core.bag import BagError
from erva_ros.core.bag.qos import control_profile
from erva_ros.core.bag.reader import open_bag
from erva_ros.core.bag.writer import BagWriter
from erva_ros.core.hil import topics as hil
from erva_ros.core.identify.fit import ECU_CHANNELS, IdentifyError, Recording, STATE_CHANNELS
from erva_ros.core.loop.validation import MessageRejected

#: Minimum road samples to place a grid.
MIN_ROAD_SAMPLES = 10


def _ns(bag, namespace: Optional[str]) -> str:
    if namespace:
        return namespace.rstrip('/') or '/'
    for topic in sorted(bag.topics):
        for suffix in (hil.ECU_MEASUREMENTS, contract.STATE):
            if topic.endswith('/' + suffix):
                return topic[:-len(suffix) - 1] or '/'
    return contract.NAMESPACE


def _topic(ns: str, name: str) -> str:
    return name if name.startswith('/') else f'{ns.rstrip("/")}/{name}'


def _messages(bag, topic: str, decode):
    out = []
    try:
        for m in bag.messages([topic]):
            out.append(decode(m.data))
    except MessageRejected as exc:       # CdrError included
        raise IdentifyError(f'{bag.path}: {topic}: undecodable message ({exc})') from None
    except BagError as exc:
        raise IdentifyError(str(exc)) from None
    return out


class _Grid:
    """The road's sample grid t_k = t0 + k·Ts and the rule that puts a stamp on it."""

    def __init__(self, stamps: np.ndarray, path: str):
        if stamps.size < MIN_ROAD_SAMPLES:
            raise IdentifyError(f'{path}: too short: {stamps.size} road samples')
        d = np.diff(stamps)
        self.ts_ns = int(np.median(d))
        if self.ts_ns <= 0:
            raise IdentifyError(f'{path}: road stamps do not increase')
        self.t0 = int(stamps[0])
        self.n = int(round((stamps[-1] - self.t0) / self.ts_ns)) + 1

    def index(self, stamp: int, early: float = 0.0) -> int:
        """Return the sample index of ``stamp``: within [t_k − early·Ts, t_k + (1 − early)·Ts)."""
        return int(np.floor((stamp - self.t0) / self.ts_ns + early))

    def place(self, stamps, values, width: int, early: float = 0.0) -> np.ndarray:
        """Return values on the grid (n × width), NaN where no sample; first one wins."""
        out = np.full((self.n, width), np.nan)
        seen = np.zeros(self.n, dtype=bool)
        for s, v in zip(stamps, values):
            k = self.index(s, early)
            if 0 <= k < self.n and not seen[k]:
                out[k] = v
                seen[k] = True
        return out


def load_recording(path: str, namespace: Optional[str] = None,
                   road_topic: str = contract.ROAD_HEIGHT,
                   warn: Optional[Callable[[str], None]] = None) -> Recording:
    """Return the identification data of one bag (module doc); one-line IdentifyError if not.

    ``warn`` is told what is wrong with the bag's files (:func:`open_bag`).
    """
    try:
        bag = open_bag(path, warn)
    except BagError as exc:
        raise IdentifyError(str(exc)) from None
    ns = _ns(bag, namespace)
    road = _topic(ns, road_topic)
    meas = _topic(ns, hil.ECU_MEASUREMENTS)
    state = [_topic(ns, t) for t in (contract.STATE, contract.SPRUNG_ACCEL, contract.GENERATOR)]
    if meas in bag.topics:
        kind = 'hil'
    elif all(t in bag.topics for t in state):
        kind = 'state'
    else:
        raise IdentifyError(
            f'{path}: nothing to identify from: no {meas} (an HIL session) and no '
            f'{", ".join(state)} (a full-state session)')
    if road not in bag.topics:
        raise IdentifyError(
            f'{path}: no {road}: identification needs the road height at the tyre at '
            f'each sample -- record on a rig with a known road, or give a road estimate\'s '
            f'topic (--road-topic)')
    rows = _messages(bag, road, wire.decode_road_height)
    stamps = [r.stamp_ns for r in rows]
    grid = _Grid(np.array(stamps, dtype=np.int64), path)
    w = grid.place(stamps, [[r.height_m] for r in rows], 1, early=0.5)[:, 0]
    if kind == 'hil':
        rec = _hil(bag, meas, grid, w, path)
    else:
        rec = _full_state(bag, state, _topic(ns, contract.DAMPING_CMD), grid, w, path)
    return rec


def _hil(bag, topic: str, grid: _Grid, w: np.ndarray, path: str) -> Recording:
    msgs = _messages(bag, topic, lambda data: wire.decode_measurements(data, strict=False))
    if not msgs:
        raise IdentifyError(f'{path}: {topic} has no message')
    vals = [[m.c_e, m.c_e_mean, m.sprung_accel, m.deflection, m.speed] for m in msgs]
    # Measured just after t_k: the estimator's window [t_k − Ts/4, t_k + 3Ts/4).
    on_grid = grid.place([m.stamp_ns for m in msgs], vals, 5, early=0.25)
    return Recording(path, grid.ts_ns * 1e-9, w, on_grid[:, 0], on_grid[:, 1], on_grid[:, 2:],
                     ECU_CHANNELS, grid.t0 * 1e-9)


def _full_state(bag, topics: List[str], cmd_topic: str, grid: _Grid, w: np.ndarray,
                path: str) -> Recording:
    st_topic, acc_topic, gen_topic = topics
    joints = _messages(bag, st_topic, wire.decode_joints)
    if joints and joints[0].names != contract.STATE_JOINTS:
        raise IdentifyError(f'{path}: {st_topic} has joints {list(joints[0].names)}: only the '
                            f'ERVA model ({", ".join(contract.STATE_JOINTS)}) is identified')
    states = _messages(bag, st_topic, wire.decode_state)
    # Full-state stamps are the sample instants themselves: the nearest grid point.
    x = grid.place([s.stamp_ns for s in states], [s.x for s in states], 6, early=0.5)
    acc = _messages(bag, acc_topic, wire.decode_accel)
    a = grid.place([r.stamp_ns for r in acc], [[r.sprung_accel] for r in acc], 1, early=0.5)
    gen = _messages(bag, gen_topic, wire.decode_generator)
    # The applied u_k = effort / velocity (effort = u·v_gen); where v_gen = 0, the command.
    u_gen = [[g.effort / g.velocity if abs(g.velocity) > 1e-12 else np.nan] for g in gen]
    u = grid.place([g.stamp_ns for g in gen], u_gen, 1, early=0.5)[:, 0]
    if np.isnan(u).any() and cmd_topic in bag.topics:
        cmds: Dict[int, float] = {}
        for c in _messages(bag, cmd_topic, wire.decode_command):
            if c.plan.size:
                cmds.setdefault(grid.index(c.stamp_ns, 0.5), c.u)
        for k in np.flatnonzero(np.isnan(u)):
            u[k] = cmds.get(int(k), np.nan)
    u_mean = np.concatenate([[np.nan], u[:-1]])     # u_k held over [t_k, t_k+1)
    return Recording(path, grid.ts_ns * 1e-9, w, u, u_mean, np.hstack([a, x]), STATE_CHANNELS,
                     grid.t0 * 1e-9)


def write_recording(bag_dir: str, rec: Recording, session: Optional[Dict[str, str]] = None,
                    t0_ns: int = 1_700_000_000_000_000_000, lag_s: float = 0.001,
                    namespace: str = contract.NAMESPACE) -> Dict:
    """Write an ECU recording as an HIL session bag: road/height and ecu/measurements.

    For simulated sessions (the tests, a study's sessions): each measurement is stamped
    ``lag_s`` after its sample, as the bridge stamps the CAN receive time.
    """
    if rec.channels != ECU_CHANNELS:
        raise ValueError('write_recording writes ECU recordings only')
    road = _topic(namespace, contract.ROAD_HEIGHT)
    meas = _topic(namespace, hil.ECU_MEASUREMENTS)
    offered = [control_profile()]
    writer = BagWriter(bag_dir, session=dict(session or {}), custom_data=dict(session or {}))
    try:
        writer.add_topic(road, contract.type_of(contract.ROAD_HEIGHT), offered)
        writer.add_topic(meas, contract.type_of(hil.ECU_MEASUREMENTS), offered)
        ts_ns = int(round(rec.ts * 1e9))
        for k in range(rec.n):
            stamp = t0_ns + k * ts_ns
            writer.write(road, wire.encode_road_height(stamp, 0.0, rec.w[k]), stamp, stamp)
            m_stamp = stamp + int(round(lag_s * 1e9))
            values = [rec.u_now[k], rec.u_mean[k], *rec.y[k], float('nan')]
            writer.write(meas, wire.MEASUREMENTS_ENCODER.encode(m_stamp, values), m_stamp,
                         m_stamp)
        return writer.close()
    except BaseException:
        writer.abort()
        raise


def load_recordings(paths, namespace: Optional[str] = None,
                    road_topic: str = contract.ROAD_HEIGHT,
                    warn: Optional[Callable[[str], None]] = None) -> Tuple[Recording, ...]:
    """Return one :class:`Recording` per bag; all must be of one kind and sample time.

    ``warn`` is told what is wrong with each bag's files, the bag's path first.
    """
    recs = tuple(load_recording(p, namespace, road_topic,
                                None if warn is None else _prefixed(warn, p)) for p in paths)
    for r in recs[1:]:
        if r.channels != recs[0].channels:
            raise IdentifyError(f'{r.name}: HIL and full-state sessions mixed: give bags of '
                                f'one kind')
        if abs(r.ts - recs[0].ts) > 1e-9:
            raise IdentifyError(f'{r.name}: sample time {r.ts:g} s, not {recs[0].ts:g} s')
    return recs


def _prefixed(warn: Callable[[str], None], path: str) -> Callable[[str], None]:
    return lambda line: warn(f'{path}: {line}')


__all__ = ['load_recording', 'load_recordings', 'write_recording']
