"""``erva compile``: compile every function the shipped configurations load, before any run."""

import sys

from erva_ros.commands._common import add_json_option, add_params_option, positive_int, print_json

COMMAND = 'compile'
HELP = 'compile the solvers and models to C once per machine (what the first run would do)'
DESCRIPTION = """\
The NMPC, the plant, the EKF and the simulated ECU load their CasADi functions compiled
to C from a cache (ERVA_CACHE_DIR, else ~/.cache/erva_ros).  The first use on a machine
compiles them, up to a minute each; this command does it for every shipped
configuration at once, in parallel, with one line per part:

  the NMPCs preview_long, preview and no_preview (config/nmpc.yaml) on the ERVA and the
  benchmark model, without and with a command delay (command_delay_s > 0: any value
  loads the same functions); the plant on both models; the EKF and the simulated ECU's
  plant of the HIL loop (config/hil.yaml).

A library is written atomically, so an interrupted compile leaves nothing broken and
the next one goes on with what is missing; processes compiling the same function
wait for each other.  `erva run`, `erva sim` and `erva bench` compile what they need
the same way before they start or time anything.

Exit status: 0 all compiled (--check: all cached), 1 a compile failed (--check:
something is missing), 2 bad input."""


def add_arguments(parser):
    parser.add_argument('--check', action='store_true',
                        help='compile nothing: report what is cached and what is missing')
    parser.add_argument('--jobs', type=positive_int, default=None, metavar='N',
                        help='parts built and compiled at a time (default: the CPUs)')
    add_params_option(parser)
    parser.add_argument('--nmpc', metavar='FILE', default=None,
                        help='controller settings file (default: the shipped config/nmpc.yaml)')
    parser.add_argument('--hil-config', metavar='FILE', default=None,
                        help='HIL parameter file (default: the shipped config/hil.yaml)')
    add_json_option(parser)


def main(args) -> int:
    from erva_ros.core import warmup

    targets = warmup.shipped_targets(args.params, args.nmpc, args.hil_config)
    log = None if args.json or args.check else (
        lambda line: print(f'erva compile: {line}', file=sys.stderr, flush=True))
    result = warmup.warm(targets, log, args.jobs, check=args.check)
    if args.json:
        print_json(result.as_dict())
        return 0 if result.ok else 1
    if result.compiler is None:
        print('no C compiler (cc or gcc) on PATH: the functions run in CasADi\'s virtual '
              'machine (codegen: auto)')
    for t in result.targets:
        if args.check or t.status == 'failed':
            state = (f'missing {t.missing} of {t.functions} functions'
                     if t.status == 'missing' else t.status)
            print(f'{state:<32} {t.label}')
        if t.error:
            print(f'  {t.error}')
    cached = sum(t.status == 'cached' for t in result.targets)
    if not args.check:
        print(f'{len(result.targets)} parts: {result.compiled} functions compiled, '
              f'{cached} parts already cached ({result.cache_dir})')
    return 0 if result.ok else 1
