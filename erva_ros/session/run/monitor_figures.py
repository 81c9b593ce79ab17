"""The figures of an `erva run` summary, each built by one small function from the monitor's store.

``obs`` is an :class:`~erva_ros.session.run.observations.Observations`: its streaming
figures of the data (``obs.streams``, :class:`~erva_ros.session.run.monitor_stats.SessionStreams`)
and each node's newest typed report.
:func:`summary` puts the blocks together: ``metrics``, ``commands``, ``nmpc``,
``scheduling``, ``plant``, ``road`` (and ``hil``), ``events``, ``messages`` and
``trajectory`` (the samples of the trajectory kept).
"""

import math
from typing import Any, Dict, Optional

from erva_ros.core.levels import LEVEL_NAMES
from erva_ros.core.metrics import comfort_power
from erva_ros.session.run import hil_summary
from erva_ros.session.run.monitor_stats import stats

#: Status changes kept in the summary (the first ones; a flapping node could make many).
MAX_EVENTS = 200
#: The NMPC's counters in the summary (fields of its report).
NMPC_COUNTERS = ('solves', 'commands', 'late', 'deadline_misses', 'state_timeouts',
                 'safe_commands', 'missed_samples', 'superseded_states', 'out_of_order',
                 'stale_previews', 'no_preview', 'rejected_state', 'rejected_preview',
                 'controller_fallback_plan', 'controller_fallback_passive',
                 'controller_failures', 'controller_late')
#: The NMPC's timings in the summary.
NMPC_TIMINGS = ('solve_ms', 'latency_ms', 'cmd_jitter_ms', 'tick_jitter_ms')
#: The plant's counters and timings in the summary.
PLANT_COUNTERS = ('steps', 'u_from_command', 'u_from_plan', 'u_from_passive', 'late_commands',
                  'road_gaps', 'lockstep_timeouts', 'rejected_road_height',
                  'rejected_damping_cmd', 'command_delay_ms', 'arrival_p999_ms')
PLANT_TIMINGS = ('loop_latency_ms', 'cmd_jitter_ms', 'road_latency_ms', 'step_ms',
                 'command_arrival_ms')


def _fields(report, names) -> Dict[str, Optional[int]]:
    return {k: None if report is None else getattr(report, k) for k in names}


def _timings(report, names) -> Dict[str, Dict[str, Any]]:
    return {k: stats(None if report is None else getattr(report, k)) for k in names}


def metrics(obs, ts: float, n_steps: int) -> Dict[str, Any]:
    """Return comfort and power of the first ``n_steps`` samples, and the real-time factor.

    The energy is the plant's own integral (``harvested_j`` of the plant, or of the ECU in
    HIL mode); the real-time factor is simulated time over the wall time between the
    first and the last state's arrival.
    """
    st = obs.streams
    n = min(st.accels, n_steps)
    plant = obs.report(hil_summary.ECU if obs.hil else 'plant_sim_node')
    harvested = float('nan') if plant is None else plant.harvested_j
    accel = st.first_accels(n)
    if not n:
        out = {}
    elif accel is not None:      # within the trajectory: the very samples
        out = comfort_power(accel, harvested, n * ts)
    else:
        out = comfort_from_sum(st.comfort_sum_squares(n), n, harvested, n * ts)
    # Between the samples too (the plant's own integral): the sampled measure sees the
    # instants where commands switch, and a delayed actuator moves the switch (docs/nmpc.md).
    out.update({'acc_rms_continuous': float('nan') if plant is None
                else plant.acc_rms_continuous, 'harvested_j': harvested, 'samples': n})
    rx = st.state_rx
    if rx.count > 1:
        span = (rx.last - rx.first) * 1e-9
        out['realtime_factor'] = (rx.count - 1) * ts / span if span > 0 else None
    return out


def comfort_from_sum(sum_squares: Optional[float], n: int, harvested_j: float,
                     duration_s: float) -> Dict[str, float]:
    """Return :func:`~erva_ros.core.metrics.comfort_power`'s figures from Σ a² of n samples."""
    if sum_squares is None:
        raise ValueError(f'the comfort of {n} samples: the monitor summed a different '
                         'number (Observations n_steps)')
    out = comfort_power([], harvested_j, duration_s)
    out.update({'acc_2norm': math.sqrt(sum_squares), 'acc_rms': math.sqrt(sum_squares / n)})
    return out


def commands(obs, ts: float, realtime: bool) -> Dict[str, Any]:
    """Return the commands received and, in real time, their rate, jitter and latencies.

    Jitter and state-to-command latency are measured where the commands are used, at the
    plant (its report; the HIL loop has no plant node), and also as this observer, one
    more subscriber, receives them.  Sample-to-command runs from the sample time t_k.
    """
    c = obs.streams.commands
    # Commands for samples the plant published a state of: not the safe commands of an
    # outage, except those stamped on a sample whose state the plant sent later (a
    # stalled road or plant bridged): such a sample is also among nmpc's missed_samples.
    out: Dict[str, Any] = {'received': c.received, 'for_samples': c.for_samples}
    if not (realtime and c.for_samples > 1):
        return out
    out['rate_hz'] = float((c.for_samples - 1) / (c.last_rx_s - c.first_rx_s))
    if not obs.hil:
        plant = obs.report('plant_sim_node')
        out['period_jitter_ms'] = stats(plant and plant.cmd_jitter_ms)
        out['state_to_command_ms'] = stats(plant and plant.loop_latency_ms)
    out['sample_to_command_ms'] = c.sample_to_command.summary()
    out['monitor'] = {'period_jitter_ms': c.jitter.jitter.summary(),
                      'state_to_command_ms': c.state_to_command.summary()}
    return out


def actuation(plant_block: Dict[str, Any], for_samples: int) -> Dict[str, Any]:
    """Return the timing model's figures: d, late commands, arrival, the d they would need.

    Each command acts at its sample t_k + d (logical execution time); it must arrive by
    then.  ``arrival_ms`` is t_k -> command received where it acts (plant or ECU), and
    ``smallest_delay_ms`` the least d that would have had 99.9 % of them on time (their
    p99.9).  ``actuation_jitter_ms`` is the actual application instant − t_k − d: the
    ECU measures its own; the simulated plant applies at t_k + d exactly (None).
    """
    late = plant_block.get('late_commands')
    p999 = plant_block.get('arrival_p999_ms')
    return {'command_delay_ms': plant_block.get('command_delay_ms'),
            'late': late,
            'late_pct': (100.0 * late / for_samples if late is not None and for_samples
                         else None),
            'arrival_ms': plant_block.get('command_arrival_ms', stats(None)),
            'smallest_delay_ms': (None if p999 is None or p999 != p999
                                  else math.ceil(p999 * 10) / 10),
            'actuation_jitter_ms': plant_block.get('actuation_jitter_ms')}


def nmpc(obs) -> Dict[str, Any]:
    """Return the controller's name, timings and counters from its newest report."""
    r = obs.report('nmpc_node')
    return {'controller': None if r is None else r.controller,
            **_timings(r, NMPC_TIMINGS), **_fields(r, NMPC_COUNTERS)}


def scheduling(obs) -> Dict[str, Any]:
    """Return what each node's threads got from realtime_priority (ros/realtime.py)."""
    return {name.replace(': bag recorder', ''): r.scheduling
            for name, r in obs.reports.items() if r.scheduling}


def plant(obs) -> Dict[str, Any]:
    """Return the plant's counters and timings (in HIL mode: the ECU's equivalents)."""
    if obs.hil:
        return hil_summary.plant_equivalents(obs.report)
    r = obs.report('plant_sim_node')
    return {**_fields(r, PLANT_COUNTERS), **_timings(r, PLANT_TIMINGS)}


#: The map preview's counts in the summary (RoadReport, without the ``map_`` prefix).
MAP_COUNTS = ('samples', 'points', 'fallback_points', 'fallback_samples', 'beyond_end_points',
              'before_start_points', 'gap_points', 'unmatched_points', 'alignments',
              'alignments_refused', 'unaligned_samples', 'offset_m', 'offset_std_m',
              'correlation')


def road(obs) -> Dict[str, Any]:
    """Return the road node's samples (published, skipped), and the map preview's counts.

    The map's streaks (``<name>_streak``: the longest run of previews that fell back, of
    unmatched previews, of refused alignments in a row) give their length and when they
    were, in s from the first state's stamp (None: there was none).
    """
    from erva_ros.core.loop.road_loop import STREAKS
    r = obs.report('road_preview_node')
    out = _fields(r, ('samples_published', 'samples_skipped'))
    if r is not None and r.source == 'map':
        out['map'] = {k: getattr(r, f'map_{k}') for k in MAP_COUNTS}
        out['map']['tries'] = r.map_alignments + r.map_alignments_refused
        out['map']['file'] = r.map_file
        s0 = obs.streams.state_stamp.first
        for name in STREAKS:
            n = getattr(r, f'map_{name}_streak')
            span = [None if not n or s0 is None else
                    round((getattr(r, f'map_{name}_streak_{end}_ns') - s0) * 1e-9, 3)
                    for end in ('from', 'to')]
            out['map'][f'{name}_streak'] = {'count': n, 'from_s': span[0], 'to_s': span[1]}
    return out


def rejected(obs, plant_block: Dict[str, Any]) -> Dict[str, Optional[int]]:
    """Return the input messages each node rejected, by topic, and those out of order."""
    nm, pl = obs.report('nmpc_node'), obs.report('plant_sim_node')
    road_node = obs.report('road_preview_node')
    out = {'state': nm and nm.rejected_state,
           'road/preview': nm and nm.rejected_preview,
           'road/height': pl and pl.rejected_road_height,
           'damping_cmd': plant_block.get('rejected_damping_cmd'),
           '/clock': road_node and road_node.rejected_clock}
    if obs.hil:   # the ECU ignores absurd road heights without counting them
        del out['road/height']
    # Inputs dropped for a stamp not newer than the newest (stamps going back).
    out['out_of_order'] = ((nm.out_of_order if nm else 0)
                           + (pl.out_of_order_commands if pl else 0))
    return out


def events(obs):
    """Return the nodes' status changes (the first MAX_EVENTS), t_s from the first state."""
    t0 = obs.streams.state_rx.first or 0
    return [{'t_s': round((rx - t0) * 1e-9, 3), 'node': node,
             'level': LEVEL_NAMES.get(level, str(level)), 'message': text}
            for rx, node, level, text in obs.events[:MAX_EVENTS]]


def messages(obs, rejected_block: Dict[str, Optional[int]]) -> Dict[str, Any]:
    """Return the message accounting: published, received, foreign, dropped, rejected."""
    published = obs.published()
    dropped = obs.dropped(published)
    return {'published': published, 'received': dict(obs.received),
            'foreign': dict(obs.foreign), 'foreign_total': sum(obs.foreign.values()),
            'foreign_statuses': obs.foreign_statuses,
            'dropped': dropped, 'dropped_total': sum(v for v in dropped.values() if v),
            'rejected': rejected_block,
            'rejected_total': sum(v for v in rejected_block.values() if v)}


def trajectory(obs) -> Dict[str, Any]:
    """Return the samples of the trajectory kept, of those received, and the cap.

    A session longer than the cap (Observations ``trajectory_cap``) keeps its first part.
    """
    st = obs.streams
    return {'samples': st.trajectory.rows, 'of': st.accels, 'cap': st.trajectory.cap,
            'complete': st.trajectory.rows == st.accels}


def summary(obs, ts: float, n_steps: int, realtime: bool) -> Dict[str, Any]:
    """Return the run's figures for a run of ``n_steps`` periods ``ts`` (see module doc)."""
    out: Dict[str, Any] = {'metrics': metrics(obs, ts, n_steps),
                           'commands': commands(obs, ts, realtime),
                           'nmpc': nmpc(obs), 'scheduling': scheduling(obs),
                           'plant': plant(obs), 'road': road(obs)}
    if obs.hil:
        finished = hil_summary.ECU in obs.finished_rx
        out['hil'] = hil_summary.hil_block(obs.report, obs.streams.error,
                                           obs.bridge_timeouts if finished else None)
        est = obs.report(hil_summary.ESTIMATOR)
        hil_summary.from_sample_instant(out, obs.streams.error,
                                        est is not None and est.road_at_tyre == 'estimated')
    if realtime:
        out['commands']['actuation'] = actuation(out['plant'], out['commands']['for_samples'])
    out['events'] = events(obs)
    out['messages'] = messages(obs, rejected(obs, out['plant']))
    out['trajectory'] = trajectory(obs)
    return out


__all__ = ['MAX_EVENTS', 'stats', 'metrics', 'commands', 'actuation', 'nmpc', 'scheduling',
           'plant', 'road', 'rejected', 'events', 'messages', 'trajectory',
           'comfort_from_sum', 'summary']
