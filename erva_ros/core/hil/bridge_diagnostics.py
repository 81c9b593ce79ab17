"""The bridge's three reports (no ROS): command link, CAN bus, ECU heartbeat.

Each function fills one typed report (:mod:`erva_ros.core.reports`) from the bridge's
units (erva_ros/core/hil/bridge.py), level and message included; ecu_bridge_node adds its
latencies and publishes the three together on ``/diagnostics``.
"""

from typing import Any, Dict, Mapping, Sequence, Tuple

from erva_ros.core.hil.bus_link import BusLink
from erva_ros.core.hil.codec import EcuMode, Kind
from erva_ros.core.hil.command_watchdog import CommandWatchdog
from erva_ros.core.hil.ecu_cycles import EcuHeartbeat
from erva_ros.core.levels import ERROR, OK, WARN
from erva_ros.core.reports import (BridgeBusReport, BridgeCommandReport, BridgeEcuReport,
                                   NodeReport)

#: E2E rejections of received frames (erva_ros/core/hil/e2e.py).
REJECTIONS = ('wrong_length', 'bad_crc', 'repeated', 'skipped', 'bad_counter')


def _set(report: NodeReport, counts: Mapping[str, int], names: Sequence[str]) -> None:
    for name in names:
        setattr(report, name, int(counts[name]))


def command_status(watchdog: CommandWatchdog, counts: Mapping[str, int],
                   c_e_range: Tuple[float, float], now: float,
                   report: BridgeCommandReport) -> BridgeCommandReport:
    """Fill the command link's report: forwarding, waiting (WARN) or timed out (ERROR)."""
    _set(report, counts, ('commands_received', 'commands_rejected', 'commands_stale',
                          'commands_clamped', 'commands_wrong_delay', 'command_timeouts',
                          'frames_sent',
                          'safe_frames_sent', 'plan_frames_sent', 'frames_not_sent'))
    worst = watchdog.timeouts_worst
    report.timeout_plan_frames_max = int(worst['plan_frames'])
    report.timeout_age_ms_max = round(worst['command_age_s'] * 1e3, 2)
    age = watchdog.command_age(now)
    cmd = watchdog.last_command
    report.command_age_s = age
    if cmd is not None:
        report.sent_c_e_ns_per_m, report.sent_duty = cmd.c_e, cmd.duty
        report.sent_mode = cmd.mode.name
    report.hardware_c_e_range_ns_per_m = '{:.1f}..{:.1f}'.format(*c_e_range)
    if watchdog.state == 'timeout':
        report.level, report.message = ERROR, (
            f'no fresh damping command for {age:.3f} s > {watchdog.timeout_s:.3f} s: sending '
            f'safe passive c_e = {watchdog.c_e_safe:.0f} Ns/m')
    elif watchdog.state == 'waiting':
        report.level, report.message = (WARN, 'waiting for the first damping command: '
                                        'sending safe passive')
    else:
        report.level, report.message = OK, 'forwarding damping commands'
    return report


def bus_status(link: BusLink, counts: Mapping[str, int], rx: Mapping[str, int],
               report: BridgeBusReport) -> BridgeBusReport:
    """Fill the CAN bus's report: up (WARN if frames were rejected) or lost (ERROR)."""
    _set(report, rx, tuple(rx))
    _set(report, counts, ('send_errors', 'bus_losses', 'bus_open_attempts',
                          'bus_open_failures', 'reconnects'))
    report.error = link.error
    if not link.up:
        report.level, report.message = ERROR, link.error or 'bus not open'
    else:
        rejected = sum(rx[k] for k in REJECTIONS)
        report.level = WARN if rejected else OK
        report.message = 'bus up' + (f', {rejected} frames rejected' if rejected else '')
    return report


def ecu_status(heartbeat: EcuHeartbeat, counts: Mapping[str, int], now: float,
               report: BridgeEcuReport) -> BridgeEcuReport:
    """Fill the ECU's report: silent (ERROR), its mode, FAULT (ERROR), passive (WARN)."""
    _set(report, counts, ('ecu_cycles', 'incomplete_cycles', 'ecu_silences'))
    st = heartbeat.last.get(Kind.STATUS)
    gen = heartbeat.last.get(Kind.GENERATOR)
    if st is not None:
        report.ecu_mode = st.mode.name
        report.c_e_applied_ns_per_m, report.c_e_mean_ns_per_m = st.c_e_applied, st.c_e_mean
        report.ecu_cmd_rejected_mod256 = int(st.cmd_rejected)
        report.ecu_cmd_timeouts_mod256 = int(st.cmd_timeouts)
    if gen is not None:
        report.generator_speed_rad_s = gen.speed
        report.generator_current_a, report.generator_voltage_v = gen.current, gen.voltage
    if not heartbeat.ever_heard:
        report.level, report.message = ERROR, 'ECU silent: no valid frame received yet'
    elif heartbeat.silent(now):
        report.level, report.message = (ERROR, 'ECU silent: no valid frame for '
                                        f'{now - heartbeat.last_heard:.3f} s')
    elif st is None:
        report.level, report.message = WARN, 'ECU sends sensors but no status yet'
    elif st.mode is EcuMode.FAULT:
        report.level, report.message = ERROR, 'ECU reports FAULT'
    elif st.mode is not EcuMode.CONTROLLED:
        report.level, report.message = WARN, f'ECU in {st.mode.name} (passive damping)'
    else:
        report.level, report.message = OK, 'ECU controlled'
    return report


def diag_dict(reports: Sequence[NodeReport]) -> Dict[str, Any]:
    """Return reports as plain data (for JSON output and tests)."""
    return {r.node: {'level': r.level, 'message': r.message, 'values': r.values()}
            for r in reports}
