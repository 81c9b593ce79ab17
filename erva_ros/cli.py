# PYTHON_ARGCOMPLETE_OK  (marks the tool for argcomplete's global shell completion)
"""``erva`` — the ERVA NMPC command-line tool.

Subcommands live in :mod:`erva_ros.commands`, one module each, and are
discovered at start-up.  A command module defines ``COMMAND`` (its name),
``HELP`` (one line), optionally ``DESCRIPTION``, ``add_arguments(parser)`` and
``main(args) -> int``.  Modules keep heavy imports (rclpy, matplotlib) inside
``main`` so ``erva --help`` (and shell completion) stays fast.

Shell completion is argcomplete's, as ros2cli's: ``eval "$(register-python-argcomplete
erva)"`` in bash or zsh; the shell then runs ``erva`` with ``_ARGCOMPLETE`` set, and
:func:`main` answers with the candidates and exits before parsing.
"""

import argparse
import importlib
import importlib.util
import os
import pkgutil
import sys
import traceback
from typing import List, Optional

from erva_ros import __version__
from erva_ros.core.errors import CLIError
from erva_ros.core.model.params import ParamError

# Order in `erva --help`: the main job first, then analysis, then tools.
ORDER = ['run', 'sim', 'fr', 'table', 'pareto', 'bench', 'replay', 'report', 'bag', 'ecu-sim']


def _command_modules(only: Optional[str] = None):
    """Return the command modules, in help order; ``only``: just that command's, if it is one.

    Importing every command module costs ~0.5 s (their option tables import much of
    erva_ros): `erva run ...` imports only commands/run.py.
    """
    import erva_ros.commands as pkg
    name = (only or '').replace('-', '_')
    if name and not name.startswith('_') and importlib.util.find_spec(
            f'erva_ros.commands.{name}') is not None:
        mod = importlib.import_module(f'erva_ros.commands.{name}')
        if getattr(mod, 'COMMAND', None) == only and hasattr(mod, 'main'):
            return [mod]
    mods = []
    for info in pkgutil.iter_modules(pkg.__path__):
        if info.name.startswith('_'):
            continue
        mod = importlib.import_module(f'erva_ros.commands.{info.name}')
        if hasattr(mod, 'COMMAND') and hasattr(mod, 'main'):
            mods.append(mod)
    rank = {name: i for i, name in enumerate(ORDER)}
    mods.sort(key=lambda m: (rank.get(m.COMMAND, len(ORDER)), m.COMMAND))
    return mods


class Parser(argparse.ArgumentParser):
    """argparse with a one-line error (the README's promise), for ``erva`` and every command.

    argparse prints the whole usage before its error (12 lines for `erva run`); here the
    error is one line that says where the usage is.  Sub-commands' parsers are of this
    class too (``add_subparsers`` makes its parsers of the parent's class).
    """

    def error(self, message: str):
        """Print ``<prog>: error: <message> (<prog> --help: ...)`` on stderr; exit 2."""
        text = ' '.join(message.splitlines())
        self.exit(2, f'{self.prog}: error: {text} ("{self.prog} --help" lists the '
                     'options)\n')


def build_parser(command: Optional[str] = None) -> argparse.ArgumentParser:
    """Return the parser of every command (``command``: of that one only, when it is one)."""
    parser = Parser(
        prog='erva',
        description='Energy-regenerative vibration absorber (ERVA): NMPC on ROS 2, offline '
                    'simulation, the paper\'s figures and table, bags and HIL tools.',
        epilog='Run "erva COMMAND --help" for the options of a command. '
               'Set ERVA_DEBUG=1 to see tracebacks of internal errors.')
    parser.add_argument('--version', action='version', version=f'erva_ros {__version__}')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND')
    sub.required = True
    for mod in _command_modules(command):
        p = sub.add_parser(mod.COMMAND, help=mod.HELP,
                           description=getattr(mod, 'DESCRIPTION', mod.HELP),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        mod.add_arguments(p)
        p.set_defaults(_main=mod.main, _name=mod.COMMAND)
        for leaf in _leaves(p):
            leaf.set_defaults(_parser=leaf)
    return parser


def _leaves(parser: argparse.ArgumentParser):
    """Yield the parsers of ``parser``'s innermost sub-commands (itself if it has none)."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield parser
    for action in subs:
        for sub in action.choices.values():
            yield from _leaves(sub)


def _complete(parser: argparse.ArgumentParser) -> None:
    """Answer a shell's completion request (argcomplete) and exit; else return."""
    if '_ARGCOMPLETE' not in os.environ:
        return
    try:
        import argcomplete
    except ImportError:    # an install without it: no completion, the tool still runs
        return
    argcomplete.autocomplete(parser)


def main(argv: Optional[List[str]] = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    completing = '_ARGCOMPLETE' in os.environ
    parser = build_parser(None if completing or not argv else argv[0])
    _complete(parser)
    args, extra = parser.parse_known_args(argv)
    if extra:       # said by the command's parser, not erva's: "erva run: error: ..."
        args._parser.error(f'unrecognized arguments: {" ".join(extra)}')
    name = f'erva {args._name}'
    try:
        return int(args._main(args) or 0)
    except (CLIError, ParamError) as exc:
        print(f'{name}: error: {exc}', file=sys.stderr)
        return getattr(exc, 'exit_code', 2)
    except KeyboardInterrupt:
        print(f'{name}: interrupted', file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0
    except Exception as exc:  # last resort: one line, traceback on demand
        if os.environ.get('ERVA_DEBUG'):
            traceback.print_exc()
        print(f'{name}: internal error: {type(exc).__name__}: {exc} '
              '(set ERVA_DEBUG=1 for the traceback)', file=sys.stderr)
        return 1


if __name__ == '__main__':
    sys.exit(main())
