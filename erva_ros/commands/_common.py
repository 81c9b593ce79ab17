"""Options and helpers shared by ``erva`` subcommands."""

import argparse
import os
import sys
from typing import Optional

from erva_ros.core.errors import CLIError
from erva_ros.session.run.report import print_json  # noqa: F401 (one home, for the commands)


def bag_warner(prog: str, into: Optional[list] = None, path: str = ''):
    """Return a ``warn`` for :func:`erva_ros.core.bag.reader.open_bag`: print on stderr.

    Each line is also appended to ``into`` (a command's --json output); ``path`` names the
    bag in the line (a command that reads several).
    """
    def warn(line: str) -> None:
        print(f'{prog}: warning: {path + ": " if path else ""}{line}', file=sys.stderr,
              flush=True)
        if into is not None:
            into.append(line)
    return warn


def add_params_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--params', metavar='FILE', default=None,
                        help='ROS 2 parameter file with the ERVA parameters '
                             '(default: the shipped config/erva_paper.yaml, paper Table I)')


def add_json_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--json', action='store_true',
                        help='print the results as one JSON object on stdout')


def add_out_option(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument('--out', metavar='DIR', default=None,
                        help=f'directory to write {what} into (created if missing)')


def positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
    if not v > 0 or v != v or v == float('inf'):
        raise argparse.ArgumentTypeError(f'{text!r} must be a positive, finite number')
    return v


def positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not an integer') from None
    if v <= 0:
        raise argparse.ArgumentTypeError(f'{text!r} must be a positive integer')
    return v


def live_type(key: str):
    """Return an argparse type checked by the spec of live parameter ``key``.

    The spec (:data:`erva_ros.core.settings.schemas.LIVE`) is imported when the option is
    given, so ``--help`` stays light.
    """
    def parse(text: str):
        from erva_ros.core.settings.schemas import LIVE
        return LIVE.specs()[key].parse(text)
    return parse


def settings_type(key: str):
    """Return an argparse type checked by the spec of controller setting ``key``."""
    def parse(text: str):
        from erva_ros.core.settings.controller import SPECS
        return SPECS[key].parse(text)
    return parse


#: argparse type of --realtime-priority (erva run, bench --live, bench-hil, ecu-sim).
realtime_priority = live_type('realtime_priority')


def add_set_option(parser: argparse.ArgumentParser, where: str) -> None:
    """Add ``--set T:KEY=VALUE`` (repeatable): a live parameter changed at sample time T."""
    parser.add_argument('--set', action='append', default=[], metavar='T:KEY=VALUE',
                        help=f'change a live parameter at T s after the first sample, {where} '
                             '(repeatable; e.g. 1.0:alpha1=0.5, 2:u_max=15000, '
                             '1.5:use_preview=false; the live ones: docs/live.md)')


def ensure_out_dir(path: Optional[str]) -> Optional[str]:
    """Create ``path`` if needed; a clear error if it cannot be written."""
    if path is None:
        return None
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as exc:
        raise CLIError(f'cannot create output directory {path!r}: {exc.strerror}') from None
    if not os.access(path, os.W_OK):
        raise CLIError(f'output directory {path!r} is not writable')
    return path


def compile_first(command: str, params, settings, model: str = 'erva',
                  enabled: bool = True) -> None:
    """Compile the NMPC of ``settings`` and the plant before ``erva COMMAND`` times anything.

    One progress line per part on stderr (only when something is compiled, and none
    unless ``enabled``: commands pass ``not args.json``); see :mod:`erva_ros.core.loop.warmup`.
    """
    from erva_ros.core.loop.warmup import ensure_compiled, nmpc_target, Target
    log = (lambda line: print(f'erva {command}: {line}', file=sys.stderr, flush=True)) \
        if enabled else None
    ensure_compiled([nmpc_target(params, settings, model),
                     Target('plant', params, model, settings.ts)], log)
