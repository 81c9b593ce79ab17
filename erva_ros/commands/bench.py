"""``erva bench``: NMPC solve times, suboptimality and real-time factor in the offline loop."""

import os
import platform

import numpy as np

from erva_ros.commands._closed_loop_options import (add_settings_options, load_settings,
                                                    seed_int, seed_list)
from erva_ros.commands._common import (add_json_option, add_out_option, add_params_option,
                                       compile_first, ensure_out_dir, positive_float,
                                       positive_int, print_json, realtime_priority)
from erva_ros.core.errors import CLIError
from erva_ros.core.progress import Progress

COMMAND = 'bench'
HELP = 'NMPC solve-time benchmark: >= 2000 closed-loop steps, suboptimality vs IPOPT'
DESCRIPTION = """\
Runs --steps closed-loop samples (default 2000 = 40 s) of the paper road with the
chosen controller and solver (default: preview, the real-time sqp), then the same
with the converged IPOPT reference, and reports:

  solve_ms           p50 / p99 / max of controller.compute() wall time (ms), over
                     `samples` solves
  solve_cpu_ms       the same for the solving thread's CPU time: without the time
                     slices other tasks took on its core, what a core of its own gives
  late               solves slower than time_budget_s (their own plan is still used)
  suboptimality_pct  100·(J − J_ref)/|J_ref|, J = the NMPC stage cost summed along the
                     closed loop on the same road (J_ref: the closed loop with IPOPT);
                     negative = better.  This mixes solver and MPC: a converged OCP
                     each sample is not the best closed loop (see README)
  step_gap_pct       the solver alone: at every --audit-every-th sample of the main run,
                     the real-time solve's objective vs IPOPT converged on the same OCP
                     (from three starts, one being the real-time solution): 100·(f − f_ref)
                     /|f_ref| >= 0, p50 / p99 / max / mean
  realtime_factor    simulated time / wall time of the offline closed loop
  load_avg           /proc/loadavg (1, 5, 15 min) before and after the run, and the
                     CPU count: solve times depend on what else the machine runs

--seeds S1,S2,.. runs one closed loop per seed; --repeat K runs the whole set K times
in turn (seed order, then again), so the spread of the solve times over repetitions
shows what the machine's load does to them (docs/nmpc.md's table is such a run).

--live measures the same in the running ROS 2 system instead (erva_ros.session);
--live --ecu virtual in the hardware-in-the-loop loop (simulated ECU on a CAN bus,
bridge, estimator), where the ECU also measures when each command really acts:
its actuation instant − (t_k + d) next to the commands' arrival (--command-delay d).
--live --foxglove-ab N compares N alternating pairs of live runs without and with
`erva run --foxglove` and a connected viewer (erva_ros.session.bench.foxglove_bench)."""


def add_arguments(parser):
    add_params_option(parser)
    add_settings_options(parser, alpha=True)
    parser.add_argument('--steps', type=positive_int, default=2000,
                        help='closed-loop samples (default 2000)')
    parser.add_argument('--seed', type=seed_int, default=0, help='paper-road seed (default 0)')
    parser.add_argument('--seeds', type=seed_list, default=None, metavar='S1,S2,..',
                        help='several paper-road seeds: one line each (real-time vs IPOPT) '
                             'and the mean, instead of --seed')
    parser.add_argument('--repeat', type=positive_int, default=1, metavar='K',
                        help='run the seed (or --seeds) K times in turn, one line each and '
                             'the spread of the solve times (default 1)')
    parser.add_argument('--no-reference', action='store_true',
                        help='skip the IPOPT reference runs (suboptimality_pct and '
                             'step_gap_pct are null)')
    parser.add_argument('--audit-every', type=positive_int, default=10, metavar='K',
                        help='step_gap_pct: re-solve every K-th sample with IPOPT '
                             '(default 10)')
    parser.add_argument('--reference-starts', type=int, choices=(1, 2, 3, 4), default=None,
                        metavar='K', help='IPOPT reference: converge from K of the real-time '
                        "solver's starts, keep the best (1-4; default: the settings file's "
                        'ipopt_starts, 2)')
    parser.add_argument('--live', action='store_true',
                        help='benchmark the live ROS 2 nodes instead of the offline loop')
    parser.add_argument('--duration', type=positive_float, default=None, metavar='S',
                        help='--live only: how long to measure (s)')
    parser.add_argument('--realtime-priority',
                        type=realtime_priority,
                        default=None, metavar='P',
                        help='--live only: SCHED_FIFO priority of the nodes, 0 = normal '
                             'scheduling (default: the live file, config/live.yaml)')
    parser.add_argument('--ecu', choices=('none', 'virtual'), default='none',
                        help='--live only: virtual = the hardware-in-the-loop loop (as `erva '
                             'run --ecu virtual`): the simulated ECU applies the commands and '
                             'measures its actuation jitter (default none: plant_sim_node)')
    parser.add_argument('--busy', type=int, default=0, metavar='K',
                        help='load the machine with K busy-looping processes while measuring '
                             '(e.g. one per core: what does the result owe to a quiet '
                             'machine?); default 0')
    parser.add_argument('--foxglove-ab', type=positive_int, default=None, metavar='N',
                        help='--live only: N alternating pairs of runs without / with the '
                             'Foxglove server and a connected viewer (default --duration '
                             '20 s each)')
    parser.add_argument('--foxglove-viewer', choices=('reading', 'stalled'), default='reading',
                        help='--foxglove-ab: the viewer reads everything, or never reads '
                             '(default reading)')
    add_out_option(parser, 'solve_time_cdf.png (offline: the solve-time CDF against the '
                           'budget, with the IPOPT reference)')
    add_json_option(parser)


def main(args) -> int:
    from erva_ros.session.bench.soak import start_busy, stop_busy
    if args.busy < 0:
        raise CLIError(f'--busy {args.busy}: give 0 or more processes')
    busy = start_busy(args.busy)
    try:
        return _main(args)
    finally:
        stop_busy(busy)


def _main(args) -> int:
    if args.reference_starts is not None and (args.live or args.no_reference):
        raise CLIError('--reference-starts sets the offline IPOPT reference; it cannot go '
                       'with ' + ('--live' if args.live else '--no-reference'))
    if args.foxglove_ab is not None or args.foxglove_viewer != 'reading':
        if not args.live or args.foxglove_ab is None:
            raise CLIError('--foxglove-ab N needs --live (and --foxglove-viewer needs '
                           '--foxglove-ab)')
        from erva_ros.session.run.foxglove_process import check_address
        check_address('127.0.0.1:0')   # foxglove-sdk installed
        from erva_ros.session.bench.foxglove_bench import run_foxglove_ab
        return run_foxglove_ab(args)
    if args.ecu != 'none' and (not args.live or args.foxglove_ab is not None):
        raise CLIError('--ecu virtual benchmarks the live HIL loop: it needs --live (and '
                       'cannot go with --foxglove-ab)')
    if args.live and args.out:
        raise CLIError('--out writes the offline solve-time CDF; it cannot go with --live')
    if args.live and args.repeat != 1:
        raise CLIError('--repeat applies to the offline bench; --live measures one run')
    if args.live:
        try:
            from erva_ros.session.bench.benchmark import run_live_bench
        except ImportError as exc:
            raise CLIError(f'--live needs erva_ros.session.bench.benchmark, which is not '
                           'available '
                           f'({exc})') from None
        return run_live_bench(args)
    if args.duration is not None:
        raise CLIError('--duration applies to --live only; use --steps offline')
    if args.seeds is not None and args.seed != 0:
        raise CLIError('give either --seed or --seeds')
    if args.realtime_priority is not None:
        raise CLIError('--realtime-priority applies to --live only')
    out = ensure_out_dir(args.out)

    from erva_ros.core.model.params import load_erva_params

    params = load_erva_params(args.params)
    settings = load_settings(args)
    name = args.controller or settings.controller
    if name in ('passive', 'skyhook'):
        raise CLIError(f'--controller {name} has no solver to benchmark; use no_preview, '
                       'preview or preview_long')
    settings = settings.with_(controller=name)
    compile_first(COMMAND, params, settings, enabled=not args.json)   # before timing
    seeds = args.seeds if args.seeds is not None else [args.seed]
    samples = {}
    results = [dict(bench_seed(args, params, settings, seed, samples), repeat=r)
               for r in range(args.repeat) for seed in seeds]
    if out:
        _write_cdf(out, settings, seeds, samples, results)
    if len(results) > 1:
        return _print_seeds(args, results)
    result = results[0]
    if args.json:
        print_json(result)
    else:
        sm = result['solve_ms']
        print(f'{name} / {settings.solver}: {result["samples"]} closed-loop samples on the '
              f'paper road, alpha = ({settings.alpha1:g}, {settings.alpha2:g}), '
              f'{result["cost"]} cost')
        print(f'  solve time   p50 {sm["p50"]:.3f} ms, p99 {sm["p99"]:.3f} ms, '
              f'max {sm["max"]:.3f} ms over {result["samples"]} samples; late '
              f'{result["late"]}')
        sc = result['solve_cpu_ms']
        print(f'  solve CPU    p50 {sc["p50"]:.3f} ms, p99 {sc["p99"]:.3f} ms, '
              f'max {sc["max"]:.3f} ms (the solving thread alone)')
        line = f'  closed-loop cost {result["closed_loop_cost"]:.6g}'
        if 'reference' in result:
            line += (f' vs IPOPT {result["reference"]["closed_loop_cost"]:.6g} '
                     f'(suboptimality {result["suboptimality_pct"]:+.2f} %)')
        print(line)
        gap = result['step_gap_pct']
        if gap:
            print(f'  per-sample objective gap to IPOPT (solver alone, {gap["samples"]} '
                  f'samples): p50 {gap["p50"]:.3f} %, p99 {gap["p99"]:.3f} %, '
                  f'max {gap["max"]:.3f} %')
        print(f'  SQP iterations per sample: mean {result["iterations_mean"]:.2f} '
              f'(max_iter {result["max_iter"]})')
        print(f'  real-time factor {result["realtime_factor"]:.1f}x')
        print(f'  {_load_line([result])}')
        for f in result.get('files', []):
            print(f'wrote {f}')
    return 0


def _load_line(results) -> str:
    """Return the load average line of one or more runs."""
    ones = [v for r in results for v in (r['load_avg']['start'][0], r['load_avg']['end'][0])]
    return (f'load average (1 min) {min(ones):.2f}-{max(ones):.2f} on '
            f'{results[0]["load_avg"]["cpus"]} CPUs (figures depend on it)')


def _write_cdf(out, settings, seeds, samples, results) -> None:
    """Write the solve-time CDF of every seed's runs against the budget (``--out``)."""
    from erva_ros.core.plots.figures import solve_time_cdf_figure
    runs = f' x {len(results) // len(seeds)} repetitions' if len(results) > len(seeds) else ''
    path = solve_time_cdf_figure(
        {label: np.concatenate(v) for label, v in samples.items()},
        settings.time_budget_s * 1e3, os.path.join(out, 'solve_time_cdf.png'),
        f'{settings.controller}, {results[0]["samples"]} samples x {len(seeds)} seed(s){runs}, '
        f'paper road; {platform.machine()}, load {os.getloadavg()[0]:.1f}',
        period_ms=settings.ts * 1e3)
    for r in results:
        r['files'] = [path]


def bench_seed(args, params, settings, seed: int, samples=None) -> dict:
    """Run the benchmark of ``settings`` on the paper road of ``seed``; return the result.

    ``samples`` (a dict) collects the solve times (ms) per solver for the CDF figure.
    """
    from erva_ros.core.studies.closed_loop import closed_loop_cost, simulate_closed_loop
    from erva_ros.core.controllers import make_controller
    from erva_ros.core.model.quarter_car import make_model
    from erva_ros.core.road.profiles import make_road

    name = settings.controller
    model = make_model(params)
    cost_kind = settings.long_cost if name == 'preview_long' else settings.cost
    duration = args.steps * settings.ts
    road = make_road('paper', duration, seed=seed)

    def run(s, record=False):
        ctrl = make_controller(name, model, s)
        if record:
            ctrl.recorded_problems = []
        progress = Progress(f'erva bench: seed {seed}, {s.solver}, samples',
                            enabled=not args.json)
        r = simulate_closed_loop(model, ctrl, road, duration, s.ts, progress=progress)
        progress.close()
        if samples is not None:
            samples.setdefault(f'{name} / {s.solver}', []).append(r.solve_time_s * 1e3)
        return ctrl, r

    load_start = _loadavg()
    ctrl, main_run = run(settings, record=settings.solver != 'ipopt')
    load_end = _loadavg()
    m = main_run.metrics
    cost = closed_loop_cost(main_run, settings.alpha1, settings.alpha2, cost_kind)
    result = {
        'solver': settings.solver, 'controller': name, 'samples': int(main_run.t.size),
        'seed': seed, 'solve_ms': {k: m['solve_ms'][k] for k in ('p50', 'p99', 'max')},
        'solve_cpu_ms': {k: m['solve_cpu_ms'][k] for k in ('p50', 'p99', 'max')},
        'late': int(m['fallbacks']['late']),
        'suboptimality_pct': None, 'step_gap_pct': None,
        'realtime_factor': m['realtime_factor'],
        'weights': [settings.alpha1, settings.alpha2], 'cost': cost_kind,
        'max_iter': settings.iteration_cap(name), 'iterations_mean': m['iterations_mean'],
        'time_budget_ms': settings.time_budget_s * 1e3,
        'closed_loop_cost': cost, 'fallbacks': m['fallbacks'],
        'acc_2norm': m['acc_2norm'], 'acc_rms_continuous': m['acc_rms_continuous'],
        'power_w': m['power_w'],
        'machine': f'{platform.machine()}, {platform.python_implementation()} '
                   f'{platform.python_version()}',
        'load_avg': {'start': load_start, 'end': load_end, 'cpus': os.cpu_count()},
    }
    if not args.no_reference and settings.solver != 'ipopt':
        problems = ctrl.recorded_problems[::args.audit_every]
        progress = Progress(f'erva bench: seed {seed}, gap to IPOPT, samples', len(problems),
                            enabled=not args.json)
        gaps = []
        for i, pr in enumerate(problems, 1):
            gaps.append(100 * ctrl.reference_gap(pr))
            progress(i)
        progress.close()
        gaps = np.array(gaps)
        if gaps.size:
            result['step_gap_pct'] = {
                'p50': float(np.percentile(gaps, 50)), 'p99': float(np.percentile(gaps, 99)),
                'max': float(gaps.max()), 'mean': float(gaps.mean()),
                'samples': int(gaps.size)}
        ref_settings = settings.with_(solver='ipopt')
        if args.reference_starts is not None:
            ref_settings = ref_settings.with_(ipopt_starts=args.reference_starts)
        _, ref = run(ref_settings)
        ref_cost = closed_loop_cost(ref, settings.alpha1, settings.alpha2, cost_kind)
        result['suboptimality_pct'] = 100 * (cost - ref_cost) / abs(ref_cost)
        result['reference'] = {'solver': 'ipopt', 'starts': ref_settings.ipopt_starts,
                               'closed_loop_cost': ref_cost,
                               'solve_ms': {k: ref.metrics['solve_ms'][k]
                                            for k in ('p50', 'p99', 'max')},
                               'acc_2norm': ref.metrics['acc_2norm'],
                               'acc_rms_continuous': ref.metrics['acc_rms_continuous'],
                               'power_w': ref.metrics['power_w']}
    elif settings.solver == 'ipopt':
        result['suboptimality_pct'] = 0.0
    return result


def _loadavg():
    """Return the 1, 5 and 15 min load averages (None where the OS has none)."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return [None] * 3


def _spread(results, get) -> list:
    """Return [min, max] of a figure over the runs."""
    values = [get(r) for r in results]
    return [float(min(values)), float(max(values))]


def _print_seeds(args, results) -> int:
    """Print one line per run (seed, repetition: real-time vs IPOPT), the spread; or JSON."""
    first = results[:len(results) // args.repeat]        # one run per seed
    subs = [r['suboptimality_pct'] for r in first if r['suboptimality_pct'] is not None]
    summary = {'seeds': [r['seed'] for r in first], 'repeat': args.repeat,
               'suboptimality_pct_mean': float(np.mean(subs)) if subs else None,
               'suboptimality_pct_max': float(np.max(subs)) if subs else None,
               'solve_ms': {k: _spread(results, lambda r, k=k: r['solve_ms'][k])
                            for k in ('p50', 'p99', 'max')},
               'solve_cpu_ms': {k: _spread(results, lambda r, k=k: r['solve_cpu_ms'][k])
                                for k in ('p50', 'p99', 'max')},
               'realtime_factor': _spread(results, lambda r: r['realtime_factor']),
               'late': sum(r['late'] for r in results),
               'load_avg_1min': _spread(results, lambda r: max(
                   r['load_avg']['start'][0] or 0, r['load_avg']['end'][0] or 0))}
    if args.json:
        print_json({'runs': results, 'summary': summary})
        return 0
    r0 = results[0]
    print(f'{r0["controller"]} / {r0["solver"]}: {r0["samples"]} samples per seed on the paper '
          f'road, alpha = ({r0["weights"][0]:g}, {r0["weights"][1]:g}), {r0["cost"]} cost')
    print('| seed | closed-loop cost | IPOPT | vs IPOPT | acc 2-norm | acc RMS cont. | '
          'power (W) | IPOPT acc 2-norm / cont. / power | solve p50 / p99 / max ms | '
          'RT factor | iter. |')
    print('|---|---|---|---|---|---|---|---|---|---|---|')
    for r in results:
        ref = r.get('reference')
        sub = r['suboptimality_pct']
        sm = r['solve_ms']
        print(f'| {r["seed"]} | {r["closed_loop_cost"]:.5g} | '
              f'{ref["closed_loop_cost"]:.5g} | {sub:+.2f} % | ' if ref else
              f'| {r["seed"]} | {r["closed_loop_cost"]:.5g} | - | - | ', end='')
        print(f'{r["acc_2norm"]:.3f} | {r["acc_rms_continuous"]:.4f} | {r["power_w"]:.3f} | '
              + (f'{ref["acc_2norm"]:.3f} / {ref["acc_rms_continuous"]:.4f} / '
                 f'{ref["power_w"]:.3f}' if ref else '-')
              + f' | {sm["p50"]:.3f} / {sm["p99"]:.3f} / {sm["max"]:.2f} | '
                f'{r["realtime_factor"]:.1f}x | {r["iterations_mean"]:.2f} |')
    if subs:
        print(f'mean vs IPOPT {summary["suboptimality_pct_mean"]:+.2f} %, worst '
              f'{summary["suboptimality_pct_max"]:+.2f} % (negative = better)')
    sp = summary['solve_ms']
    print(f'{len(results)} runs of {r0["samples"]} samples: solve p50 {sp["p50"][0]:.3f}-'
          f'{sp["p50"][1]:.3f} ms, p99 {sp["p99"][0]:.3f}-{sp["p99"][1]:.3f} ms, max '
          f'{sp["max"][0]:.2f}-{sp["max"][1]:.2f} ms, real-time factor '
          f'{summary["realtime_factor"][0]:.1f}-{summary["realtime_factor"][1]:.1f}x, '
          f'late {summary["late"]}; {_load_line(results)}')
    sc = summary['solve_cpu_ms']
    print(f'solve CPU time (the solving thread alone): p50 {sc["p50"][0]:.3f}-'
          f'{sc["p50"][1]:.3f} ms, p99 {sc["p99"][0]:.3f}-{sc["p99"][1]:.3f} ms, max '
          f'{sc["max"][0]:.2f}-{sc["max"][1]:.2f} ms')
    for f in results[0].get('files', []):
        print(f'wrote {f}')
    return 0
