"""The processes `erva run --ecu virtual` starts instead of plant_sim_node (the HIL loop).

    NMPC → damping_cmd → ecu_bridge_node ⇄ CAN (UDP on 127.0.0.1) ⇄ erva ecu-sim (plant)
         ← state ← state_estimator_node ← ecu/* ← ecu_bridge_node

:func:`hil_process_specs` returns three :class:`ProcessSpec` (argv + environment),
in start order: the simulated ECU (it waits for the first road height), the bridge
and the estimator.  The bridge and the ECU get a fresh pair of loopback UDP ports
(:class:`~erva_ros.core.hil.transport.LoopbackUdpBus`), so parallel runs never share a
bus.  The ECU publishes the ground truth (``sprung_accel``, ``generator``,
``ecu_sim/state``) and reports ``finished: true`` on /diagnostics after
``duration_s``; the estimator publishes ``state``.
"""

from dataclasses import dataclass, field
import os
import sys
from typing import Dict, List, Optional, Sequence

from erva_ros.core.hil.settings import default_hil_file
from erva_ros.ros.realtime import DEFAULT_PRIORITY
from erva_ros.core.hil.transport import free_udp_ports


@dataclass
class ProcessSpec:
    """One process to start: a name, its argv and its environment."""

    name: str
    argv: List[str]
    env: Dict[str, str] = field(default_factory=dict)


def hil_process_specs(params_file: str, namespace: str = '/erva', duration_s: float = 0.0,
                      hil_file: Optional[str] = None, model: str = 'erva', ts: float = 0.02,
                      ports: Optional[tuple] = None, env: Optional[Dict[str, str]] = None,
                      road: str = 'session', wait_road_s: float = 60.0,
                      stamp_on_road_grid: bool = False,
                      realtime_priority: int = DEFAULT_PRIORITY,
                      prefix: Sequence[str] = ()) -> List[ProcessSpec]:
    """Return the HIL processes for a session (see the module docstring).

    ``params_file`` is the session's ROS params file (physical parameters in ``/**``,
    as `erva run` writes it); ``hil_file`` the HIL parameters (default
    config/hil.yaml).  ``env`` is the base environment (default os.environ); the
    caller's ROS_DOMAIN_ID and ROS_STATIC_PEERS are kept and ROS_AUTOMATIC_DISCOVERY_RANGE
    is forced to LOCALHOST (with static peers: the hosts named there too, docs/hil.md).
    ``duration_s`` = 0 runs the ECU until it is stopped (SIGINT/SIGTERM); the ECU's run
    starts with the first road height it receives (within ``wait_road_s``).  ``road`` is
    the ECU's road: ``session`` (the road of ``params_file``, an `erva run` session file,
    known ahead on the grid of road/height) or ``ros`` (the heights as they arrive).
    ``prefix`` is put before each argv (e.g. ``ip netns exec NS``, ``taskset -c 1``): it
    must exec the command, so that signals reach it.
    ``stamp_on_road_grid`` stamps the estimates with the road's sample instants, which the
    NMPC needs to pair a state with its preview (`erva run`).  ``realtime_priority`` is
    the SCHED_FIFO priority of all three once started (0: normal scheduling).
    """
    hil_file = hil_file or default_hil_file()
    bridge_port, ecu_port = ports or free_udp_ports(2)
    base = dict(os.environ if env is None else env)
    base['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    base['PYTHONUNBUFFERED'] = '1'
    ros_args = ['--ros-args', '-r', f'__ns:={namespace}', '--params-file', params_file,
                '--params-file', hil_file]
    ecu = [sys.executable, '-m', 'erva_ros.cli', 'ecu-sim',
           '--bus', f'udp:{ecu_port}:{bridge_port}', '--params', params_file,
           '--hil-config', hil_file, '--model', model, '--ts', repr(float(ts)),
           '--road', road, '--wait-road', repr(float(wait_road_s)), '--ros',
           '--namespace', namespace,
           '--duration', repr(float(duration_s)), '--json',
           '--realtime-priority', str(int(realtime_priority))]
    bridge = [sys.executable, '-m', 'erva_ros.nodes.ecu_bridge_node', *ros_args,
              '-p', f'bus:=udp:{bridge_port}:{ecu_port}']
    estimator = [sys.executable, '-m', 'erva_ros.nodes.state_estimator_node', *ros_args]
    if stamp_on_road_grid:
        estimator += ['-p', 'stamp_on_road_grid:=true']
    for argv in (bridge, estimator):
        argv += ['-p', f'realtime_priority:={int(realtime_priority)}']
    prefix = list(prefix)
    return [ProcessSpec('ecu_sim', prefix + ecu, dict(base)),
            ProcessSpec('ecu_bridge_node', prefix + bridge, dict(base)),
            ProcessSpec('state_estimator_node', prefix + estimator, dict(base))]
