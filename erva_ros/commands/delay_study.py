"""``erva delay-study``: what a command delay costs, and what modelling it recovers."""

from erva_ros.commands._closed_loop_options import add_settings_options, load_settings
from erva_ros.commands._common import (add_json_option, add_params_option, positive_float,
                                       positive_int, print_json)
from erva_ros.commands._jobs import run_jobs
from erva_ros.core.errors import CLIError
from erva_ros.core.progress import Progress

COMMAND = 'delay-study'
HELP = 'command delay: comfort/power without, with, and with the delay modelled, per seed'
DESCRIPTION = """\
On a vehicle each command acts a delay d after its sample t_k (HIL here: 7-9 ms of
the 20 ms period).  For road seeds 0..--seeds-1 of the paper road (--duration each)
this runs the controller four ways:

  no_delay    the command acts at its sample (the plant of `erva sim`)
  delayed     the plant applies every command d late (--delay), the controller
              does not know (erva sim --actuation-delay)
  predicted   ... and the controller plans from x(t_k + d) predicted with the
              acting command on the preview shifted by d (erva_ros/core/controllers/
              delay.py, the method for laws without a model of their own)
  modelled    ... and the NMPC models the delay in its OCP: over [t_k, t_k + d]
              the acting command, then the plan (setting command_delay_s; the
              NMPC's default compensation)

and prints per seed and as mean ± std: the continuous RMS chassis acceleration
(∫ z̈_s² dt, exact), the sampled RMS (at t_k, the paper's measure), the power.
With a delay the command switches at t_k + d, so the samples at t_k no longer sit
on the switching instants: the continuous measure is the one comparable across
delays.  The real-time budget is not enforced (results do not depend on load).

Example: erva delay-study --seeds 8 --duration 10 --delay 0.008 --jobs 2"""

VARIANTS = ('no_delay', 'delayed', 'predicted', 'modelled')


def add_arguments(parser):
    add_params_option(parser)
    add_settings_options(parser, alpha=True)
    parser.add_argument('--seeds', type=positive_int, default=8,
                        help='number of paper-road seeds 0..n-1 (default 8)')
    parser.add_argument('--duration', type=positive_float, default=10.0, metavar='S',
                        help='simulated time per run in s (default 10)')
    parser.add_argument('--delay', type=positive_float, default=0.008, metavar='S',
                        help='the command delay d in s, 0 < d < ts (default 0.008)')
    parser.add_argument('--jobs', type=positive_int, default=1,
                        help='worker processes, one seed each (default 1)')
    add_json_option(parser)


def run_seed(job):
    """Run the four variants on one seed; return {variant: metrics}."""
    from erva_ros.core.studies.closed_loop import simulate_closed_loop
    from erva_ros.core.controllers import make_controller
    from erva_ros.core.model.quarter_car import make_model
    from erva_ros.core.road.profiles import make_road

    params, settings, seed, duration, delay = job
    model = make_model(params)
    road = make_road('paper', duration, seed=seed)
    out = {}
    for variant in VARIANTS:
        s = settings.with_(command_delay_s=delay if variant == 'modelled' else 0.0)
        ctrl = make_controller(s.controller, model, s)
        if variant == 'predicted':
            ctrl.predict_delay(model, delay)
        run = simulate_closed_loop(model, ctrl, road, duration, s.ts,
                                   actuation_delay_s=0.0 if variant == 'no_delay' else delay)
        m = run.metrics
        out[variant] = {'acc_rms_continuous': m['acc_rms_continuous'],
                        'acc_rms': m['acc_rms'], 'power_w': m['power_w'],
                        'fallbacks': sum(m['fallbacks'][k] for k in
                                         ('fallback_plan', 'fallback_passive'))}
    return seed, out


def main(args) -> int:
    import numpy as np
    from erva_ros.core.model.params import load_erva_params

    params = load_erva_params(args.params)
    # Offline study: no real-time budget, so results do not depend on machine load.
    settings = load_settings(args, time_budget_s=10.0)
    if settings.controller == 'passive':
        raise CLIError('--controller passive does not react to a delay; choose another')
    if not args.delay < settings.ts:
        raise CLIError(f'--delay {args.delay:g} must be below ts = {settings.ts:g} s')
    jobs = [(params, settings, seed, args.duration, args.delay) for seed in range(args.seeds)]
    with Progress('erva delay-study: seeds', len(jobs), enabled=not args.json) as progress:
        per_seed = dict(run_jobs(run_seed, jobs, args.jobs, progress=progress))
    keys = ('acc_rms_continuous', 'acc_rms', 'power_w')
    summary = {}
    for v in VARIANTS:
        summary[v] = {}
        for k in keys:
            vals = np.array([per_seed[s][v][k] for s in sorted(per_seed)])
            summary[v][k] = {'mean': float(vals.mean()),
                             'std': float(vals.std(ddof=1)) if vals.size > 1 else 0.0}
    cont = {v: np.array([per_seed[s][v]['acc_rms_continuous'] for s in sorted(per_seed)])
            for v in VARIANTS}
    result = {'controller': settings.controller, 'weights': [settings.alpha1, settings.alpha2],
              'cost': settings.long_cost if settings.controller == 'preview_long'
              else settings.cost, 'delay_s': args.delay, 'duration_s': args.duration,
              'seeds': {str(s): per_seed[s] for s in sorted(per_seed)}, 'summary': summary,
              'modelled_vs_no_delay_pct': float(100 * (cont['modelled'].mean()
                                                       / cont['no_delay'].mean() - 1)),
              'modelled_better_than_delayed': int(np.sum(cont['modelled'] < cont['delayed']))}
    if args.json:
        print_json(result)
        return 0
    print(f'{settings.controller}, alpha = ({settings.alpha1:g}, {settings.alpha2:g}), '
          f'{result["cost"]} cost; delay {args.delay * 1e3:g} ms; paper road, '
          f'{args.duration:g} s per seed')
    print('RMS chassis acceleration, continuous / at the samples (m/s²); power (W)')
    print('| seed | ' + ' | '.join(VARIANTS) + ' |')
    print('|---|' + '---|' * len(VARIANTS))

    def cell(m):
        return f'{m["acc_rms_continuous"]:.4f} / {m["acc_rms"]:.4f}; {m["power_w"]:.3f}'
    for s in sorted(per_seed):
        print(f'| {s} | ' + ' | '.join(cell(per_seed[s][v]) for v in VARIANTS) + ' |')
    print('| mean ± std | ' + ' | '.join(
        f'{summary[v]["acc_rms_continuous"]["mean"]:.4f} ± '
        f'{summary[v]["acc_rms_continuous"]["std"]:.4f} / {summary[v]["acc_rms"]["mean"]:.4f}; '
        f'{summary[v]["power_w"]["mean"]:.3f}' for v in VARIANTS) + ' |')
    print(f'modelled vs no delay (continuous RMS, mean): '
          f'{result["modelled_vs_no_delay_pct"]:+.1f} %; modelled better than delayed on '
          f'{result["modelled_better_than_delayed"]} of {len(per_seed)} seeds')
    return 0
