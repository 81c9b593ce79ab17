"""``erva identify-study``: identification measured on plants the fit has never seen."""

import json
import os
import time

from erva_ros.commands._closed_loop_options import (add_settings_options, load_settings,
                                                    non_negative_int)
from erva_ros.commands._common import (add_json_option, add_out_option, ensure_out_dir,
                                       positive_float, positive_int, print_json)
from erva_ros.core.progress import Progress
from erva_ros.commands._jobs import add_jobs_options, run_jobs

COMMAND = 'identify-study'
HELP = 'identify simulated devices (±20 %% off the paper) and compare their NMPCs'
DESCRIPTION = """\
For each of --plants devices, every parameter of the equations of motion is the paper's
times a factor drawn uniformly from [1 - spread, 1 + spread] (seeded by --seed and the
plant's number).  On each device: a --excite-s session of the excite controller (PRBS
over [u_min, u_max]) on an ISO 8608 road through a 6 ms actuator delay, measured as the
ECU does (shipped sensor noise, DBC quantisation), and a --heldout-s session on another
road; `erva identify` from the paper's values; then the NMPC (preview) built on the
identified, the true and the paper's nominal parameters, each run on the device on a
--eval-s paper road at the weightings (1, 0) and (0, 1); and, as the floor of that
comparison, the true model with every parameter moved by ±0.1 % (two sign patterns).

Reports per parameter the error of the estimate and of the prior against the truth and
how often the truth lies inside the 95 % interval; per weighting the gap of J =
a1·acc_rms² - a2·P_avg to the true model's NMPC, identified and nominal, per plant, with
the comfort each NMPC minimises: continuous (∫z̈_s² dt) for --cost continuous (the
default of config/nmpc.yaml), sampled at t_k for --cost paper.
Each device is one job (--jobs, or a Dask cluster with --scheduler).  NMPC model
functions run in CasADi's virtual machine unless --codegen says otherwise (each
device's model would compile its own library)."""


def add_arguments(parser):
    parser.add_argument('--plants', type=positive_int, default=10,
                        help='number of simulated devices (default 10)')
    parser.add_argument('--seed', type=non_negative_int, default=2027,
                        help='seed of the perturbations, roads and noise (default 2027)')
    parser.add_argument('--spread', type=positive_float, default=0.2, metavar='F',
                        help='largest relative perturbation of each parameter (default 0.2)')
    parser.add_argument('--excite-s', type=positive_float, default=60.0, metavar='S',
                        help='length of the identification session (default 60)')
    parser.add_argument('--heldout-s', type=positive_float, default=20.0, metavar='S',
                        help='length of the held-out session (default 20)')
    parser.add_argument('--eval-s', type=positive_float, default=10.0, metavar='S',
                        help='length of each closed-loop run (default 10)')
    add_settings_options(parser, controller=False)
    add_jobs_options(parser, 'device')
    add_out_option(parser, 'study.json and study.md')
    add_json_option(parser)


def _f(v, digits=2):
    return '-' if v is None else f'{v:.{digits}f}'


def markdown(res) -> str:
    """Return the study's two tables."""
    s = res['summary']
    n = res['plants']
    lines = [f'{n} devices (seed {res["seed"]}, ±{100 * res["spread"]:g} %), '
             f'{res["excite_s"]:g} s of excitation each; errors in % of the truth; NMPC '
             f'{res["controller"]}, cost {res["cost"]}, judged on {res["objective"]}', '',
             '| parameter | prior error, mean | free in | error, mean | error, max | '
             'rel. sd, mean | truth inside 95 % | fixed because |',
             '|---|---|---|---|---|---|---|---|']
    for p in s['parameters']:
        lines.append(
            f'| {p["name"]} | {_f(p["prior_error_pct_mean_abs"], 1)} | {p["free_in"]}/{n} | '
            f'{_f(p["error_pct_mean_abs"])} | {_f(p["error_pct_max_abs"])} | '
            f'{_f(p["rel_std_pct_mean"])} | {p["inside_95"]}/{p["free_in"]} | '
            f'{"; ".join(p["fixed_reasons"]) or "-"} |')
    held = s['heldout_fit_pct']
    lines += ['', 'Held-out fit (normalised RMS, %, mean), identified / prior: ' + ', '.join(
        f'{c} {v["identified_mean"]:.1f} / {v["prior_mean"]:.1f}' for c, v in held.items()),
        '', 'J gap to the true model\'s NMPC on each device, % of |J| (negative: better); '
        'floor: the largest |gap| of the true model moved by ±0.1 %', '',
        '| (α1, α2) | model | per device | max |gap| | within 2 % |', '|---|---|---|---|---|']
    for g in s['closed_loop']:
        w = f'({g["weights"][0]:g}, {g["weights"][1]:g})'
        for lab, digits in (('identified', 2), ('nominal', 1)):
            gaps = g[f'{lab}_gap_pct']
            lines.append(f'| {w} | {lab} | {", ".join(f"{v:+.{digits}f}" for v in gaps)} | '
                         f'{g[f"{lab}_gap_pct_max_abs"]:.{digits}f} | '
                         f'{sum(abs(v) <= 2 for v in gaps)}/{n} |')
        floor = [f for f in g['floor_pct'] if f is not None]
        if floor:
            lines.append(f'| {w} | floor (true ±0.1 %) | '
                         f'{", ".join(f"{v:.2f}" for v in g["floor_pct"])} | '
                         f'{max(floor):.2f} | {sum(v <= 2 for v in floor)}/{n} |')
    return '\n'.join(lines) + '\n'


def main(args) -> int:
    from erva_ros.core.studies.identify_study import StudyConfig, study_plant, summarise
    out = ensure_out_dir(args.out)
    settings = load_settings(args, time_budget_s=10.0,
                             **({} if args.codegen else {'codegen': 'off'}))
    cfg = StudyConfig(seed=args.seed, spread=args.spread, excite_s=args.excite_s,
                      heldout_s=args.heldout_s, eval_s=args.eval_s)
    # Each NMPC is judged on what it minimises: the continuous cost on ∫z̈_s² dt, the
    # paper's on the samples.
    objective = 'J_continuous' if settings.cost == 'continuous' else 'J_sampled'
    jobs = [(cfg, settings, i) for i in range(args.plants)]
    t0 = time.perf_counter()
    plants = run_jobs(study_plant, jobs, args.jobs, args.scheduler,
                      Progress('erva identify-study: devices'))
    res = {'plants': args.plants, 'seed': args.seed, 'spread': args.spread,
           'excite_s': args.excite_s, 'heldout_s': args.heldout_s, 'eval_s': args.eval_s,
           'road': f'{cfg.road} class {cfg.road_class}', 'eval_road': cfg.eval_road,
           'controller': cfg.controller, 'cost': settings.cost, 'codegen': settings.codegen,
           'objective': objective, 'summary': summarise(plants, objective),
           'devices': plants,
           'elapsed_s': round(time.perf_counter() - t0, 1)}
    if out:
        with open(os.path.join(out, 'study.json'), 'w', encoding='utf-8') as fh:
            json.dump(res, fh, indent=1)
        with open(os.path.join(out, 'study.md'), 'w', encoding='utf-8') as fh:
            fh.write(markdown(res))
    if args.json:
        print_json(res)
    else:
        print(markdown(res), end='')
        print(f'({res["elapsed_s"]:.0f} s)')
    return 0
