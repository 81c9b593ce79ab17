"""``erva pareto``: comfort vs harvested power as the weight ratio α2/α1 sweeps."""

import csv
import os
import time

from erva_ros.commands._closed_loop_options import (add_settings_options, load_settings,
                                                    PAPER_T1_S)
from erva_ros.commands._common import (add_json_option, add_out_option, add_params_option,
                                       ensure_out_dir, positive_float, positive_int,
                                       print_json)
from erva_ros.commands._jobs import add_jobs_options, run_jobs
from erva_ros.core.errors import CLIError
from erva_ros.core.progress import Progress

COMMAND = 'pareto'
HELP = 'comfort vs harvested power as alpha2/alpha1 sweeps, with passive and skyhook points'
DESCRIPTION = """\
The trade-off the paper describes in words (§IV.B): the NMPC (default: preview) is run
with α1 = 1 and α2 = each --ratios value (and α = (0, 1) for the pure-energy end),
averaged over --seeds paper-road seeds; passive and skyhook are the baselines.
Writes pareto.csv and pareto.png (acceleration RMS vs average power) with --out.
Every (point, seed) run is a job: local worker processes (--jobs) or a Dask cluster
(--scheduler); the numbers are the same either way."""

DEFAULT_RATIOS = '0,0.01,0.1,1,3,10,30,100'


def _ratios(text):
    try:
        vals = [float(v) for v in text.split(',') if v.strip()]
    except ValueError:
        raise CLIError(f'--ratios: {text!r} is not a comma-separated list of numbers') from None
    if not vals or any(v < 0 or v != v or v == float('inf') for v in vals):
        raise CLIError(f'--ratios: {text!r} must be non-negative finite numbers')
    return sorted(set(vals))


def add_arguments(parser):
    add_params_option(parser)
    add_settings_options(parser)
    parser.add_argument('--ratios', default=DEFAULT_RATIOS, metavar='R1,R2,...',
                        help=f'alpha2/alpha1 values with alpha1 = 1 (default {DEFAULT_RATIOS}); '
                             'the point alpha = (0, 1) is always added')
    parser.add_argument('--seeds', type=positive_int, default=3,
                        help='paper-road seeds 0..n-1 averaged per point (default 3)')
    parser.add_argument('--duration', type=positive_float, default=PAPER_T1_S, metavar='S',
                        help=f'simulated time per run in s (default {PAPER_T1_S:g})')
    add_jobs_options(parser, '(point, seed) run')
    add_out_option(parser, 'pareto.csv and pareto.png')
    add_json_option(parser)


def run_point(job):
    """Return (acc RMS, power) of one controller, weighting and seed (a pure function)."""
    from erva_ros.core.studies.closed_loop import simulate_closed_loop
    from erva_ros.core.controllers import make_controller
    from erva_ros.core.model.quarter_car import make_model
    from erva_ros.core.road.profiles import make_road

    params, settings, name, seed, duration = job
    model = make_model(params)
    run = simulate_closed_loop(model, make_controller(name, model, settings),
                               make_road('paper', duration, seed=seed), duration, settings.ts)
    return run.metrics['acc_rms'], run.metrics['power_w']


def main(args) -> int:
    import numpy as np

    from erva_ros.core.model.params import load_erva_params

    ratios = _ratios(args.ratios)
    out = ensure_out_dir(args.out)
    params = load_erva_params(args.params)
    # Offline quality runs: the real-time budget is not enforced (10 s), so results do
    # not depend on machine load; `erva bench` measures timing.
    settings = load_settings(args, time_budget_s=10.0)
    name = args.controller or ('preview' if settings.controller in ('passive', 'skyhook')
                               else settings.controller)
    if name in ('passive', 'skyhook'):
        raise CLIError(f'--controller {name} has no weights to sweep; use an NMPC controller')
    cost_kind = settings.long_cost if name == 'preview_long' else settings.cost
    points = [(1.0, r) for r in ratios] + [(0.0, 1.0)]
    cases = ([(name, settings.with_(alpha1=a1, alpha2=a2)) for a1, a2 in points]
             + [(base, settings) for base in ('passive', 'skyhook')])
    jobs = [(params, s, ctrl, seed, args.duration) for ctrl, s in cases
            for seed in range(args.seeds)]
    t0 = time.perf_counter()
    with Progress('erva pareto: runs', len(jobs), enabled=not args.json) as progress:
        results = run_jobs(run_point, jobs, args.jobs, args.scheduler, progress)
    means = [np.mean(results[i:i + args.seeds], axis=0)
             for i in range(0, len(results), args.seeds)]
    curve = []
    for (a1, a2), (acc, pw) in zip(points, means):
        curve.append({'alpha1': a1, 'alpha2': a2,
                      'ratio': (a2 / a1) if a1 > 0 else float('inf'),
                      'acc_rms': float(acc), 'power_w': float(pw)})
    baselines = [{'controller': base, 'acc_rms': float(acc), 'power_w': float(pw)}
                 for base, (acc, pw) in zip(('passive', 'skyhook'), means[len(points):])]
    elapsed = time.perf_counter() - t0
    json_curve = [dict(c, ratio=None if c['alpha1'] == 0 else c['ratio']) for c in curve]
    result = {'controller': name, 'cost': cost_kind, 'seeds': args.seeds,
              'duration_s': args.duration, 'curve': json_curve, 'baselines': baselines,
              'elapsed_s': round(elapsed, 1)}
    if out:
        from erva_ros.core.plots.closed_loop import pareto_figure
        csv_path = os.path.join(out, 'pareto.csv')
        with open(csv_path, 'w', newline='', encoding='utf-8') as fh:
            wr = csv.writer(fh)
            wr.writerow(['controller', 'alpha1', 'alpha2', 'acc_rms_m_s2', 'power_w'])
            for c in curve:
                wr.writerow([name, c['alpha1'], c['alpha2'], f'{c["acc_rms"]:.6g}',
                             f'{c["power_w"]:.6g}'])
            for b in baselines:
                wr.writerow([b['controller'], '', '', f'{b["acc_rms"]:.6g}',
                             f'{b["power_w"]:.6g}'])
        png = pareto_figure(curve, baselines, os.path.join(out, 'pareto.png'),
                            f'{name} ({cost_kind} cost), paper road, {args.seeds} seed(s)')
        result['files'] = [csv_path, png]
    if args.json:
        print_json(result)
    else:
        print(f'{name}, paper road, {args.seeds} seeds x {args.duration:g} s '
              f'({elapsed:.0f} s)')
        print(f'{"alpha1":>7} {"alpha2":>7} {"acc RMS (m/s²)":>15} {"power (W)":>10}')
        for c in curve:
            print(f'{c["alpha1"]:7g} {c["alpha2"]:7g} {c["acc_rms"]:15.4f} {c["power_w"]:10.4f}')
        for b in baselines:
            print(f'{b["controller"]:>15} {b["acc_rms"]:15.4f} {b["power_w"]:10.4f}')
        for f in result.get('files', []):
            print(f'wrote {f}')
    return 0
