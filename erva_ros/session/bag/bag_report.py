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
  within milliseconds (the fastest eigenvalue is −250 to −1300 1/s, docs/model.md),
  long before the next sample.
* Timing (realtime sessions): the command period and its jitter |Δ − Ts| from the
  damping_cmd publish times (the publisher's clock) and log times (the recorder's);
  the state → command latency as command publish/log time minus the stamp of the
  state it was computed from (damping_cmd.header.stamp = state stamp).  Lock-step
  sessions stamp in sim time: only the wall time per step is reported.  Solve times,
  deadline misses and fallbacks as the controller reports them on /diagnostics (its
  last typed report).  Commands more than 1.5·Ts after their predecessor are counted as
  late, states that never got a command as unanswered.
* Prediction (``prediction``, when nmpc_node published it): each plan's predicted z̈_s,
  power and states against what the bag then shows at t_k + h·Ts, h = 1, 5 and N
  (:func:`erva_ros.core.loop.prediction.prediction_errors`): RMS and max of the error.

Every message is decoded by the contract's one decoder per family
(:mod:`erva_ros.core.contract`): a report needs no ROS install.
"""

from dataclasses import dataclass, field
import math
from typing import Dict, List, Optional, Tuple

import numpy as np

from erva_ros.core import contract as wire, topics as contract
from erva_ros.core.bag import BagError
from erva_ros.core.plots import bag_report as report_plots
from erva_ros.core.bag.reader import Bag
from erva_ros.core.bag.session import stored_parameters
from erva_ros.core.bag.session_check import session_warnings
from erva_ros.core.levels import ERROR
from erva_ros.core.loop.prediction import OUTPUT_NAMES, prediction_errors
from erva_ros.core.metrics import comfort_power, percentiles_ms
from erva_ros.core.model.quarter_car import kind_of_joints, STATE_NAMES
from erva_ros.core.reports import (EcuSimReport, NMPCReport, NodeReport, PlantReport,
                                   report_from_status, Timing)
from erva_ros.session.run.segments import bag_block


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
    #: Every report on /diagnostics, by log time: (log_ns, report).
    reports: List[Tuple[int, NodeReport]] = field(default_factory=list)
    model: str = 'erva'      # the state's model kind (its joints): erva or benchmark
    #: ``prediction``: stamps t_k, joint names, tables (N + 1 rows, one column per name).
    prediction_stamp_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    prediction_names: Tuple[str, ...] = ()
    predictions: List[np.ndarray] = field(default_factory=list)

    @property
    def t0_ns(self) -> int:
        for s in (self.state, self.cmd, self.accel, self.road):
            if s.n:
                return int(s.stamp_ns[0])
        return int(self.bag.start_ns or 0)

    def x(self, i: int) -> np.ndarray:
        """Return the i-th recorded state as the model's x = [z_s, ż_s, z_us, ż_us(, z_d, ż_d)]."""
        v = self.state.values[i]
        n = len(STATE_NAMES[self.model]) // 2
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


def load_session(bag: Bag, namespace: Optional[str] = None) -> SessionData:
    """Decode the contract topics of ``bag`` into arrays (see module doc)."""
    ns = namespace or guess_namespace(bag)
    topic = {name: _topic(name, ns) for name in (
        contract.STATE, contract.SPRUNG_ACCEL, contract.GENERATOR, contract.ROAD_HEIGHT,
        contract.ROAD_PREVIEW, contract.DAMPING_CMD, contract.PREDICTION)}
    rows: Dict[str, list] = {name: [] for name in topic}
    plans, previews, preview_dt, preview_stamps = [], [], [], []
    predicted: List[wire.Predicted] = []
    reports: List[Tuple[int, NodeReport]] = []
    joints = None
    by_topic = {v: k for k, v in topic.items()}
    wanted = [t for t in bag.topics if t in by_topic or t == contract.DIAGNOSTICS]
    for m in bag.messages(wanted):
        try:
            if m.topic == contract.DIAGNOSTICS:
                reports += [(m.log_time_ns, report_from_status(st))
                            for st in wire.decode_diagnostics(m.data)[1]]
                continue
            name = by_topic[m.topic]
            if name == contract.STATE:
                j = wire.decode_joints(m.data)
                joints = joints or j.names
                row = (j.stamp_ns, _padded(j.position) + _padded(j.velocity))
            elif name == contract.ROAD_PREVIEW:
                r = wire.decode_preview(m.data)
                preview_stamps.append(r.stamp_ns)
                previews.append(r.heights)
                preview_dt.append(np.array(wire.decode_command_offsets(m.data)))
                continue
            elif name == contract.PREDICTION:
                predicted.append(wire.decode_prediction(m.data))
                continue
            elif name == contract.DAMPING_CMD:
                r = wire.decode_command(m.data)
                plans.append(r.plan)
                row = (r.stamp_ns, [r.plan[0]])
            else:
                r = wire.DECODERS[name](m.data)
                row = (r.stamp_ns, {contract.SPRUNG_ACCEL: lambda: [r.sprung_accel],
                                    contract.GENERATOR: lambda: [r.position, r.velocity,
                                                                 r.effort],
                                    contract.ROAD_HEIGHT: lambda: [r.distance_m, r.height_m]
                                    }[name]())
        except wire.MessageRejected as exc:
            raise BagError(f'{bag.path}: a {m.type} message on {m.topic} at '
                           f'{m.log_time_ns} ns does not decode ({exc})') from None
        rows[name].append((row[0], m.log_time_ns, m.publish_time_ns, row[1]))
    try:
        model = kind_of_joints(joints) if joints else 'erva'
    except ValueError as exc:
        raise BagError(f'{bag.path}: {exc}') from None
    return SessionData(bag, ns, _series(rows[contract.STATE], 6),
                       _series(rows[contract.SPRUNG_ACCEL], 1),
                       _series(rows[contract.GENERATOR], 3),
                       _series(rows[contract.ROAD_HEIGHT], 2),
                       _series(rows[contract.DAMPING_CMD], 1),
                       plans, np.asarray(preview_stamps, dtype=np.int64), previews, preview_dt,
                       reports, model,
                       np.asarray([p.stamp_ns for p in predicted], dtype=np.int64),
                       predicted[0].names if predicted else (),
                       [p.values for p in predicted])


def last_reports(data: SessionData) -> Dict[str, NodeReport]:
    """Return the last report of each status name on /diagnostics."""
    return {r.node: r for _, r in data.reports}


def _numbers(named: Dict[str, float]) -> Dict[str, float]:
    return {k: float(v) for k, v in named.items() if v is not None and math.isfinite(v)}


def _timing(name: str, field_name: str, t: Timing) -> Dict[str, float]:
    return _numbers({f'{name}/{field_name}_{k}': v for k, v in t.as_dict().items()})


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
    last = last_reports(data)
    plants = {k: r for k, r in last.items() if isinstance(r, (PlantReport, EcuSimReport))}
    controllers = {k: r for k, r in last.items() if isinstance(r, NMPCReport)}

    energy = _numbers({f'{k}/harvested_j': r.harvested_j for k, r in plants.items()})
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
        # Not closed properly, cut short, repaired, or holding another session's messages.
        'warnings': _warnings(bag),
        'session': dict(bag.session),
        'namespace': data.namespace,
        'messages': {t.name: t.count for t in sorted(bag.topics.values(), key=lambda t: t.name)},
        'ts_s': ts,
        'duration_s': duration,
        'samples': {'state': data.state.n, 'sprung_accel': n, 'generator': data.generator.n,
                    'road_height': data.road.n, 'road_preview': len(data.previews),
                    'damping_cmd': data.cmd.n, 'prediction': len(data.predictions)},
        'comfort': {'acc_2norm': metrics['acc_2norm'], 'acc_rms': metrics['acc_rms']},
        'power': {'power_w': metrics['power_w'], 'harvested_j': harvested_j,
                  'source': source,
                  'power_mean_samples_w': float(np.nanmean(power_samples))
                  if power_samples.size else math.nan},
    }
    report['timing'] = timing_report(data, ts)
    report['prediction'] = prediction_report(data, ts)
    deadline = {f'{k}/deadline_misses': float(r.deadline_misses)
                for k, r in controllers.items()}
    fallbacks = {f'{k}/controller_fallback_{which}': float(
        getattr(r, f'controller_fallback_{which}'))
        for k, r in controllers.items() for which in ('plan', 'passive')}
    report['deadline_misses'] = {'reported': deadline,
                                 'total': int(sum(deadline.values())) if deadline else None,
                                 'late_commands': report['timing']['late_commands']}
    report['fallbacks'] = {'reported': fallbacks,
                           'total': int(sum(fallbacks.values())) if fallbacks else None}
    report['solve_ms'] = {}
    report['reported_timing_ms'] = {}
    for k, r in controllers.items():
        report['solve_ms'].update(_timing(k, 'solve_ms', r.solve_ms))
        for name in ('latency_ms', 'cmd_jitter_ms', 'tick_jitter_ms'):
            report['reported_timing_ms'].update(_timing(k, name, getattr(r, name)))
    report['plant_command_source'] = {
        f'{k}/u_from_{src}': float(getattr(r, f'u_from_{src}'))
        for k, r in plants.items() if isinstance(r, PlantReport)
        for src in ('command', 'plan', 'passive')}
    inside, outside = errors_by_span(data, ts)
    report['diagnostics_errors'] = inside
    report['diagnostics_errors_outside'] = outside
    report['tuning'] = bag_block(data)      # the segments by parameter set (live changes)
    return report


def errors_by_span(data: SessionData, ts: Optional[float]
                   ) -> Tuple[List[str], Dict[str, List[str]]]:
    """Return the ERROR statuses ('node: message') logged within the loop, and outside it.

    Those outside by node: {node: [messages]}.

    The loop spans the first state's arrival to one period after the last's (the bag's
    log times).  Outside it come the start-up's and the shut-down's designed states: the
    bridge waiting for the ECU's first frame before the loop starts, its safe command
    once the NMPC stopped after the last sample and the ECU silent once it ended.
    """
    errors = [(t, r.node, r.message) for t, r in data.reports if r.level >= ERROR]
    if data.state.n:
        lo = int(data.state.log_ns.min())
        hi = int(data.state.log_ns.max()) + int(round((ts or 0.0) * 1e9))
    else:
        lo, hi = -1, 2 ** 63
    inside = sorted({f'{node}: {text}' for t, node, text in errors if lo <= t <= hi})
    outside: Dict[str, List[str]] = {}
    for t, node, text in errors:
        if not lo <= t <= hi and f'{node}: {text}' not in inside:
            outside.setdefault(node, [])
            if text not in outside[node]:
                outside[node].append(text)
    return inside, outside


def _warnings(bag) -> List[str]:
    """Return what is wrong with the bag's files (its one home) and with its session."""
    return bag.warnings() + session_warnings(bag)


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


def actual_signals(data: SessionData) -> Dict[str, Tuple[np.ndarray, np.ndarray]]:
    """Return what happened, by prediction joint name: (stamps ns, values)."""
    out = {}
    if data.accel.n:
        out[OUTPUT_NAMES[0]] = (data.accel.stamp_ns, data.accel.values[:, 0])
    if data.generator.n:
        out[OUTPUT_NAMES[1]] = (data.generator.stamp_ns,
                                data.generator.values[:, 1] * data.generator.values[:, 2])
    if data.state.n:
        xs = np.array([data.x(i) for i in range(data.state.n)])
        for j, name in enumerate(STATE_NAMES[data.model]):
            out[name] = (data.state.stamp_ns, xs[:, j])
    return {k: v for k, v in out.items() if k in data.prediction_names}


def prediction_report(data: SessionData, ts: Optional[float]) -> Optional[Dict]:
    """Return the prediction errors at 1, 5 and N steps ahead (None: no prediction)."""
    if not data.predictions or not ts:
        return None
    ts_ns = int(round(ts * 1e9))
    errors = prediction_errors(data.prediction_stamp_ns.tolist(), data.predictions,
                               data.prediction_names, ts_ns, actual_signals(data))
    return {'messages': len(data.predictions),
            'horizon': min(len(t) for t in data.predictions) - 1,
            'names': list(data.prediction_names),
            'steps': {str(h): e for h, e in errors.items()}}


def write_plots(data: SessionData, out_dir: str, timing: bool = True) -> List[str]:
    """Write the report's PNG figures into ``out_dir`` (timing.png if ``timing``)."""
    live = stored_parameters(data.bag.session).get('live') or {}
    deadlines = {'ts': _sample_time(data.state.stamp_ns) or _sample_time(data.cmd.stamp_ns)
                 or 0.0, 'd': float(live.get('command_delay_s') or 0.0)}
    return report_plots.write_all(data, out_dir, timing, actual_signals(data), deadlines)


__all__ = ['SessionData', 'Series', 'load_session', 'compute_report', 'write_plots',
           'guess_namespace', 'last_reports', 'errors_by_span', 'actual_signals',
           'prediction_report']
