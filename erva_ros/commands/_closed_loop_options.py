"""Options shared by `erva sim`, `erva table`, `erva pareto` and `erva bench` (closed loop).

Controller settings come from config/nmpc.yaml (``--settings``), physical parameters
from config/erva_paper.yaml (``--params``); command-line options override the file.
"""

import argparse

from erva_ros.commands._common import positive_float
from erva_ros.core.errors import CLIError

ROAD_CHOICES = ('paper', 'iso8608', 'bump', 'sine')
PAPER_T1_S = 4.0        # paper Table I: t0 = 0 s, t1 = 4 s


def weights(text: str):
    """Parse 'A1,A2' into a tuple of two non-negative floats (argparse type)."""
    parts = text.split(',')
    try:
        vals = tuple(float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not two numbers "A1,A2"') from None
    if len(vals) != 2 or any(v < 0 or v != v or v == float('inf') for v in vals):
        raise argparse.ArgumentTypeError(f'{text!r} must be two non-negative numbers "A1,A2"')
    if vals == (0.0, 0.0):
        raise argparse.ArgumentTypeError('weights 0,0 leave nothing to optimise')
    return vals


def weight_list(text: str):
    """Parse 'A1,A2;B1,B2;...' into a list of weight pairs (argparse type)."""
    return [weights(part) for part in text.split(';') if part.strip()]


def non_negative_int(text: str) -> int:
    """Parse an integer >= 0, e.g. a seed or a count (argparse type)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not an integer') from None
    if v < 0:
        raise argparse.ArgumentTypeError(f'{text!r} must be >= 0')
    return v


#: A road/noise seed: any integer >= 0.
seed_int = non_negative_int


def seed_list(text: str):
    """Parse 'S1,S2,...' into a list of distinct non-negative seeds (argparse type)."""
    seeds = [seed_int(part.strip()) for part in text.split(',') if part.strip()]
    if not seeds:
        raise argparse.ArgumentTypeError(f'{text!r} names no seed')
    if len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f'{text!r} repeats a seed')
    return seeds


def add_settings_options(parser: argparse.ArgumentParser, controller: bool = True,
                         alpha: bool = False) -> None:
    """Add --settings and the common controller overrides (checked by the settings' specs).

    ``alpha`` adds --alpha A1,A2 (one weighting; `erva table`/`pareto` take lists instead).
    """
    from erva_ros.core.settings.controller import NUMERIC_SPECS, SPECS

    def option(flag, key, text, **kw):
        # Numbers are checked by load_settings (the spec's check: one line naming the key).
        spec = SPECS[key]
        extra = spec.argparse(text, checked=False) if key in NUMERIC_SPECS else \
            spec.argparse(text)
        parser.add_argument(flag, default=None, **kw, **extra)

    parser.add_argument('--settings', metavar='FILE', default=None,
                        help='controller settings, a ROS 2 params file with an nmpc_node '
                             'section (default: the shipped config/nmpc.yaml)')
    if controller:
        option('--controller', 'controller',
               'control law (default: "controller" in the settings file)')
    option('--cost', 'cost',
           'stage cost of every NMPC: paper (as printed, jerk-like comfort term, '
           'node-sampled power) or continuous (alpha1 a^2 - alpha2 P integrated); '
           'default: cost (and long_cost for preview_long) in the settings file')
    if alpha:
        parser.add_argument('--alpha', type=weights, default=None, metavar='A1,A2',
                            help='cost weights alpha1,alpha2 (paper: 1,0 / 0,1 / 1,0.01; '
                                 'default: the settings file)')
    option('--solver', 'solver', 'NMPC solver: sqp (real-time) or ipopt (converged reference)')
    option('--horizon', 'horizon', 'NMPC horizon N in samples (paper: 10)', metavar='N')
    option('--max-iter', 'max_iter', 'real-time SQP iterations per sample (sets max_iter, '
           'and long_max_iter for preview_long)', metavar='K')
    option('--codegen', 'codegen',
           'compile the real-time solver\'s model functions to C: on, off, or auto = on '
           'when cc/gcc is on PATH (first use of a configuration compiles for ~25 s, '
           'then cached in ~/.cache/erva_ros; default: settings file, auto)')
    option('--u-min', 'u_min', 'lower bound of the damping command', metavar='NS_PER_M')
    option('--u-max', 'u_max', 'upper bound of the damping command', metavar='NS_PER_M')
    option('--command-delay', 'command_delay_s',
           'the OCP models a command delay d = S: the command acts at t_k + d, planned '
           'from the state predicted to then (S < ts; offline default 0, the paper\'s loop; '
           'live loops: config/live.yaml)', metavar='S')


def add_road_options(parser: argparse.ArgumentParser, seed: bool = True) -> None:
    """Add --road, --duration and the road's options."""
    parser.add_argument('--road', choices=ROAD_CHOICES, default='paper',
                        help='road: paper (1.7 Hz, 1 mm sine + filtered noise at 7 dB SNR), '
                             'iso8608 (random, --road-class, --speed), bump, sine '
                             '(default paper)')
    parser.add_argument('--duration', type=positive_float, default=PAPER_T1_S, metavar='S',
                        help=f'simulated time in s (default {PAPER_T1_S:g}, paper t1)')
    if seed:
        parser.add_argument('--seed', type=seed_int, default=0,
                            help='noise seed of the road (default 0)')
    parser.add_argument('--road-class', default='C', choices=list('ABCDE'),
                        help='ISO 8608 road class for --road iso8608 (default C)')
    parser.add_argument('--speed', type=positive_float, default=20.0, metavar='M_PER_S',
                        help='vehicle speed for iso8608/bump roads (m/s, default 20)')
    parser.add_argument('--preview-snr', type=float, default=None, metavar='DB',
                        help='add Gaussian noise at this SNR to the road preview '
                             '(default: perfect preview)')
    parser.add_argument('--preview-delay', type=float, default=0.0, metavar='S',
                        help='the road preview is this old (s, default 0)')


def load_settings(args, **extra):
    """Return validated ControllerSettings from --settings and the override options.

    ``extra`` (keyword overrides) wins over the options, e.g. an offline time budget.
    """
    from erva_ros.core.controllers.settings import (load_controller_settings,
                                                    with_linked_iteration_cap)
    overrides = {'controller': getattr(args, 'controller', None), 'cost': args.cost,
                 'long_cost': args.cost, 'codegen': args.codegen,
                 'solver': args.solver, 'horizon': args.horizon, 'max_iter': args.max_iter,
                 'u_min': args.u_min, 'u_max': args.u_max,
                 'command_delay_s': args.command_delay}
    alpha = getattr(args, 'alpha', None)
    if alpha is not None:
        overrides.update(alpha1=alpha[0], alpha2=alpha[1])
    overrides = with_linked_iteration_cap(overrides)
    overrides.update(extra)
    return load_controller_settings(args.settings, overrides)


def make_road_from_args(args, duration_s: float, seed: int):
    """Return the road chosen on the command line (one-line CLIError on bad options)."""
    from erva_ros.core.road.profiles import make_road, RoadError
    opts = {}
    if args.road in ('iso8608', 'bump'):
        opts['speed_mps'] = args.speed
    if args.road == 'iso8608':
        opts['road_class'] = args.road_class
    try:
        return make_road(args.road, duration_s, seed=seed, **opts)
    except RoadError as exc:
        raise CLIError(str(exc)) from None


def preview_model_from_args(args, seed: int, ts: float):
    """Return the PreviewErrorModel of --preview-snr/--preview-delay, or None."""
    from erva_ros.core.road.preview import PreviewErrorModel
    if args.preview_snr is None and not args.preview_delay:
        return None
    if args.preview_delay < 0:
        raise CLIError(f'--preview-delay {args.preview_delay:g} must be >= 0')
    return PreviewErrorModel(args.preview_snr, args.preview_delay, seed=seed + 7919, ts=ts)


__all__ = ['add_settings_options', 'add_road_options', 'load_settings',
           'make_road_from_args', 'preview_model_from_args', 'weights', 'weight_list',
           'non_negative_int', 'seed_int', 'seed_list', 'PAPER_T1_S']


def add_can_log_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--can-log FILE`` (`erva run --ecu virtual`: the bridge's CAN trace)."""
    parser.add_argument('--can-log', metavar='FILE', default=None,
                        help='with --ecu virtual: write every raw CAN frame of the bridge, '
                             'both directions, to FILE.blf or FILE.asc (python-can writers; '
                             'timestamps in epoch seconds, the clock of the bag\'s receive '
                             'stamps); finished when the bridge stops')


def can_log_path(args) -> str:
    """Return --can-log as an absolute path ('' if not given); CLIError if unusable."""
    import os
    from erva_ros.core.hil.can_trace import check_path
    from erva_ros.core.model.params import ParamError
    path = getattr(args, 'can_log', None)
    if path is None:
        return ''
    if getattr(args, 'ecu', 'none') == 'none':
        raise CLIError('--can-log needs --ecu virtual (it traces the bridge\'s CAN bus)')
    try:
        check_path(path, '--can-log')
    except ParamError as exc:
        raise CLIError(str(exc)) from None
    return os.path.abspath(path)
