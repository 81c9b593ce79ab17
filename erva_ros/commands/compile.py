"""``erva compile``: compile every function the shipped configurations load, before any run."""

import os
import sys

from erva_ros.commands._common import add_json_option, add_params_option, positive_int, print_json
from erva_ros.core.model import codegen
from erva_ros.core.loop import warmup

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
  plant of the HIL loop (config/hil.yaml), and the road EKF of a map's preview.

Targets.  The libraries are built for a CPU, named as GCC's -march takes it: `native`
(the default: this CPU, fastest), `x86-64-v2`, `x86-64-v3`, `x86-64-v4` (the x86-64
psABI levels) or a CPU (`znver3`, `skylake-avx512`, ...).  ERVA_CODEGEN_TARGET picks
the one that runs load; --target builds for others, e.g. a vehicle PC:

  erva compile --target x86-64-v3          # on the workstation, into the cache
  (copy the cache directory to the vehicle PC)
  ERVA_CODEGEN_TARGET=x86-64-v3 ros2 run erva_ros nmpc_node ...   # on the vehicle

The cache is keyed by the target: a run never loads a library built for another
target, and loads a target's libraries only on a CPU that has every instruction-set
feature its code may use (a `native` library only on the CPU that built it).

A library is written atomically, so an interrupted compile leaves nothing broken and
the next one goes on with what is missing; processes compiling the same function
wait for each other.  `erva run`, `erva sim` and `erva bench` compile what they need
the same way before they start or time anything.

Exit status: 0 all compiled (--check: all cached), 1 a compile failed (--check:
something is missing), 2 bad input, 130 interrupted."""


def add_arguments(parser):
    parser.add_argument('--target', action='append', default=None, metavar='MARCH',
                        help='build for this CPU target, as GCC -march names it (native, '
                             'x86-64-v2, x86-64-v3, x86-64-v4, znver3, ...); repeatable '
                             f'(default: ${codegen.TARGET_ENV}, else native)')
    parser.add_argument('--check', action='store_true',
                        help='compile nothing: report what is cached for the target(s), and '
                             'every target the cache holds and whether this CPU runs it')
    parser.add_argument('--jobs', type=positive_int, default=None, metavar='N',
                        help='parts built and compiled at a time (default: the CPUs)')
    add_params_option(parser)
    parser.add_argument('--nmpc', metavar='FILE', default=None,
                        help='controller settings file (default: the shipped config/nmpc.yaml)')
    parser.add_argument('--hil-config', metavar='FILE', default=None,
                        help='HIL parameter file (default: the shipped config/hil.yaml)')
    add_json_option(parser)


def main(args) -> int:
    try:
        return _main(args)
    except KeyboardInterrupt:
        print('erva compile: interrupted; what finished is cached, the next erva compile '
              'goes on from there', file=sys.stderr)
        return 130


def _main(args) -> int:
    parts = warmup.shipped_targets(args.params, args.nmpc, args.hil_config)
    names = args.target or [codegen.codegen_target()]
    log = None if args.json or args.check else (
        lambda line: print(f'erva compile: {line}', file=sys.stderr, flush=True))
    results = {}
    for name in dict.fromkeys(names):
        # The planning processes build as a run with this target would.
        os.environ[codegen.TARGET_ENV] = name
        record = codegen.toolchain().record      # a target GCC does not know: one line
        if log is not None and len(names) > 1:
            log(f'target {name}')
        results[name] = (record, warmup.warm(parts, log, args.jobs, check=args.check))
    overview = warmup.cached_targets(parts) if args.check else []
    ok = all(result.ok for _, result in results.values())
    if args.json:
        print_json({'ok': ok, 'targets': {n: dict(r.as_dict(), record=rec.as_dict())
                                          for n, (rec, r) in results.items()},
                    'cache': [c.as_dict() for c in overview]})
        return 0 if ok else 1
    for name, (record, result) in results.items():
        _print_result(name, record, result, args.check)
    if args.check:
        _print_overview(overview)
    return 0 if ok else 1


def _print_result(name, record, result, check: bool) -> None:
    if result.compiler is None:
        print('no C compiler (cc or gcc) on PATH: the functions run in CasADi\'s virtual '
              'machine (codegen: auto), or from the libraries the cache holds')
    head = f'target {name}' + (f' ({record.cpu})' if record.cpu else '')
    for t in result.targets:
        if check or t.status == 'failed':
            state = (f'missing {t.missing} of {t.functions} functions'
                     if t.status == 'missing' else t.status)
            print(f'{head}: {state:<32} {t.label}')
        if t.error:
            print(f'  {t.error}')
    cached = sum(t.status == 'cached' for t in result.targets)
    if not check:
        print(f'{head}: {len(result.targets)} parts: {result.compiled} functions compiled, '
              f'{cached} parts already cached ({result.cache_dir})')
    missing = record.missing_here()
    if missing:
        print(f'{head}: this CPU cannot run it (no {", ".join(missing)}): copy '
              f'{result.cache_dir} to a machine that can and set '
              f'{codegen.TARGET_ENV}={name} there')


def _print_overview(overview) -> None:
    if not overview:
        print(f'the cache {codegen.codegen_cache_dir()} holds no target yet')
        return
    print(f'targets in the cache {codegen.codegen_cache_dir()} (* the one runs here use):')
    for c in overview:
        name = c.record.target + (f' ({c.record.cpu})' if c.record.cpu else '')
        if c.cached is None:
            state = 'built on another CPU: never loaded here'
        else:
            runs = (f'this CPU cannot run it (no {", ".join(c.missing_here)})'
                    if c.missing_here else 'this CPU runs it')
            state = f'{c.cached} of {c.parts} parts cached; {runs}'
        print(f'{"*" if c.selected else " "} {name:<28} {state}')
