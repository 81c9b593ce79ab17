"""Session figures from a bag alone: comfort, power, timing, deadline misses, fallbacks.

Data (:func:`load_session`) are taken from the topics of ``erva_ros.core.topics``; the
time axis is the header stamp t_k of each message, relative to the first state.

* Comfort (paper §IV.B, :func:`erva_ros.core.metrics.comfort_power`): 2-norm and RMS of
  z̈_s(t_k) on ``sprung_accel``.
* Power: P(t_k) = effort·velocity on ``generator`` (W).  The average harvested power
  is E_h / T with E_h the plant's own integrated energy when its /diagnostics carry
  it (``harvested_j``; exact), else Σ P(t_k)·Ts (a rectangle rule on the samples).
  The samples can overstate the energy badly when the command switches: right after
  a switch to high damping P(t_k) is large, but the generator velocity then decays
  within milliseconds (fastest eigenvalue −250 to −1300 1/s, NOTES.md), long before
  the next sample.
* Timing (realtime sessions): the command period and its jitter |Δ − Ts| from the
  damping_cmd publish times (the publisher's clock) and log times (the recorder's);
  the state → command latency as command publish/log time minus the stamp of the
  state it was computed from (damping_cmd.header.stamp = state stamp).  Lock-step
  sessions stamp in sim time: only the wall time per step is reported.  Solve times,
  deadline misses and fallbacks as the controller reports them on /diagnostics (last
  value of each counter).  Commands more than 1.5·Ts after their predecessor are
  counted as late, states that never got a command as unanswered.
"""

from dataclasses import dataclass, field
import math
import re
from typing import Dict, List, Optional

import numpy as np

from erva_ros.core import topics as contract

from erva_ros.core.bag.reader import Bag
from erva_ros.core.levels import ERROR
from erva_ros.core.metrics import comfort_power, percentiles_ms
from erva_ros.ros.bag_messages import decoded
from erva_ros.ros.diagnostics import parse_status
from erva_ros.ros.msgs import state_joint_names, time_to_ns

#: Diagnostic keys (regular expressions) that carry each figure, as plant_sim_node and
#: nmpc_node (and offline sessions) name them.
ENERGY_KEY = re.compile(r'^harvested_j$')
DEADLINE_KEY = re.compile(r'^deadline_misses$')
FALLBACK_KEY = re.compile(r'(^|_)fallback_(plan|passive)$')
SOLVE_KEY = re.compile(r'^solve_ms_')
REPORTED_TIMING_KEY = re.compile(r'^(latency_ms|cmd_jitter_ms|tick_jitter_ms)_')
PLANT_HOLD_KEY = re.compile(r'^u_from_')


def _topic(name: str, namespace: str) -> str:
    return name if name.startswith('/') else f'{namespace}/{name}'


@dataclass
class Series:
    """A topic's samples: stamp, log and publish times (ns) and values."""

    stamp_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    log_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    pub_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    values: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    @property
    def n(self) -> int:
        return int(self.stamp_ns.size)


@dataclass
class SessionData:
    """Everything the report needs, decoded from one bag."""

    bag: Bag
    namespace: str
    state: Series            # values: positions z_s, z_us, z_d, velocities (NaN: no z_d)
    accel: Series
    generator: Series        # values: position, velocity, effort
    road: Series             # values: distance, height
    cmd: Series              # values: u0
    plans: List[np.ndarray]
    preview_stamp_ns: np.ndarray
    previews: List[np.ndarray]   # heights w(t0 + i·Ts)
    preview_dt: List[np.ndarray]  # time_from_start (s)
    diagnostics: List[Dict] = field(default_factory=list)   # per status message
    model: str = 'erva'      # the state's model kind (its joints): erva or benchmark

    @property
    def t0_ns(self) -> int:
        for s in (self.state, self.cmd, self.accel, self.road):
            if s.n:
                return int(s.stamp_ns[0])
        return int(self.bag.start_ns or 0)

    def x(self, i: int) -> np.ndarray:
        """Return the i-th recorded state as the model's x = [z_s, ż_s, z_us, ż_us(, z_d, ż_d)]."""
        v = self.state.values[i]
        n = len(state_joint_names(self.model))
        x = np.empty(2 * n)
        x[0::2], x[1::2] = v[:n], v[3:3 + n]
        return x


def _series(rows, width) -> Series:
    if not rows:
        return Series(values=np.zeros((0, width)))
    arr = np.asarray([r[3] for r in rows], dtype=float).reshape(len(rows), width)
    return Series(np.asarray([r[0] for r in rows], dtype=np.int64),
                  np.asarray([r[1] for r in rows], dtype=np.int64),
                  np.asarray([r[2] for r in rows], dtype=np.int64), arr)


def _first(values) -> float:
    """Return the first of a message's values, NaN if it has none."""
    return values[0] if len(values) else math.nan


def _padded(values, n: int = 3) -> List[float]:
    """Return the first ``n`` values, NaN-padded (a benchmark state has no z_d)."""
    values = list(values)[:n]
    return values + [math.nan] * (n - len(values))


def guess_namespace(bag: Bag) -> str:
    """Return the namespace of the contract topics in ``bag`` (default /erva).

    A namespace with both ``state`` and ``damping_cmd`` wins: an `erva run --ecu
    virtual` bag also holds ``<ns>/ecu_sim/state``.
    """
    found = []
    for suffix in (contract.DAMPING_CMD, contract.STATE):
        found += [n.rsplit('/', 1)[0] or '/' for n in sorted(bag.topics)
                  if n.endswith('/' + suffix)]
    for ns in found:
        if {_topic(contract.STATE, ns), _topic(contract.DAMPING_CMD, ns)} <= set(bag.topics):
            return ns
    return found[0] if found else contract.NAMESPACE


class _Rows:
    """The rows of one bag's contract topics, one small decoder per topic."""

    def __init__(self):
        self.rows: Dict[str, list] = {k: [] for k in (
            contract.STATE, contract.SPRUNG_ACCEL, contract.GENERATOR, contract.ROAD_HEIGHT,
            contract.DAMPING_CMD)}
        self.plans: List[np.ndarray] = []
        self.previews: List[np.ndarray] = []
        self.preview_dt: List[np.ndarray] = []
        self.preview_stamps: List[int] = []
        self.diagnostics: List[Dict] = []
        self.state_joints: Optional[tuple] = None

    def _row(self, kind: str, m, msg, values) -> None:
        self.rows[kind].append((time_to_ns(msg.header.stamp), m.log_time_ns,
                                m.publish_time_ns, values))

    def state(self, m, msg) -> None:
        self.state_joints = self.state_joints or tuple(msg.name)
        self._row(contract.STATE, m, msg, _padded(msg.position) + _padded(msg.velocity))

    def sprung_accel(self, m, msg) -> None:
        self._row(contract.SPRUNG_ACCEL, m, msg, [msg.accel.linear.z])

    def generator(self, m, msg) -> None:
        self._row(contract.GENERATOR, m, msg,
                  [_first(msg.position), _first(msg.velocity), _first(msg.effort)])

    def road_height(self, m, msg) -> None:
        self._row(contract.ROAD_HEIGHT, m, msg, [msg.point.x, msg.point.z])

    def road_preview(self, m, msg) -> None:
        self.preview_stamps.append(time_to_ns(msg.header.stamp))
        self.previews.append(np.array([_first(p.positions) for p in msg.points]))
        self.preview_dt.append(np.array([time_to_ns(p.time_from_start) * 1e-9
                                         for p in msg.points]))

    def damping_cmd(self, m, msg) -> None:
        plan = np.array([_first(p.positions) for p in msg.points])
        self.plans.append(plan)
        self._row(contract.DAMPING_CMD, m, msg, [_first(plan)])

    def diagnostics_array(self, m, msg) -> None:
        for status in msg.status:
            name, level, text, values = parse_status(status)
            self.diagnostics.append({'log_ns': m.log_time_ns, 'name': name, 'level': level,
                                     'message': text, 'values': values})

    def model(self) -> str:
        """Return the model kind whose state joints were recorded (erva without states)."""
        bench = state_joint_names('benchmark')
        return 'benchmark' if self.state_joints == bench else 'erva'


def load_session(bag: Bag, namespace: Optional[str] = None) -> SessionData:
    """Decode the contract topics of ``bag`` into arrays (see module doc)."""
    ns = namespace or guess_namespace(bag)
    rows = _Rows()
    decoders = {_topic(contract.STATE, ns): rows.state,
                _topic(contract.SPRUNG_ACCEL, ns): rows.sprung_accel,
                _topic(contract.GENERATOR, ns): rows.generator,
                _topic(contract.ROAD_HEIGHT, ns): rows.road_height,
                _topic(contract.ROAD_PREVIEW, ns): rows.road_preview,
                _topic(contract.DAMPING_CMD, ns): rows.damping_cmd,
                contract.DIAGNOSTICS: rows.diagnostics_array}
    for m, msg in decoded(bag, [t for t in bag.topics if t in decoders]):
        decoders[m.topic](m, msg)
    r = rows.rows
    return SessionData(bag, ns, _series(r[contract.STATE], 6),
                       _series(r[contract.SPRUNG_ACCEL], 1), _series(r[contract.GENERATOR], 3),
                       _series(r[contract.ROAD_HEIGHT], 2), _series(r[contract.DAMPING_CMD], 1),
                       rows.plans, np.asarray(rows.preview_stamps, dtype=np.int64),
                       rows.previews, rows.preview_dt, rows.diagnostics, rows.model())


def _number(text) -> Optional[float]:
    try:
        v = float(text)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def last_diagnostic_values(data: SessionData) -> Dict[str, Dict[str, str]]:
    """Return, per status name, the last value of each key seen on /diagnostics."""
    out: Dict[str, Dict[str, str]] = {}
    for d in data.diagnostics:
        out.setdefault(d['name'], {}).update(d['values'])
    return out


def _pick(last: Dict[str, Dict[str, str]], pattern) -> Dict[str, float]:
    found: Dict[str, float] = {}
    for status, values in last.items():
        for key, text in values.items():
            v = _number(text)
            if v is not None and pattern.search(key):
                found[f'{status}/{key}'] = v
    return found


def _sample_time(stamps_ns: np.ndarray) -> Optional[float]:
    if stamps_ns.size < 2:
        return None
    d = np.diff(stamps_ns) * 1e-9
    d = d[d > 0]
    return float(np.median(d)) if d.size else None


def _jitter(times_ns: np.ndarray, ts: float) -> Dict:
    if times_ns.size < 2:
        return {'period_ms': percentiles_ms([]), 'jitter_ms': percentiles_ms([])}
    d = np.diff(np.sort(times_ns)) * 1e-9
    return {'period_ms': percentiles_ms(d), 'jitter_ms': percentiles_ms(np.abs(d - ts))}


def compute_report(data: SessionData) -> Dict:
    """Return the report figures of a session (see module doc) as plain data."""
    bag = data.bag
    ts = _sample_time(data.state.stamp_ns) or _sample_time(data.cmd.stamp_ns)
    n = data.accel.n
    duration = n * ts if ts else bag.duration_s
    last = last_diagnostic_values(data)

    energy = _pick(last, ENERGY_KEY)
    gen = data.generator.values
    power_samples = gen[:, 1] * gen[:, 2] if data.generator.n else np.zeros(0)
    if energy:
        harvested_j = max(energy.values())
        source = 'plant diagnostics (' + ', '.join(sorted(energy)) + ')'
    elif power_samples.size and ts:
        harvested_j = float(np.nansum(power_samples) * ts)
        source = 'generator samples, rectangle rule'
    else:
        harvested_j, source = math.nan, 'none'
    metrics = comfort_power(data.accel.values[:, 0] if n else [], harvested_j, duration)

    report: Dict = {
        'bag': bag.path,
        'complete': bag.complete,
        'session': dict(bag.session),
        'namespace': data.namespace,
        'messages': {t.name: t.count for t in sorted(bag.topics.values(), key=lambda t: t.name)},
        'ts_s': ts,
        'duration_s': duration,
        'samples': {'state': data.state.n, 'sprung_accel': n, 'generator': data.generator.n,
                    'road_height': data.road.n, 'road_preview': len(data.previews),
                    'damping_cmd': data.cmd.n},
        'comfort': {'acc_2norm': metrics['acc_2norm'], 'acc_rms': metrics['acc_rms']},
        'power': {'power_w': metrics['power_w'], 'harvested_j': harvested_j,
                  'source': source,
                  'power_mean_samples_w': float(np.nanmean(power_samples))
                  if power_samples.size else math.nan},
    }
    report['timing'] = timing_report(data, ts)
    deadline = _pick(last, DEADLINE_KEY)
    fallbacks = _pick(last, FALLBACK_KEY)
    report['deadline_misses'] = {'reported': deadline,
                                 'total': int(sum(deadline.values())) if deadline else None,
                                 'late_commands': report['timing']['late_commands']}
    report['fallbacks'] = {'reported': fallbacks,
                           'total': int(sum(fallbacks.values())) if fallbacks else None}
    report['solve_ms'] = _pick(last, SOLVE_KEY)
    report['reported_timing_ms'] = _pick(last, REPORTED_TIMING_KEY)
    report['plant_command_source'] = _pick(last, PLANT_HOLD_KEY)
    report['diagnostics_errors'] = sorted({f'{d["name"]}: {d["message"]}'
                                           for d in data.diagnostics if d['level'] >= ERROR})
    return report


def timing_report(data: SessionData, ts: Optional[float]) -> Dict:
    """Return command period/jitter, state → command latency and unanswered states.

    ``clock`` says what the stamps are: ``wall`` (realtime: stamps, publish and log
    times share the system clock), ``sim`` (lock-step: stamps and log times are sim
    time, publish times wall time -- then only ``wall_per_step_ms``, the wall time
    between commands, is meaningful) or ``offline`` (no transport at all).
    """
    offline = data.bag.session.get('source', '').startswith('offline')
    out: Dict = {'offline': offline, 'clock': 'offline' if offline else None,
                 'publish': None, 'log': None, 'latency_publish_ms': percentiles_ms([]),
                 'latency_log_ms': percentiles_ms([]), 'late_commands': None,
                 'unanswered_states': None, 'wall_per_step_ms': percentiles_ms([])}
    cmd = data.cmd
    if not ts or cmd.n < 2:
        return out
    state_stamps = set(data.state.stamp_ns.tolist())
    answered = np.array([s in state_stamps for s in cmd.stamp_ns.tolist()])
    out['unanswered_states'] = int(len(state_stamps - set(cmd.stamp_ns.tolist())))
    lat_pub = (cmd.pub_ns[answered] - cmd.stamp_ns[answered]) * 1e-9
    lat_log = (cmd.log_ns[answered] - cmd.stamp_ns[answered]) * 1e-9
    # Stamps in sim time (lock-step) and publish times in wall time do not compare.
    wall = bool(lat_pub.size) and abs(float(np.median(lat_pub))) < 1.0
    if offline:
        return out
    if not wall:
        out['clock'] = 'sim'
        out['wall_per_step_ms'] = percentiles_ms(np.diff(np.sort(cmd.pub_ns)) * 1e-9)
        return out
    out['clock'] = 'wall'
    out['publish'] = _jitter(cmd.pub_ns, ts)
    out['log'] = _jitter(cmd.log_ns, ts)
    out['late_commands'] = int(np.sum(np.diff(np.sort(cmd.pub_ns)) * 1e-9 > 1.5 * ts))
    out['latency_publish_ms'] = percentiles_ms(lat_pub)
    out['latency_log_ms'] = percentiles_ms(lat_log)
    return out


def write_plots(data: SessionData, out_dir: str, timing: bool = True) -> List[str]:
    """Write the report's PNG figures into ``out_dir`` (timing.png if ``timing``)."""
    from erva_ros.core.bag import report_plots
    return report_plots.write_all(data, out_dir, timing)


__all__ = ['SessionData', 'Series', 'load_session', 'compute_report', 'write_plots',
           'guess_namespace', 'last_diagnostic_values']
