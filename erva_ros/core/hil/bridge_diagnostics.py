"""The bridge's three statuses (no ROS): command link, CAN bus, ECU heartbeat.

ROS-free :class:`DiagStatus` (diagnostic_msgs/DiagnosticStatus's fields) built from the
bridge's units (erva_ros/core/hil/bridge.py); ecu_bridge_node adds its latencies and
publishes them on ``/diagnostics``.
"""

from dataclasses import dataclass, field
from typing import Any, Dict, Mapping, Sequence, Tuple

from erva_ros.core.hil.bus_link import BusLink
from erva_ros.core.hil.codec import EcuMode, Kind
from erva_ros.core.hil.command_watchdog import CommandWatchdog
from erva_ros.core.hil.ecu_cycles import EcuHeartbeat
from erva_ros.core.levels import ERROR, OK, WARN

#: E2E rejections of received frames (erva_ros/core/hil/e2e.py).
REJECTIONS = ('wrong_length', 'bad_crc', 'repeated', 'skipped', 'bad_counter')


@dataclass
class DiagStatus:
    """A ROS-free diagnostic_msgs/DiagnosticStatus."""

    level: int
    name: str
    message: str
    values: Dict[str, str] = field(default_factory=dict)


def command_status(watchdog: CommandWatchdog, counts: Mapping[str, int],
                   c_e_range: Tuple[float, float], now: float, name: str) -> DiagStatus:
    """Return the command link's status: forwarding, waiting (WARN) or timed out (ERROR)."""
    cmd = watchdog.last_command
    values = {k: str(counts[k]) for k in (
        'commands_received', 'commands_rejected', 'commands_stale', 'commands_clamped',
        'command_timeouts', 'frames_sent', 'safe_frames_sent', 'plan_frames_sent',
        'frames_not_sent')}
    worst = watchdog.timeouts_worst
    values['timeout_plan_frames_max'] = str(worst['plan_frames'])
    values['timeout_age_ms_max'] = f'{worst["command_age_s"] * 1e3:.2f}'
    age = watchdog.command_age(now)
    values.update({
        'command_age_s': f'{age:.4f}',
        'sent_c_e_ns_per_m': f'{cmd.c_e:.1f}' if cmd else '',
        'sent_duty': f'{cmd.duty:.4f}' if cmd else '',
        'sent_mode': cmd.mode.name if cmd else '',
        'hardware_c_e_range_ns_per_m': '{:.1f}..{:.1f}'.format(*c_e_range)})
    if watchdog.state == 'timeout':
        return DiagStatus(ERROR, name, f'no fresh damping command for {age:.3f} s > '
                          f'{watchdog.timeout_s:.3f} s: sending safe passive c_e = '
                          f'{watchdog.c_e_safe:.0f} Ns/m', values)
    if watchdog.state == 'waiting':
        return DiagStatus(WARN, name, 'waiting for the first damping command: sending safe '
                          'passive', values)
    return DiagStatus(OK, name, 'forwarding damping commands', values)


def bus_status(link: BusLink, counts: Mapping[str, int], rx: Mapping[str, int],
               name: str) -> DiagStatus:
    """Return the CAN bus's status: up (WARN if frames were rejected) or lost (ERROR)."""
    values = {k: str(v) for k, v in rx.items()}
    values.update({k: str(counts[k]) for k in (
        'send_errors', 'bus_losses', 'bus_open_attempts', 'bus_open_failures', 'reconnects')})
    values['error'] = link.error
    if not link.up:
        return DiagStatus(ERROR, name, link.error or 'bus not open', values)
    rejected = sum(rx[k] for k in REJECTIONS)
    message = 'bus up' + (f', {rejected} frames rejected' if rejected else '')
    return DiagStatus(WARN if rejected else OK, name, message, values)


def ecu_status(heartbeat: EcuHeartbeat, counts: Mapping[str, int], now: float,
               name: str) -> DiagStatus:
    """Return the ECU's status: silent (ERROR), its mode, FAULT (ERROR), passive (WARN)."""
    st = heartbeat.last.get(Kind.STATUS)
    gen = heartbeat.last.get(Kind.GENERATOR)
    values = {k: str(counts[k]) for k in ('ecu_cycles', 'incomplete_cycles', 'ecu_silences')}
    if st is not None:
        values.update({'ecu_mode': st.mode.name, 'c_e_applied_ns_per_m': f'{st.c_e_applied:g}',
                       'c_e_mean_ns_per_m': f'{st.c_e_mean:g}',
                       'ecu_cmd_rejected_mod256': str(st.cmd_rejected),
                       'ecu_cmd_timeouts_mod256': str(st.cmd_timeouts)})
    if gen is not None:
        values.update({'generator_speed_rad_s': f'{gen.speed:g}',
                       'generator_current_a': f'{gen.current:g}',
                       'generator_voltage_v': f'{gen.voltage:g}'})
    if not heartbeat.ever_heard:
        return DiagStatus(ERROR, name, 'ECU silent: no valid frame received yet', values)
    if heartbeat.silent(now):
        return DiagStatus(ERROR, name, 'ECU silent: no valid frame for '
                          f'{now - heartbeat.last_heard:.3f} s', values)
    if st is None:
        return DiagStatus(WARN, name, 'ECU sends sensors but no status yet', values)
    if st.mode is EcuMode.FAULT:
        return DiagStatus(ERROR, name, 'ECU reports FAULT', values)
    if st.mode is not EcuMode.CONTROLLED:
        return DiagStatus(WARN, name, f'ECU in {st.mode.name} (passive damping)', values)
    return DiagStatus(OK, name, 'ECU controlled', values)


def diag_dict(statuses: Sequence[DiagStatus]) -> Dict[str, Any]:
    """Return statuses as plain data (for JSON output and tests)."""
    return {s.name: {'level': s.level, 'message': s.message, 'values': dict(s.values)}
            for s in statuses}
