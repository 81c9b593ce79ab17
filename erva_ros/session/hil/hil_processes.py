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

from typing import Dict, List, Optional, Sequence

from erva_ros.core import topics
from erva_ros.core.hil.settings import default_hil_file
from erva_ros.core.hil.transport import free_udp_ports
from erva_ros.ros.realtime import DEFAULT_PRIORITY
from erva_ros.session.processes import child_env, module_argv, node_argv, ProcessSpec


def hil_process_specs(params_file: str, namespace: str = topics.NAMESPACE,
                      duration_s: float = 0.0,
                      hil_file: Optional[str] = None, model: str = 'erva', ts: float = 0.02,
                      ports: Optional[tuple] = None, env: Optional[Dict[str, str]] = None,
                      road: str = 'session', wait_road_s: float = 60.0,
                      stamp_on_road_grid: bool = False,
                      realtime_priority: int = DEFAULT_PRIORITY,
                      prefix: Sequence[str] = (), can_log: str = '') -> List[ProcessSpec]:
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
    must exec the command, so that signals reach it.  ``can_log`` is the bridge's CAN
    trace (FILE.blf or FILE.asc; '' none).
    ``stamp_on_road_grid`` stamps the estimates with the road's sample instants, which the
    NMPC needs to pair a state with its preview (`erva run`).  ``realtime_priority`` is
    the SCHED_FIFO priority of all three once started (0: normal scheduling).
    """
    hil_file = hil_file or default_hil_file()
    bridge_port, ecu_port = ports or free_udp_ports(2)
    base = child_env(env, force_local=True)
    files = [params_file, hil_file]
    priority = {'realtime_priority': int(realtime_priority)}
    ecu = module_argv('erva_ros.cli', 'ecu-sim',
                      '--bus', f'udp:{ecu_port}:{bridge_port}', '--params', params_file,
                      '--hil-config', hil_file, '--model', model, '--ts', repr(float(ts)),
                      '--road', road, '--wait-road', repr(float(wait_road_s)), '--ros',
                      '--namespace', namespace,
                      '--duration', repr(float(duration_s)), '--json',
                      '--realtime-priority', str(int(realtime_priority)))
    bridge = node_argv('ecu_bridge_node', namespace, files,
                       {'bus': f'udp:{bridge_port}:{ecu_port}', **priority,
                        **({'can_log': can_log} if can_log else {})})
    estimator = node_argv('state_estimator_node', namespace, files,
                          {**({'stamp_on_road_grid': True} if stamp_on_road_grid else {}),
                           **priority})
    prefix = list(prefix)
    return [ProcessSpec('ecu_sim', prefix + ecu, dict(base)),
            ProcessSpec('ecu_bridge_node', prefix + bridge, dict(base)),
            ProcessSpec('state_estimator_node', prefix + estimator, dict(base))]


__all__ = ['ProcessSpec', 'hil_process_specs']
