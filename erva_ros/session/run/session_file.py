"""A validated `erva run` session: its effective parameters and the params file the nodes read.

:func:`prepare_session` validates every value in-process first (physical parameters,
controller settings, live parameters, the road), so a bad option fails with one line
before any process starts, gives the session its id, and writes the session's effective
parameters to one ROS 2 params file (``/**`` for what all nodes share, ``/**/<node>`` for
each node, :func:`erva_ros.core.settings.schemas.session_sections`) in a session directory.
"""

from dataclasses import dataclass
import os
import secrets
import sys
import tempfile
import time
from typing import Any, Dict, Optional, Tuple

import yaml

from erva_ros.core import topics
from erva_ros.core.bag import session as bag_session
from erva_ros.core.roadmap import MapError
from erva_ros.core.roadmap.fleet import map_for_session
from erva_ros.core.settings.files import shipped_config
from erva_ros.core.controllers.settings import load_controller_settings
from erva_ros.core.errors import CLIError
from erva_ros.core.loop.scenario import build_road, required_preview_steps
from erva_ros.core.settings.schemas import LIVE, session_sections
from erva_ros.core.model.params import load_erva_params, ParamError, read_sections
from erva_ros.core.settings.specs import check_all
from erva_ros.session.run.run_config import NODES, OPTION_OF, RunConfig
from erva_ros.session.run.session_dirs import remove_stale_session_dirs, SESSION_DIR_PREFIX
from erva_ros.session.run.tuning_schedule import first_hold_s, plan

#: Least settling time before sample 0 in HIL mode (live start_delay_s, default 0.5 s).
#: Seven processes discover each other on a loaded machine: with 0.5 s the recorder's
#: readers were sometimes matched ~0.2 s into the run and it lost the first samples.
HIL_START_DELAY_S = 1.5
#: The session params file's name in the session directory.
PARAMS_FILE = 'session_params.yaml'


def default_config_file(name: str) -> str:
    """Return the path of a shipped config file (source tree or installed share)."""
    return shipped_config(name)


def read_live_file(path: Optional[str]) -> Dict[str, Any]:
    """Return the live parameters of a params file: ``/**`` merged with each node's section."""
    path = path or default_config_file('live.yaml')
    if not os.path.isfile(path):
        raise ParamError(f'live parameter file {path!r} does not exist')
    out: Dict[str, Any] = {}
    for section, params in read_sections(path, NODES):
        unknown = sorted(set(params) - set(LIVE.specs()) - {'use_sim_time'})
        if unknown:
            raise ParamError(f'{path}: unknown live parameter(s) {", ".join(unknown)} '
                             f'in {section}')
        out.update(params)
    return out


def validate_live(values: Dict[str, Any], source: str = '') -> Dict[str, Any]:
    """Return the live parameters (defaults filled in) checked by their specs."""
    return check_all(LIVE.specs(), {k: v for k, v in values.items() if k != 'use_sim_time'},
                     source, LIVE.defaults())


@dataclass
class Session:
    """A validated scenario: effective parameters and the params file the nodes read."""

    erva: Dict[str, float]
    settings: Any
    live: Dict[str, Any]
    directory: str
    params_file: str
    scenario: str
    ecu: str = 'none'
    preview_map: str = ''           # the map file the preview reads ('' : the road's preview)
    preview_source: str = ''        # --preview map:MAP as it may be shown (no password)
    steps: tuple = ()               # --set: live changes (session/run/tuning_schedule.Step)

    @property
    def session_id(self) -> str:
        """Return the session's id: every node of the session reports it."""
        return self.live['session_id']

    @property
    def hil(self) -> bool:
        """Return True for the hardware-in-the-loop loop (--ecu virtual)."""
        return self.ecu != 'none'

    @property
    def road_estimated(self) -> bool:
        """Return True when the estimator estimates the road and the preview is the map's."""
        return bool(self.preview_map)

    @property
    def realtime(self) -> bool:
        """Return True for a wall-clock run."""
        return self.live['mode'] == 'realtime'

    @property
    def n_steps(self) -> int:
        """Return the number of control periods of the scenario."""
        return int(round(self.live['duration_s'] / self.live['ts']))

    @property
    def sim_window_ns(self):
        """Return the span (ns) of a lock-step session's simulated stamps (None: realtime)."""
        if self.realtime:
            return None
        return 0, int((self.live['duration_s'] + 10.0) * 1e9)   # simulated time from 0


def new_session_id() -> str:
    """Return a new session id: 16 hex digits, the start in ms since 1970, then 20 random bits.

    The nodes report it, so another session on the same DDS domain (or a stale node of an
    earlier one) is never counted as this one's; and ids sort by start, so of two sessions
    that start on one namespace the earlier one runs (erva_ros/session/run/start_gate.py).
    """
    return f'{time.time_ns() // 1_000_000:011x}{secrets.randbits(20):05x}'


def live_values(cfg: RunConfig, settings, recording: bool) -> Dict[str, Any]:
    """Return the session's validated live parameters: the live file, then the options."""
    live_path = cfg.live_file or default_config_file('live.yaml')
    values = read_live_file(live_path)
    values['ts'] = settings.ts
    values['command_delay_s'] = settings.command_delay_s
    values['session_id'] = new_session_id()
    options = {key: value for key, value in (
        ('mode', cfg.mode), ('model', cfg.model), ('road', cfg.road), ('seed', cfg.seed),
        ('duration_s', cfg.duration_s)) if value is not None}
    options.update(cfg.live_overrides)
    specs = LIVE.specs()
    for key, value in options.items():      # an option's error names the option
        flag = '--' + OPTION_OF.get(key, key).replace('_', '-')
        options[key] = specs[key].check(key, value, flag)
    values.update(options)
    live = validate_live(values, source=live_path)
    if cfg.ecu != 'none':
        if live['mode'] != 'realtime':
            raise CLIError(f'--ecu {cfg.ecu} runs in real time only (the ECU keeps wall-clock '
                           f'time), not with mode {live["mode"]}')
        live['start_delay_s'] = max(live['start_delay_s'], HIL_START_DELAY_S)
    live['preview_steps'] = max(live['preview_steps'], required_preview_steps(settings))
    # The time master starts when each of its topics has the other loop node, this
    # process's monitor, (when recording / serving) the recorder / Foxglove server and
    # the user's own readers (--extra-readers).
    live['wait_for_subscribers'] = (2 + (1 if recording else 0) + (1 if cfg.foxglove else 0)
                                    + cfg.extra_readers)
    # ... and one of them is the monitor itself, not any reader that happens to be there.
    live['wait_for_reader'] = topics.MONITOR_NODE
    build_road(live)   # a bad road option fails here, not in a node
    return live


def session_params(erva: Dict[str, float], settings, live: Dict[str, Any],
                   preview_map: str = '') -> Dict[str, Any]:
    """Return the session params file's content: ``/**`` shared, ``/**/<node>`` per node.

    Which section each value goes to comes from the nodes' schemas
    (:func:`erva_ros.core.settings.schemas.session_sections`).  With ``preview_map`` the road
    node previews from it and the estimator estimates the road (config/road.yaml).
    """
    own = {k: v for k, v in settings.as_dict().items() if k not in ('ts', 'command_delay_s')}
    values = {**live, **erva, **own}
    doc = session_sections(values)
    if preview_map:
        doc['/**/road_preview_node']['ros__parameters'].update(source='map',
                                                               map_file=preview_map)
        doc['/**/state_estimator_node'] = {'ros__parameters': {
            'road_at_tyre': 'estimated', 'speed_mps': live['speed_mps']}}
    if live['mode'] == 'lockstep':
        doc['/**']['ros__parameters']['use_sim_time'] = True
    return doc


def prepare_session(cfg: RunConfig, recording: bool) -> Session:
    """Validate everything and write the session params file; raise ParamError (one line)."""
    erva = load_erva_params(cfg.params_file)
    # The loop's sample time is the live file's (the controller runs at it).
    live_file = read_live_file(cfg.live_file)
    # So is the command delay d: the OCP models the d at which plant and ECU apply.
    loop = _loop_timing(cfg, live_file)
    overrides = {'controller': cfg.controller, 'alpha1': cfg.alpha1, 'alpha2': cfg.alpha2,
                 **loop}
    overrides.update(cfg.settings_overrides)
    settings = load_controller_settings(cfg.nmpc_file, overrides)
    live = live_values(cfg, settings, recording)
    steps = plan(cfg.changes, settings, erva.c_e0, live)
    live['lockstep_hold_s'] = first_hold_s(steps, live)
    preview_map, preview_source = _preview_map(cfg, live)
    if cfg.session_dir is None:
        remove_stale_session_dirs()
    directory = cfg.session_dir or tempfile.mkdtemp(prefix=f'{SESSION_DIR_PREFIX}{os.getpid()}_')
    os.makedirs(directory, exist_ok=True)
    scenario = live['road'] if not live['road_file'] else 'recorded'
    path = os.path.join(directory, PARAMS_FILE)
    with open(path, 'w', encoding='utf-8') as fh:
        fh.write('# Effective parameters of an `erva run` session (ROS 2 params file).\n')
        yaml.safe_dump(session_params(erva.as_dict(), settings, live, preview_map), fh,
                       sort_keys=False)
    return Session(erva.as_dict(), settings, live, directory, path, scenario, cfg.ecu,
                   preview_map, preview_source, tuple(steps))


def _loop_timing(cfg: RunConfig, live_file: Dict[str, Any]) -> Dict[str, float]:
    """Return the loop's ts and command_delay_s, checked; a bad one is blamed on its source.

    Each comes from its option (``--command-delay``), else the live file, else the
    shipped config/live.yaml; the controller settings take them as given.
    """
    specs, out, source = LIVE.specs(), {}, {}
    for key in ('ts', 'command_delay_s'):
        if key in cfg.live_overrides:
            value = cfg.live_overrides[key]
            source[key] = '--' + OPTION_OF.get(key, key).replace('_', '-')
        elif key in live_file:
            value, source[key] = live_file[key], cfg.live_file or default_config_file(
                'live.yaml')
        else:
            value, source[key] = LIVE.defaults()[key], default_config_file('live.yaml')
        out[key] = specs[key].check(key, value, source[key])
    if not out['command_delay_s'] < out['ts']:
        where = source['command_delay_s'] + (
            '' if source['ts'] == source['command_delay_s'] else f' (ts: {source["ts"]})')
        raise ParamError(f'{where}: parameter \'command_delay_s\' = '
                         f'{out["command_delay_s"]:g} must be below ts = {out["ts"]:g} s')
    return out


def _preview_map(cfg: RunConfig, live: Dict[str, Any]) -> Tuple[str, str]:
    """Return (the checked map file of ``--preview map:MAP``, MAP as shown); CLIError.

    A server map's section is fetched into its local cache first, and the preview reads
    only that file (core/roadmap/fleet.map_for_session); ('', '') without the option.
    """
    if not cfg.preview_map:
        return '', ''
    if cfg.ecu == 'none':
        raise CLIError('--preview map:FILE needs --ecu virtual (the road is estimated from '
                       'the ECU\'s sensors)')
    try:
        return map_for_session(cfg.preview_map, live,
                               lambda line: print(line, file=sys.stderr, flush=True))
    except MapError as exc:
        raise CLIError(f'--preview map: {exc}') from None


def session_description(session: Session) -> Dict[str, str]:
    """Return what describes the session (the bag's erva_session record).

    ``params_yaml`` is the session params file itself, as every node read it: the bag
    keeps it, the file goes with the session directory.
    """
    params = {'erva': session.erva, 'controller': session.settings.as_dict(),
              'live': session.live}
    with open(session.params_file, encoding='utf-8') as fh:
        params_yaml = fh.read()
    return bag_session.session_metadata(
        session.scenario, parameters=params, seed=session.live['seed'],
        controller=session.settings.controller,
        extra={'mode': session.live['mode'], 'model': session.live['model'],
               'duration_s': session.live['duration_s'], 'ecu': session.ecu,
               'preview': f'map:{session.preview_source}' if session.preview_map else 'road',
               'params_yaml': params_yaml, 'session_id': session.session_id})


__all__ = ['HIL_START_DELAY_S', 'PARAMS_FILE', 'Session', 'default_config_file',
           'read_live_file', 'validate_live', 'new_session_id', 'live_values', 'session_params',
           'prepare_session', 'session_description']
