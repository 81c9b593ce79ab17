"""``erva sensitivity``: what a wrong model, a degraded preview or a delay costs the NMPC."""

import json
import os
import time

from erva_ros.commands._closed_loop_options import (add_settings_options, load_settings,
                                                    PAPER_T1_S, seed_list, weight_list)
from erva_ros.commands._common import (add_json_option, add_out_option, add_params_option,
                                       ensure_out_dir, positive_float, print_json)
from erva_ros.core.progress import Progress
from erva_ros.commands._jobs import add_jobs_options, run_jobs
from erva_ros.core.errors import CLIError

COMMAND = 'sensitivity'
HELP = 'J and its terms against parameter mismatch, preview error and command delay (tornado)'
DESCRIPTION = """\
The paper's open question, "sensitivity analysis of NMPC": on the nominal device (the
--params file, the paper's by default) the NMPC runs with one thing wrong at a time --

  a parameter of its model off by each --levels per cent (every parameter of the
  equations of motion; c_e0 is a command value, not the device's),
  preview_snr: Gaussian noise at each --snr dB on the preview beyond its first point,
  preview_delay: a preview --preview-delays seconds late,
  command_delay: each command acting --command-delays seconds after its sample,
  unmodelled (the NMPC's command_delay_s stays 0);

and reports, per factor and level, the change of J = a1·acc² - a2·P_avg against the
nominal run in per cent of |J| (positive: worse), with the changes of the comfort term
(continuous RMS for --cost continuous, sampled for --cost paper) and of the power,
averaged over --seeds paper-road seeds, at each of --weights.  One row per factor,
sorted by its largest change; --out writes sensitivity.json, sensitivity.md and the
tornado plot sensitivity.png.

Every run is a job: local worker processes (--jobs) or a Dask cluster (--scheduler),
the same numbers either way.  The NMPC's model functions run in CasADi's virtual
machine unless --codegen says otherwise (each mismatched model would compile its own
library)."""

DEFAULT_WEIGHTS = '1,0;0,1'


def _numbers(text, what):
    try:
        vals = [float(v) for v in text.split(',') if v.strip()]
    except ValueError:
        raise CLIError(f'{what}: {text!r} is not a comma-separated list of numbers') from None
    if not vals or any(v != v or abs(v) == float('inf') for v in vals):
        raise CLIError(f'{what}: {text!r} must be finite numbers')
    return vals


def add_arguments(parser):
    add_params_option(parser)
    add_settings_options(parser)
    parser.add_argument('--factors', default='all', metavar='F1,F2',
                        help='factors to vary: parameter names, preview_snr, preview_delay, '
                             'command_delay (default all)')
    parser.add_argument('--levels', default='-20,-10,10,20', metavar='P1,P2',
                        help='parameter mismatches in %% (default -20,-10,10,20; a list that '
                             'starts with a minus needs the = form: --levels=-10,10)')
    parser.add_argument('--snr', default='20,10', metavar='DB1,DB2',
                        help='preview_snr levels in dB (default 20,10)')
    parser.add_argument('--preview-delays', default='0.02,0.04', metavar='S1,S2',
                        help='preview_delay levels in s (default 0.02,0.04)')
    parser.add_argument('--command-delays', default='0.006,0.012', metavar='S1,S2',
                        help='command_delay levels in s, each < ts (default 0.006,0.012: '
                             'the HIL loop\'s p50, and twice that)')
    parser.add_argument('--weights', type=weight_list, default=weight_list(DEFAULT_WEIGHTS),
                        metavar='A1,A2;B1,B2', help=f'weightings (default "{DEFAULT_WEIGHTS}")')
    parser.add_argument('--seeds', type=seed_list, default=[0], metavar='S1,S2',
                        help='paper-road seeds averaged per level (default 0)')
    parser.add_argument('--duration', type=positive_float, default=PAPER_T1_S, metavar='S',
                        help=f'simulated time per run in s (default {PAPER_T1_S:g})')
    add_jobs_options(parser, 'run')
    add_out_option(parser, 'sensitivity.json, sensitivity.md and sensitivity.png')
    add_json_option(parser)


def main(args) -> int:
    from erva_ros.core.model.params import load_erva_params
    from erva_ros.core.studies.sensitivity import (FACTORS, INPUT_FACTORS, markdown, plan,
                                                   run_one, table)

    factors = list(FACTORS) if args.factors == 'all' else [
        f.strip() for f in args.factors.split(',') if f.strip()]
    for f in factors:
        if f not in FACTORS:
            raise CLIError(f'--factors: unknown factor {f!r}; choose from {", ".join(FACTORS)}')
    if not factors:
        raise CLIError('--factors: give at least one factor')
    levels = _numbers(args.levels, '--levels')
    if any(v <= -100 for v in levels):
        raise CLIError(f'--levels: {args.levels!r}: a mismatch must be above -100 %')
    params = load_erva_params(args.params)
    settings = load_settings(args, time_budget_s=10.0,
                             **({} if args.codegen else {'codegen': 'off'}))
    inputs = {'preview_snr': _numbers(args.snr, '--snr'),
              'preview_delay': _numbers(args.preview_delays, '--preview-delays'),
              'command_delay': _numbers(args.command_delays, '--command-delays')}
    for v in inputs['preview_delay']:
        if v < 0:
            raise CLIError(f'--preview-delays: {v:g} must be >= 0')
    for v in inputs['command_delay']:
        if not 0 <= v < settings.ts:
            raise CLIError(f'--command-delays: {v:g} s must be in [0, ts = {settings.ts:g} s)')
    runs = plan(factors, levels, inputs, args.weights, args.seeds)
    out = ensure_out_dir(args.out)
    jobs = [(params, settings, r, args.duration, 'paper') for r in runs]
    t0 = time.perf_counter()
    results = run_jobs(run_one, jobs, args.jobs, args.scheduler,
                       Progress('erva sensitivity: runs', enabled=not args.json))
    rows = table(results)
    header = (f'NMPC {settings.controller}, cost {settings.cost}, paper road '
              f'{args.duration:g} s, seeds {",".join(map(str, args.seeds))}; plant: '
              f'{args.params or "paper Table I"}')
    res = {'controller': settings.controller, 'cost': settings.cost,
           'duration_s': args.duration, 'seeds': args.seeds,
           'levels': {'parameters_pct': levels, **{k: inputs[k] for k in INPUT_FACTORS}},
           'rows': rows, 'runs': results, 'elapsed_s': round(time.perf_counter() - t0, 1)}
    if out:
        files = [os.path.join(out, f'sensitivity.{ext}') for ext in ('json', 'md', 'png')]
        with open(files[0], 'w', encoding='utf-8') as fh:
            json.dump(res, fh, indent=1)
        with open(files[1], 'w', encoding='utf-8') as fh:
            fh.write(markdown(rows, header))
        from erva_ros.core.plots.closed_loop import tornado_figure
        tornado_figure(rows, files[2], header)
        res['files'] = files
    if args.json:
        print_json(res)
    else:
        print(markdown(rows, header), end='')
        print(f'({res["elapsed_s"]:.0f} s)')
        for f in res.get('files', []):
            print(f'wrote {f}')
    return 0
