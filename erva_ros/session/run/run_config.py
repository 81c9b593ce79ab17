"""What `erva run` is asked to run: its options (:class:`RunConfig`) and what they start.

The options are validated and turned into a session -- its effective parameters and the
params file the nodes read -- by :mod:`erva_ros.session.run.session_file`.
"""

from dataclasses import dataclass, field
from typing import Any, Dict, Optional

from erva_ros.core import topics
from erva_ros.core.errors import CLIError

#: The live nodes in start order (the slowest to start first).
NODES = ('nmpc_node', 'plant_sim_node', 'road_preview_node')
#: The processes replacing plant_sim_node with --ecu virtual, in start order.
HIL_PROCESSES = ('ecu_sim', 'ecu_bridge_node', 'state_estimator_node')
HIL_NODES = ('nmpc_node', *HIL_PROCESSES, 'road_preview_node')
#: Managed (lifecycle) nodes `erva run` configures, then activates in this order: the
#: controller first, then (--ecu) the estimator and the CAN bridge, the time master (the
#: road in real time, the plant in lock-step) last, so nothing is published before every
#: node that takes it acts on it.
ACTIVATION_ORDER = {'realtime': ('nmpc_node', 'state_estimator_node', 'ecu_bridge_node',
                                 'plant_sim_node', 'road_preview_node'),
                    'lockstep': ('nmpc_node', 'road_preview_node', 'plant_sim_node')}
#: The `erva run` option of a live parameter, where its name differs.
OPTION_OF = {'duration_s': 'duration', 'preview_snr_db': 'preview_snr',
             'preview_delay_s': 'preview_delay', 'road_file': 'road_file',
             'command_delay_s': 'command_delay'}


#: How long (s) a session's processes may take to start and connect: a cold start builds
#: and compiles CasADi functions, which a busy 2-core machine stretches to tens of seconds.
STARTUP_TIMEOUT_S = 90.0


@dataclass
class RunConfig:
    """What `erva run` runs; ``None`` means "as in the config files"."""

    controller: Optional[str] = None
    alpha1: Optional[float] = None
    alpha2: Optional[float] = None
    road: Optional[str] = None
    seed: Optional[int] = None
    mode: Optional[str] = None
    model: Optional[str] = None
    duration_s: Optional[float] = None
    params_file: Optional[str] = None      # physical parameters (config/erva_paper.yaml)
    nmpc_file: Optional[str] = None        # controller settings (config/nmpc.yaml)
    live_file: Optional[str] = None        # live parameters (config/live.yaml)
    record_dir: Optional[str] = None       # parent of the session bag; None: no recording
    namespace: str = topics.NAMESPACE
    startup_timeout_s: float = STARTUP_TIMEOUT_S
    live_overrides: Dict[str, Any] = field(default_factory=dict)
    settings_overrides: Dict[str, Any] = field(default_factory=dict)
    recorder_overrides: Dict[str, Any] = field(default_factory=dict)  # recorder_node params
    session_dir: Optional[str] = None      # where the params file and node logs go
    ecu: str = 'none'                      # 'virtual': the HIL loop (simulated ECU, CAN)
    foxglove: Optional[str] = None         # [HOST:]PORT: serve the session to Foxglove
    ecu_prefix: tuple = ()                 # argv prefix of the HIL processes (--ecu-prefix)
    can_log: str = ''                      # the bridge's CAN trace, FILE.blf|.asc ('' none)
    extra_readers: int = 0                 # the user's own readers the start waits for
    force: bool = False                    # start even if another session runs here
    strict: bool = False                   # real-time warnings fail the run (exit 1)
    preview_map: Optional[str] = None      # --preview map:FILE: the road estimated, the
    #                                        preview from this map (needs --ecu)
    changes: tuple = ()                    # --set T:KEY=VALUE: live changes at sample times


def ensure_ecu_available(ecu: str) -> None:
    """Raise CLIError unless the HIL loop for ``--ecu`` can run (its modules import)."""
    if ecu == 'none':
        return
    try:
        import erva_ros.core.hil  # noqa: F401  (python-can, cantools, the estimator)
    except ImportError as exc:
        raise CLIError(f'--ecu {ecu} is not available: the HIL modules (erva_ros.core.hil) do not '
                       f'import ({exc})') from None


__all__ = ['NODES', 'HIL_PROCESSES', 'HIL_NODES', 'ACTIVATION_ORDER', 'OPTION_OF',
           'STARTUP_TIMEOUT_S',
           'RunConfig', 'ensure_ecu_available']
