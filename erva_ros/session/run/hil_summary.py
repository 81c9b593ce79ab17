"""The hardware-in-the-loop figures of `erva run --ecu virtual`, for the monitor's summary.

In HIL mode the plant is the simulated ECU (``erva ecu-sim``): it publishes the true
``sprung_accel``, ``generator`` and ``ecu_sim/state``; ``state`` comes from
state_estimator_node, and ecu_bridge_node carries the commands over CAN.  This module
maps what the summary takes from plant_sim_node to those processes' diagnostics
where an equivalent exists (:func:`published`, :func:`plant_equivalents`) and builds
the summary's ``hil`` block (:func:`hil_block`): the E2E drops and link counters of the
bridge and the ECU, the bridge's and the estimator's latencies, and the estimation
error against the ECU's ground truth.

The bridge never finishes: when the NMPC stops after the last sample, it follows the
plan once or twice, then times out to the safe command (as it should).  Its counters
include that tail; ``command_timeouts`` counts only the timeouts that began before
the ECU finished (``command_timeouts_total`` all of them).
"""

from typing import Any, Callable, Dict, Optional

import numpy as np

from erva_ros.core import topics
from erva_ros.core.hil import topics as hil_topics
from erva_ros.core.model.quarter_car import state_names_of
from erva_ros.core.reports import NodeReport
from erva_ros.session.run.monitor_stats import DERIVED, PairedError, stats

ECU = 'ecu_sim'
ESTIMATOR = 'state_estimator_node'
#: ecu_bridge_node publishes three statuses; the monitor keys them by these names.
BRIDGE_COMMAND = 'ecu_bridge_node: command'
BRIDGE_BUS = 'ecu_bridge_node: can bus'
BRIDGE_ECU = 'ecu_bridge_node: ecu'
#: Reports that come only periodically until the node stops (no `finished` one).
PERIODIC = (BRIDGE_COMMAND, BRIDGE_BUS, BRIDGE_ECU, ESTIMATOR)
#: ECU cycles left out of the estimation error: the filter starts from rest.
WARMUP = 25
#: The loop's latency chain, each stage as time since the sample instant t_k (report,
#: timing): the ECU's sensor frames on CAN, ecu/measurements at the estimator, the state
#: published, (the NMPC's command: the monitor's ``sample_to_command_ms``), the command
#: on CAN, and applied by the ECU.
CHAIN = {'sensors_on_can': (ECU, 'sample_to_can_ms'),
         'measurements_at_estimator': (ESTIMATOR, 'sample_to_measurements_ms'),
         'state_published': (ESTIMATOR, 'sample_to_state_ms'),
         'command_on_can': (BRIDGE_COMMAND, 'sample_to_can_ms'),
         'command_applied': (ECU, 'sample_to_applied_ms')}
#: The stages timed from the state's stamp (the estimator's, which the command carries);
#: the others from the ECU's own sample instant.
STAMPED_STAGES = ('measurements_at_estimator', 'state_published', 'command_on_can')
#: E2E rejections (erva_ros.core.hil.e2e) grouped as the summary reports them.
DROPS = {'crc': ('bad_crc',), 'counter': ('repeated', 'skipped', 'bad_counter'),
         'length': ('wrong_length',)}

Reports = Callable[[str], Optional[NodeReport]]


def _get(report: Optional[NodeReport], name: str):
    return None if report is None else getattr(report, name)


def published(report: Reports, final_only: bool = False) -> Dict[str, Optional[int]]:
    """Return the loop-side messages published per topic (None: not reported)."""

    def counted(r):
        return None if r is None or (final_only and not r.final) else r
    ecu, est = counted(report(ECU)), counted(report(ESTIMATOR))
    samples = _get(ecu, 'samples_published')
    return {topics.STATE: _get(est, 'updates'), topics.SPRUNG_ACCEL: samples,
            topics.GENERATOR: samples, hil_topics.TRUE_STATE: samples}


#: The ECU's figures of the timing model under the plant's names (monitor_figures.actuation).
TIMING_EQUIVALENTS = ('command_delay_ms', 'late_commands', 'arrival_p999_ms', 'u_from_command',
                      'u_from_plan', 'u_from_passive')
TIMING_STATS = ('command_arrival_ms', 'cmd_jitter_ms', 'actuation_jitter_ms')


def plant_equivalents(report: Reports) -> Dict[str, Any]:
    """Return the plant figures that have a HIL equivalent; the others are left out.

    steps = the ECU's integrated cycles; rejected_damping_cmd = commands the bridge
    refused (malformed, or made for another command delay).  The timing model's figures
    are the ECU's, where the commands act: its d, the late commands, t_k → command frame
    received (and its p99.9), the frames' period jitter, and the actuation instant's
    lateness (actual − (t_k + d), measured by the software ECU; none with d = 0, where
    a frame acts when it arrives); with d > 0 also where each cycle's damping came from
    (the cycle's command, an earlier plan, passive), decided at t_k + d as in the plant.
    """
    ecu = report(ECU)
    out: Dict[str, Any] = {'steps': _get(ecu, 'cycles'),
                           'rejected_damping_cmd': _get(report(BRIDGE_COMMAND),
                                                        'commands_rejected')}
    if ecu is not None:
        out.update({k: getattr(ecu, k) for k in TIMING_EQUIVALENTS})
        out.update({k: stats(getattr(ecu, k)) for k in TIMING_STATS})
        if not ecu.command_delay_ms > 0:     # at arrival: no fixed instant, no source
            for k in ('u_from_command', 'u_from_plan', 'u_from_passive'):
                out[k] = None
    return out


def hil_block(report: Reports, error: PairedError,
              timeouts_before_end: Optional[int]) -> Dict[str, Any]:
    """Return the summary's ``hil`` block (see the module doc).

    ``error`` holds the estimates against the ECU's truth (by stamp);
    ``timeouts_before_end`` counts the bridge's command status turning ERROR before the
    ECU's `finished` report arrived (None: it did not finish).
    """
    cmd, bus, link = report(BRIDGE_COMMAND), report(BRIDGE_BUS), report(BRIDGE_ECU)
    ecu, est = report(ECU), report(ESTIMATOR)
    bridge: Dict[str, Any] = {f'dropped_{k}': _sum(bus, names) for k, names in DROPS.items()}
    total = _get(cmd, 'command_timeouts')
    bridge['command_timeouts'] = total if timeouts_before_end is None else timeouts_before_end
    bridge['command_timeouts_total'] = total
    bridge.update({k: _get(cmd, k) for k in (
        'commands_received', 'commands_rejected', 'commands_clamped', 'commands_wrong_delay',
        'plan_frames_sent')})
    bridge['bus_errors'] = _sum(bus, ('send_errors', 'bus_losses', 'bus_open_failures'))
    bridge['reconnects'] = _get(bus, 'reconnects')
    bridge['incomplete_cycles'] = _get(link, 'incomplete_cycles')
    # The ECU checks the command frames the same way (its counters are rx_<name>).
    rx = {} if ecu is None else ecu.rx
    ecu_out: Dict[str, Any] = {f'dropped_{k}': None if ecu is None else
                               sum(rx.get(n, 0) for n in names) for k, names in DROPS.items()}
    ecu_out.update({k: _get(ecu, k) for k in (
        'cycles', 'commands_applied', 'command_timeouts', 'duty_out_of_range', 'overruns',
        'cycles_skipped', 'recomputed', 'mode_changes_unlogged', 'late_commands',
        'late_plan_frames', 'first_late_cycle')})
    ecu_out['bus_errors'] = _sum(ecu, ('send_errors', 'bus_losses'))
    ecu_out['mode'] = _get(ecu, 'ecu_mode')
    ecu_out['mode_changes'] = _get(ecu, 'mode_changes')
    ecu_out['road_mismatches'] = _get(ecu, 'road_mismatches')
    ecu_out['start_lag_ms'] = _get(ecu, 'start_lag_ms')
    bridge['commands_stale'] = _get(cmd, 'commands_stale')
    bridge['timeout_plan_frames_max'] = _get(cmd, 'timeout_plan_frames_max')
    bridge['timeout_age_ms_max'] = _get(cmd, 'timeout_age_ms_max')
    estimator: Dict[str, Any] = {k: _get(est, k) for k in (
        'updates', 'incomplete', 'gaps', 'restarts', 'late_or_repeated', 'rejected',
        'no_road', 'road_waits', 'road_extrapolated', 'before_road')}
    estimator['nis_mean'] = _get(est, 'nis_mean')
    estimator['error'] = estimation_error(error, _get(est, 'road_at_tyre') == 'estimated')
    return {'bridge': bridge, 'ecu': ecu_out, 'estimator': estimator,
            'latency_ms': {'bridge_ros_to_can': stats(_get(cmd, 'ros_to_can_ms')),
                           'bridge_can_to_ros': stats(_get(link, 'can_to_ros_ms')),
                           'estimator': stats(_get(est, 'latency_ms'))},
            # Each stage's point in time after the sample instant t_k (CHAIN).
            'chain_ms': {stage: stats(_get(report(name), timing))
                         for stage, (name, timing) in CHAIN.items()}}


#: The state's coordinates left out of the estimation error with the road at the tyre
#: estimated: the absolute heights z_s, z_us carry the road's unobservable offset, which
#: drifts (docs/road.md), so their error relative to their RMS means nothing; the
#: deflection z_s - z_us takes their place.  The velocities are observable up to a common
#: vertical velocity the road model's prior bounds.
NOT_OBSERVABLE = ('z_s', 'z_us')


def road_estimated_coordinates(state_names) -> tuple:
    """Return the coordinates shown with the road estimated (NOT_OBSERVABLE replaced)."""
    return ('z_s - z_us',) + tuple(n for n in state_names if n not in NOT_OBSERVABLE)


def estimation_error(error: PairedError, road_estimated: bool = False) -> Dict[str, Any]:
    """Return the RMS of estimate - truth per coordinate over the samples both have.

    Each estimate is paired with the ECU's truth of its sample (monitor_stats.PairedError);
    the first ``WARMUP`` pairs are left out (``error.warmup``).  ``relative_rms`` is that
    RMS over the truth's own RMS (the coordinate's size).  With ``road_estimated`` the
    coordinates are :func:`road_estimated_coordinates`, and ``not_observable`` names the
    state's coordinates left out.
    """
    n = error.matched
    if not n:
        return {'matched': 0}
    states = state_names_of(error.err2.shape[0] - len(DERIVED))
    names = states + tuple(name for name, _, _ in DERIVED)
    shown = road_estimated_coordinates(states) if road_estimated else states
    rms = dict(zip(names, np.sqrt(error.err2 / n).tolist()))
    scale = dict(zip(names, np.sqrt(error.true2 / n).tolist()))
    out: Dict[str, Any] = {
        'matched': n, 'rms': {k: rms[k] for k in shown},
        'relative_rms': {k: rms[k] / scale[k] if scale[k] > 0 else None for k in shown}}
    if road_estimated:
        out['not_observable'] = list(NOT_OBSERVABLE)
    return out


def from_sample_instant(summary: Dict[str, Any], error: PairedError,
                        road_estimated: bool) -> None:
    """Make the figures timed from a state's stamp start at the ECU's sample instant t_k.

    On the road grid the estimator stamps each cycle with t_k itself.  With the road
    estimated it stamps it with the k·Ts of the real-ECU contract (docs/hil.md §8), which
    is t_k when the ECU keeps the contract (`erva run`'s does: the road's samples are on
    k·Ts).  An ECU off that grid puts t_k ``error.offset_ns`` before the stamp the state,
    the preview and the command carry; each figure timed from it (the estimator's stages
    of the chain, the command on CAN, the NMPC's and the monitor's sample -> command) is
    then shifted by that constant, measured here against the ECU's truth, so it runs from
    t_k too (a percentile of values shifted by a constant is shifted by it).  Unknown (no
    pair, or pairs at different offsets): those figures are not shown.
    ``summary['hil']['stamp_offset_ms']`` gives the offset.
    """
    hil = summary['hil']
    if not road_estimated:
        offset_ms: Optional[float] = 0.0
    elif error.offset_ns is not None and error.offset_spread_ns == 0:
        offset_ms = error.offset_ns * 1e-6
    else:
        offset_ms = None
    hil['stamp_offset_ms'] = offset_ms
    timed = [(hil['chain_ms'], k) for k in STAMPED_STAGES]
    timed += [(summary['commands'], 'sample_to_command_ms'), (summary['nmpc'], 'latency_ms')]
    for block, key in timed:
        if key not in block or offset_ms == 0.0:
            continue
        block[key] = stats(None) if offset_ms is None else {
            k: v if k == 'samples' else v + offset_ms for k, v in block[key].items()}


def _sum(report: Optional[NodeReport], names) -> Optional[int]:
    """Return the sum of a report's counters (None without the report)."""
    return None if report is None else sum(getattr(report, n) for n in names)


__all__ = ['ECU', 'ESTIMATOR', 'PERIODIC', 'CHAIN', 'STAMPED_STAGES',
           'road_estimated_coordinates', 'NOT_OBSERVABLE', 'published', 'plant_equivalents',
           'hil_block', 'estimation_error', 'from_sample_instant']
