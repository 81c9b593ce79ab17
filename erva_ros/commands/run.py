"""``erva run``: the live system -- plant, road-preview and NMPC nodes over ROS 2, one scenario."""

import argparse
import os
import shlex
import sys

from erva_ros.commands._closed_loop_options import (add_can_log_option, can_log_path,
                                                    non_negative_int)
from erva_ros.commands._common import (add_json_option, add_params_option, add_set_option,
                                       live_type, positive_float, print_json,
                                       realtime_priority)
from erva_ros.core import topics
from erva_ros.core.bag.writer import MIN_SPLIT_SIZE
from erva_ros.core.errors import CLIError

COMMAND = 'run'
HELP = 'run the live system (plant, road preview, NMPC nodes over ROS 2) and summarise it'
DESCRIPTION = """\
Start plant_sim_node, road_preview_node and nmpc_node as separate processes (and the
session recorder), wait until they are connected, run one scenario, stop them cleanly
and print a summary: comfort (chassis-acceleration 2-norm and RMS) and power metrics,
command rate, command period jitter and state-to-command latency (measured at the
plant), solve-time p50/p99, deadline misses, fallbacks, dropped and rejected messages.

Default: the paper's scenario -- 4 s on the paper road, NMPC with preview, the
nonlinear ERVA, real time at Ts = 0.02 s -- recorded to bags/<UTC time>_<road>/.
Parameters come from config/erva_paper.yaml, config/nmpc.yaml and config/live.yaml;
options override them.  Modes: realtime (wall clock, 50 Hz) or lockstep (the plant
publishes /clock, deterministic, equal to `erva sim`).

--ecu virtual runs the hardware-in-the-loop loop instead of plant_sim_node (real
time only): NMPC -> ecu_bridge_node -> CAN (UDP on 127.0.0.1) -> simulated ECU and
plant (`erva ecu-sim`) -> CAN -> ecu_bridge_node -> state_estimator_node -> NMPC.
--ecu-prefix runs those three processes through a command prefix, e.g. in another
network namespace (`ip netns exec NS`, the loop split across two DDS hosts:
docs/hil.md) or on other cores (`taskset -c 1`).

--foxglove [HOST:]PORT serves the session live to Foxglove (WebSocket, no ROS install
needed): every topic as on DDS (ros2msg schemas, CDR bytes), /diagnostics and the
session description on <namespace>/session; open config/foxglove_layout.json there.
The server is a separate, niced process: a viewer that does not keep up loses its own
oldest messages, never the loop's or the bag's.

Exit status: 0 ok; 1 a node died, did not stop cleanly, or no command arrived;
2 bad option or parameter; 130/143 interrupted by SIGINT/SIGTERM (the nodes are
stopped and the summary printed first)."""

#: Kept literal so `erva --help` needs no Foxglove SDK; test_foxglove checks it against
#: erva_ros/ros/foxglove_server.py.
FOXGLOVE_DEFAULT = '127.0.0.1:8765'


# Checked by the parameters' own specs (the session file checks the same).
_snr = live_type('preview_snr_db')
_delay = live_type('preview_delay_s')
_command_delay = live_type('command_delay_s')


def _option(parser, flag: str, name: str, help: str, **kw) -> None:
    """Add ``flag`` for parameter ``name``: choices, type and range from its spec."""
    from erva_ros.core.settings.schemas import argparse_kwargs
    opts = argparse_kwargs(name, help)
    parser.add_argument(flag, default=None, **{**opts, **kw})


def add_scenario_arguments(parser, duration_default: str = 'config/live.yaml: 4 s') -> None:
    """Add the scenario options shared by `erva run` and `erva bench --live`."""
    _option(parser, '--controller', 'controller',
            'control law (default: config/nmpc.yaml, preview)')
    _option(parser, '--alpha1', 'alpha1', 'comfort weight alpha1 (paper eq. (12); default '
            'config/nmpc.yaml: 1)', metavar='A1')
    _option(parser, '--alpha2', 'alpha2', 'energy weight alpha2 (paper eq. (12); default '
            'config/nmpc.yaml: 0)', metavar='A2')
    _option(parser, '--road', 'road', 'road profile (default: config/live.yaml, paper)')
    parser.add_argument('--road-file', metavar='CSV', default=None,
                        help='a recorded road: CSV rows "time_s, height_m" (overrides --road)')
    _option(parser, '--seed', 'seed', 'road noise and preview error seed (default: '
            'config/live.yaml, 0)')
    _option(parser, '--mode', 'mode', 'realtime: wall clock at 1/Ts; lockstep: simulated '
            'time, deterministic (default: config/live.yaml, realtime)')
    _option(parser, '--model', 'model', 'plant and controller model: erva (nonlinear, eq. '
            '(11)) or benchmark (linear, eq. (15)) (default: erva)')
    parser.add_argument('--duration', type=positive_float, default=None, metavar='S',
                        help=f'scenario length in seconds (default: {duration_default})')
    parser.add_argument('--preview-snr', type=_snr, default=None, metavar='DB',
                        help='add Gaussian noise at this SNR to the road preview, as '
                             '`erva sim --preview-snr` (default: perfect preview)')
    parser.add_argument('--preview-delay', type=_delay, default=None, metavar='S',
                        help='the road preview is this old (s, default 0)')
    add_params_option(parser)
    parser.add_argument('--realtime-priority', type=realtime_priority, default=None, metavar='P',
                        help='SCHED_FIFO priority of every loop process in realtime mode, '
                             '0 = normal scheduling (config/live.yaml: 20; needs '
                             'CAP_SYS_NICE, else each node warns once)')
    parser.add_argument('--nmpc', metavar='FILE', default=None,
                        help='controller settings params file (default: config/nmpc.yaml)')
    parser.add_argument('--command-delay', type=_command_delay, default=None, metavar='S',
                        help='command delay d: each command acts at its sample t_k + d in '
                             'the plant (or ECU), and the OCP models it (s, < Ts; 0 = the '
                             'paper\'s ideal loop; default: config/live.yaml)')
    parser.add_argument('--live', metavar='FILE', default=None,
                        help='live-system params file (default: config/live.yaml)')
    parser.add_argument('--namespace', default=topics.NAMESPACE, metavar='NS',
                        help='ROS namespace of the nodes and topics (default: '
                             f'{topics.NAMESPACE})')


def add_arguments(parser):
    add_scenario_arguments(parser)
    rec = parser.add_mutually_exclusive_group()
    rec.add_argument('--record', metavar='DIR', default='bags',
                     help='record the session to a bag under DIR/<UTC time>_<road>/ '
                          '(default: bags)')
    rec.add_argument('--no-record', action='store_true', help='do not record the session')
    add_bag_split_arguments(parser)
    parser.add_argument('--ecu', choices=('none', 'virtual'), default='none',
                        help='none (default): plant_sim_node closes the loop; virtual: '
                             'hardware-in-the-loop -- the commands go through '
                             'ecu_bridge_node over a loopback CAN bus (UDP) to a simulated '
                             'ECU with the plant (`erva ecu-sim`), and the NMPC gets the '
                             'state from state_estimator_node (EKF on the ECU\'s sensor '
                             'frames); comfort and power are the ECU\'s ground truth, the '
                             'HIL topics are recorded and the summary adds a hil block '
                             '(bridge drops and timeouts, latencies, estimation error); '
                             'real time only')
    parser.add_argument('--preview', metavar='map:FILE', default=None, type=_preview,
                        help='with --ecu virtual: the vehicle\'s own road -- the estimator '
                             'estimates the road at the tyre from the ECU\'s sensors '
                             '(road/estimate, with odometry) and the NMPC\'s preview comes '
                             'from the road map FILE (erva map build), aligned by profile '
                             'matching (road/alignment); the map is checked first: it must '
                             'be of this road, seed and speed and cover the drive; '
                             'map:postgresql://USER@HOST/DB: a fleet\'s map on a server, its '
                             'section fetched into a local cache before the start, the cache '
                             'used (one WARN line) if the server is unreachable (default: '
                             'the scenario road\'s own preview; docs/road.md)')
    parser.add_argument('--foxglove', nargs='?', const=FOXGLOVE_DEFAULT, default=None,
                        metavar='[HOST:]PORT',
                        help='serve the session live to Foxglove on this address '
                             f'(default {FOXGLOVE_DEFAULT}: this machine only; another '
                             'host only when named, e.g. 0.0.0.0:8765; PORT 0 = any free '
                             'port)')
    parser.add_argument('--ecu-prefix', metavar='CMD', default=None,
                        help='with --ecu virtual: start the ECU simulator, the bridge and the '
                             'estimator through this command prefix (split like a shell '
                             'does), e.g. "ip netns exec NS" or "taskset -c 1"; it must exec '
                             'the command (signals stop it) and see the same files; DDS '
                             'settings come from the environment (docs/hil.md)')
    add_can_log_option(parser)
    add_set_option(parser, 'sent to nmpc_node through its SetParameters service (lock-step: '
                           'acting from exactly that sample, as erva sim --set; real time: '
                           'sent Ts/2 before it)')
    parser.add_argument('--strict', action='store_true',
                        help='fail the run (exit 1) when it was not real time: deadline '
                             'misses, state timeouts, skipped road samples or command pauses '
                             'over the thresholds of config/session.yaml (erva_run); without '
                             'it they are WARN lines')
    parser.add_argument('--force', action='store_true',
                        help='start even if another session runs on this ROS_DOMAIN_ID and '
                             'namespace (refused by default: the two loops would merge)')
    parser.add_argument('--extra-readers', type=non_negative_int, default=0, metavar='N',
                        help='start the loop only once N readers of your own (a logger, a '
                             'plotter, ros2 bag record) are matched on the topics of the '
                             'time master: road/height and road/preview in real time, state '
                             'in lock-step; started before the run, they get sample 0 '
                             '(default 0)')
    parser.add_argument('-v', '--timing', action='store_true',
                        help='print when each stage of the bring-up and the stop ended '
                             '(s since the command started: imports, domain, each node\'s '
                             'start, configure, matching, first sample, stop, bag, summary; '
                             'docs/live.md) on stderr after the summary')
    add_json_option(parser)


def add_bag_split_arguments(parser, short: bool = False) -> None:
    """Add --max-bag-duration and --max-bag-size (``short``: also -d and -b, as ros2 bag's)."""
    split = parser.add_argument_group(
        'bag splitting', 'as ros2 bag record: the bag becomes <bag>_0.mcap, <bag>_1.mcap, ... '
        '(each complete, all listed in metadata.yaml, read as one bag by every erva command); '
        'the recorder holds a file\'s index in memory until the file is finished')
    from erva_ros.core.settings.schemas import argparse_kwargs
    split.add_argument(*(['-d'] if short else []), '--max-bag-duration', default=None,
                       metavar='S', **argparse_kwargs(
                           'max_bag_duration_s', 'start the next file once a message is S '
                           'seconds later than the file\'s first; 0 = one file (default: '
                           'config/session.yaml, 300)'))
    split.add_argument(*(['-b'] if short else []), '--max-bag-size', type=_bag_size,
                       default=None, metavar='BYTES',
                       help='start the next file once this one holds BYTES; 0 = no limit '
                            f'(default), else at least {MIN_SPLIT_SIZE}')


def bag_split_parameters(args) -> dict:
    """Return the recorder parameters of --max-bag-duration/--max-bag-size that were given."""
    given = (('max_bag_duration_s', getattr(args, 'max_bag_duration', None)),
             ('max_bag_size_bytes', getattr(args, 'max_bag_size', None)))
    return {name: value for name, value in given if value is not None}


def _bag_size(text: str) -> int:
    """Parse --max-bag-size: 0 or at least MIN_SPLIT_SIZE bytes (argparse type)."""
    from erva_ros.core.settings.schemas import spec_of
    size = spec_of('max_bag_size_bytes', 'recorder').parse(text)
    if 0 < size < MIN_SPLIT_SIZE:
        raise argparse.ArgumentTypeError(f'{text!r}: 0 (no limit) or at least '
                                         f'{MIN_SPLIT_SIZE} bytes')
    return size


def _preview(text: str) -> str:
    """Parse ``map:FILE`` (or ``map:URI``) into FILE (argparse type)."""
    from erva_ros.core.redact import redact_text
    kind, _, path = text.partition(':')
    if kind != 'map' or not path:
        raise argparse.ArgumentTypeError(f'{redact_text(text)!r}: expected map:FILE or '
                                         'map:postgresql://...')
    return path


def run_config(args, record_dir=None):
    """Return the RunConfig of parsed scenario options."""
    from erva_ros.session.run.run_config import RunConfig
    live = {}
    if args.preview_snr is not None:
        live.update(preview_noise=True, preview_snr_db=args.preview_snr)
    if args.preview_delay is not None:
        live['preview_delay_s'] = args.preview_delay
    if args.road_file is not None:
        live['road_file'] = os.path.abspath(args.road_file)
    if args.realtime_priority is not None:
        live['realtime_priority'] = args.realtime_priority
    if args.command_delay is not None:
        live['command_delay_s'] = args.command_delay
    return RunConfig(controller=args.controller, alpha1=args.alpha1, alpha2=args.alpha2,
                     road=args.road, seed=args.seed, mode=args.mode, model=args.model,
                     duration_s=args.duration, params_file=args.params, nmpc_file=args.nmpc,
                     live_file=args.live, record_dir=record_dir, namespace=args.namespace,
                     live_overrides=live, ecu=args.ecu, ecu_prefix=_ecu_prefix(args),
                     can_log=can_log_path(args),
                     foxglove=getattr(args, 'foxglove', None),
                     extra_readers=getattr(args, 'extra_readers', 0),
                     force=getattr(args, 'force', False),
                     recorder_overrides=bag_split_parameters(args),
                     strict=getattr(args, 'strict', False),
                     preview_map=getattr(args, 'preview', None),
                     changes=tuple(getattr(args, 'set', ()) or ()))


def _ecu_prefix(args) -> tuple:
    """Return --ecu-prefix as argv words; CLIError without --ecu virtual or if malformed."""
    if args.ecu_prefix is None:
        return ()
    if args.ecu == 'none':
        raise CLIError('--ecu-prefix needs --ecu virtual')
    try:
        words = tuple(shlex.split(args.ecu_prefix))
    except ValueError as exc:
        raise CLIError(f'--ecu-prefix {args.ecu_prefix!r}: {exc}') from None
    if not words:
        raise CLIError('--ecu-prefix is empty')
    return words


def _check_namespace(namespace: str) -> str:
    """Return the namespace made absolute, or raise CLIError if ROS would refuse it."""
    from erva_ros.ros.context import absolute_namespace
    try:
        return absolute_namespace(namespace)
    except ValueError as exc:
        raise CLIError(f'--namespace {namespace!r} is not a valid ROS namespace ({exc})'
                       ) from None


def main(args) -> int:
    """Run the session, print its summary and end the process with its exit status."""
    from erva_ros.session.run.bringup import Timeline
    timeline = Timeline()
    timeline.mark('options parsed')
    from erva_ros.session.run.orchestrator import run_session
    from erva_ros.session.run.run_config import ensure_ecu_available
    from erva_ros.session.run.report import format_summary, jsonable

    ensure_ecu_available(args.ecu)
    args.namespace = _check_namespace(args.namespace)
    if args.foxglove is not None:   # a port in use fails here, before anything starts
        from erva_ros.session.run.foxglove_process import check_address
        check_address(args.foxglove)
    cfg = run_config(args, None if args.no_record else args.record)
    log = lambda line: print(f'erva run: {line}', file=sys.stderr, flush=True)  # noqa: E731
    result = run_session(cfg, log=log, timeline=timeline)
    if args.json:
        print_json(jsonable(result.summary))
    else:
        print(format_summary(result.summary), flush=True)
    if args.timing:
        timeline.mark('summary printed')
        for line in timeline.lines(result.summary['timing']['nodes']):
            log(line)
    # Everything is done and said: the interpreter's own exit would only join the
    # middleware's threads (0.4-0.9 s of timed sleeps), as a node's would (ros/runtime.py).
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(result.exit_code)
