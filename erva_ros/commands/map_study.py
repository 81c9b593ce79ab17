"""``erva map-study``: the NMPC previewing from a map of past drives, against the oracle."""

import json
import os
import time

from erva_ros.commands._closed_loop_options import add_settings_options, load_settings
from erva_ros.commands._common import (add_json_option, add_out_option, add_params_option,
                                       ensure_out_dir, positive_float, positive_int,
                                       print_json)
from erva_ros.core.progress import Progress
from erva_ros.commands._jobs import add_jobs_options, run_jobs
from erva_ros.core.errors import CLIError

COMMAND = 'map-study'
HELP = 'comfort and power with the preview from a map of past drives vs the oracle preview'
DESCRIPTION = """\
For every road seed (paper road as a route, by distance): drives with passive damping,
recorded as the ECU measures them, smoothed by the road estimator and fused into a map
(1, 3, 10 drives; every drive's odometry with the error level e); then 4 s test drives of
the NMPC (after 1 s of warm-up) at (α1, α2) = (1, 0) and (0, 1):

  oracle       true state, the true road ahead (today's preview)
  no_preview   true state, no preview
  estimated    state and road from the road estimator, the true road's shape ahead
  map          estimator + map preview (N drives, odometry error e m, aligned by profile
               matching); also with variance weighting, at another speed than the map
               drives', and with the HIL command delay (modelled in the OCP)

Shares of the oracle's gain over no preview: comfort (continuous RMS z̈_s) at (1, 0),
power at (0, 1), from the means over the seeds.  The goal (issue 26): ≥ 80 % and ≥ 70 %
with a 3-drive map, 0.5 m odometry error and the HIL delay.  Jobs (one per seed) run in
parallel (--jobs) or on a Dask cluster (--scheduler); nothing depends on wall-clock time,
so every way gives the same numbers.  docs/road.md has the tables."""


def _floats(text: str):
    try:
        vals = tuple(float(v) for v in text.split(',') if v.strip())
    except ValueError:
        raise CLIError(f'{text!r}: expected numbers separated by commas') from None
    if not vals or any(not (v >= 0 and v < 1e3) for v in vals):
        raise CLIError(f'{text!r}: expected non-negative numbers')
    return vals


def add_arguments(parser):
    add_params_option(parser)
    add_settings_options(parser, controller=False)
    parser.add_argument('--seeds', type=positive_int, default=10,
                        help='road seeds (default 10)')
    parser.add_argument('--first-seed', type=int, default=100, metavar='N',
                        help='first seed (default 100: nothing was tuned on 100 and up)')
    parser.add_argument('--drives', default='1,3,10', metavar='N[,N...]',
                        help='map sizes in drives (default 1,3,10)')
    parser.add_argument('--odometry', default='0,0.2,0.5,1', metavar='M[,M...]',
                        help='odometry error levels in m (default 0,0.2,0.5,1)')
    parser.add_argument('--duration', type=positive_float, default=4.0, metavar='S',
                        help='measured seconds per test drive, after 1 s warm-up (default 4)')
    parser.add_argument('--other-speed', type=positive_float, default=15.0, metavar='M_PER_S',
                        help='speed of the speed variant (map drives at 20 m/s; default 15)')
    add_jobs_options(parser, 'seed')
    add_out_option(parser, 'map_study.json and map_study.md')
    add_json_option(parser)


def main(args) -> int:
    from erva_ros.core.model.params import load_erva_params
    from erva_ros.core.studies.map_study import aggregate, default_config, run_seed

    drives = tuple(int(v) for v in _floats(args.drives))
    if any(d < 1 or d > 50 for d in drives):
        raise CLIError(f'--drives {args.drives}: each between 1 and 50')
    odometry = _floats(args.odometry)
    cfg = default_config(drives=drives, odometry_m=odometry, duration_s=args.duration,
                         other_speed=args.other_speed,
                         goal_drives=3 if 3 in drives else drives[0],
                         goal_odometry_m=0.5 if 0.5 in odometry else odometry[0])
    out_dir = ensure_out_dir(args.out)
    params = load_erva_params(args.params)
    settings = load_settings(args, time_budget_s=10.0)
    if settings.controller not in ('preview', 'preview_long'):
        settings = settings.with_(controller='preview')
    cfg = default_config(**{**cfg.__dict__, 'controller': settings.controller})
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    jobs = [(params, settings, seed, cfg) for seed in seeds]
    t0 = time.perf_counter()
    per_seed = [r for _, r in run_jobs(run_seed, jobs, args.jobs, args.scheduler,
                                       Progress('erva map-study: seeds'))]
    result = aggregate(per_seed, cfg)
    result.update({'seeds': list(seeds), 'config': {k: v for k, v in cfg.__dict__.items()},
                   'elapsed_s': round(time.perf_counter() - t0, 1),
                   'cost': settings.cost})
    text = markdown(result)
    if out_dir:
        with open(os.path.join(out_dir, 'map_study.json'), 'w', encoding='utf-8') as fh:
            json.dump(result, fh, indent=1)
        with open(os.path.join(out_dir, 'map_study.md'), 'w', encoding='utf-8') as fh:
            fh.write(text)
    if args.json:
        print_json(result)
    else:
        print(text, end='')
    return 0


def _row(result, name, alpha, speed, n=0, e=0.0, delay=False):
    from erva_ros.core.studies.map_study import Variant
    return result['rows'].get(Variant(name, alpha, speed, n, e, delay).key())


def _pct(v):
    return '-' if v is None else f'{v:.0f}'


def markdown(result) -> str:
    """Return the study's tables (docs/road.md shows them)."""
    cfg = result['config']
    v0, comfort, power = cfg['map_speed'], (1.0, 0.0), (0.0, 1.0)
    lines = [f'Seeds {result["seeds"][0]}..{result["seeds"][-1]}, NMPC {cfg["controller"]} '
             f'(cost {result["cost"]}), paper road at {v0:g} m/s, {cfg["duration_s"]:g} s '
             'per test drive; share of the oracle\'s gain over no preview: comfort at (1, 0) '
             '/ power at (0, 1), %', '',
             '| map drives | ' + ' | '.join(f'odometry {e:g} m' for e in cfg['odometry_m'])
             + ' |', '|---|' + '---|' * len(cfg['odometry_m'])]
    for n in cfg['drives']:
        cells = []
        for e in cfg['odometry_m']:
            a, b = _row(result, 'map', comfort, v0, n, e), _row(result, 'map', power, v0, n, e)
            cells.append(f'{_pct(a and a["share_pct"])} / {_pct(b and b["share_pct"])}')
        lines.append(f'| {n} | ' + ' | '.join(cells) + ' |')
    n, e = cfg['goal_drives'], cfg['goal_odometry_m']
    lines += ['', f'The chain at {n} drives, {e:g} m (each row adds one link):', '',
              '| | comfort RMS (m/s²) | share | power (W) | share |', '|---|---|---|---|---|']
    chain = [('no preview (true state)', 'no_preview', 0, 0.0, False),
             ('oracle (true state, true road ahead)', 'oracle', 0, 0.0, False),
             ('+ estimated state and road', 'estimated', 0, 0.0, False),
             (f'+ map of {n} drives (perfect odometry)', 'map', n, 0.0, False),
             (f'+ odometry error {e:g} m, aligned', 'map', n, e, False),
             ('+ HIL command delay 6 ms (modelled)', 'map', n, e, True),
             ('no preview, estimated state and road', 'no_preview_estimated', 0, 0.0, False)]
    for label, name, nn, ee, d in chain:
        a, b = _row(result, name, comfort, v0, nn, ee, d), _row(result, name, power, v0, nn, ee, d)
        if a is None or b is None:
            continue
        lines.append(f'| {label} | {a["acc_rms_continuous"]["mean"]:.4f} ± '
                     f'{a["acc_rms_continuous"]["std"]:.4f} | {_pct(a["share_pct"])} | '
                     f'{b["power_w"]["mean"]:.3f} ± {b["power_w"]["std"]:.3f} | '
                     f'{_pct(b["share_pct"])} |')
    other = cfg['other_speed']
    lines += ['', '| variant | comfort share | power share |', '|---|---|---|']
    for label, name, speed, d in (
            ('map, weighted by variance', 'variance', v0, False),
            (f'map, test drive at {other:g} m/s (own oracle and no preview)', 'map', other, False),
            ('oracle with the HIL delay', 'oracle', v0, True),
            ('no preview with the HIL delay', 'no_preview', v0, True)):
        nn, ee = (0, 0.0) if name in ('oracle', 'no_preview') else (n, e)
        a = _row(result, name, comfort, speed, nn, ee, d)
        b = _row(result, name, power, speed, nn, ee, d)
        if a and b:
            lines.append(f'| {label} | {_pct(a["share_pct"])} | {_pct(b["share_pct"])} |')
    goal = result.get('goal', {})
    if goal:
        lines += ['', 'Goal (3 drives, 0.5 m, HIL delay): ' + ', '.join(
            f'({k}) {_pct(g["share_pct"])} % (target {g["target_pct"]:g} %: '
            f'{"met" if g["met"] else "not met"})' for k, g in goal.items())]
    de, rd = result['drive_error_m'], result['road_detail_rms_m']
    lines += ['', f'Road detail RMS {rd["mean"] * 1e3:.3f} mm; one drive\'s smoothed estimate '
              f'{de["mean"] * 1e3:.3f} ± {de["std"] * 1e3:.3f} mm off; the maps (placed on the '
              'road): ' + ', '.join(
                  f'{k.split("|")[0]} drives {v["rms_m"]["mean"] * 1e3:.3f} mm'
                  for k, v in result['map_errors'].items() if k.endswith(f'|{e:g}'))]
    lines.append(f'({result["elapsed_s"]:.0f} s)')
    return '\n'.join(lines) + '\n'
