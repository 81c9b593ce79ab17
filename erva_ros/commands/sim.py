"""``erva sim``: offline closed loop (no ROS) of any controller on any road."""

import csv
import os

from erva_ros.commands._closed_loop_options import (add_road_options, add_settings_options,
                                                    load_settings, make_road_from_args,
                                                    preview_model_from_args)
from erva_ros.commands._common import (add_json_option, add_out_option, add_params_option,
                                       add_set_option, compile_first, ensure_out_dir,
                                       print_json)
from erva_ros.core.errors import CLIError
from erva_ros.core.settings.loop import MODEL_KINDS

COMMAND = 'sim'
HELP = 'offline closed loop of a controller on a road (paper Figs. 5-7), no ROS'
DESCRIPTION = """\
Offline closed loop: plant simulator (0.5 ms RK4) + controller + road, one control
period Ts per step, exactly as the live lock-step system runs (paper §IV.B).

Metrics: chassis-acceleration 2-norm (over the samples at Ts, the paper's measure)
and RMS (m/s²), the continuous-time RMS (∫ z̈_s² dt integrated by the plant: the
acceleration jumps where the command switches, at the samples, so the sampled
measure can flatter a controller that optimises those instants), average harvested
power (W), controller solve time p50/p99/max (ms) and fallback counts.

--actuation-delay S makes the plant an actuator behind a delay (as the ECU in HIL
mode: each command acts S seconds after its sample, the previous one until then);
--command-delay S makes the controller compensate it (setting command_delay_s).

--set T:KEY=VALUE changes a live setting (weights, damping box, preview switch,
fallback, budget: docs/live.md) before the sample at T s, as `erva run --set` does in the
live loop (in lock-step: from that very sample, the same commands); the output then
gives the run's segments by parameter set, with comfort and power each.

With --out DIR: timeseries.csv and timeseries.png (road, acceleration, power and
damping vs time, like Figs. 5-7).

Example: erva sim --controller preview --alpha 0,1 --seed 3 --out out/sim"""


def add_arguments(parser):
    add_params_option(parser)
    add_settings_options(parser, alpha=True)
    parser.add_argument('--model', choices=MODEL_KINDS, default=MODEL_KINDS[0],
                        help='plant and prediction model (default erva)')
    parser.add_argument('--actuation-delay', type=float, default=0.0, metavar='S',
                        help='the plant applies each command S seconds after its sample '
                             '(0 <= S < ts; default 0)')
    add_road_options(parser)
    add_set_option(parser, 'before that sample is computed')
    add_out_option(parser, 'timeseries.csv and timeseries.png')
    add_json_option(parser)


def main(args) -> int:
    from erva_ros.core.studies.closed_loop import simulate_closed_loop
    from erva_ros.core.controllers import make_controller
    from erva_ros.core.model.quarter_car import make_model
    from erva_ros.core.model.params import load_erva_params

    from erva_ros.core.controllers.tuning import (Built, check_schedule, parse_change,
                                                  ScheduledTuning)
    out = ensure_out_dir(args.out)
    params = load_erva_params(args.params)
    settings = load_settings(args)
    changes = [parse_change(text) for text in args.set]
    check_schedule(Built.of(settings, params.c_e0), settings, changes)   # before anything
    compile_first(COMMAND, params, settings, args.model, not args.json)
    model = make_model(params, args.model)
    controller = make_controller(settings.controller, model, settings)
    road = make_road_from_args(args, args.duration, args.seed)
    preview = preview_model_from_args(args, args.seed, settings.ts)
    tuner = ScheduledTuning(controller, settings, params.c_e0, changes) if changes else None
    try:
        run = simulate_closed_loop(model, controller, road, args.duration, settings.ts,
                                   preview_model=preview,
                                   actuation_delay_s=args.actuation_delay,
                                   before_sample=tuner.before_sample if tuner else None)
    except ValueError as exc:
        raise CLIError(str(exc)) from None
    m = run.metrics
    result = {
        'controller': controller.name, 'road': road.name, 'model': args.model,
        'weights': [settings.alpha1, settings.alpha2],
        'cost': getattr(controller, 'cost', None),
        'solver': settings.solver if controller.name not in ('passive', 'skyhook') else None,
        'duration_s': run.duration_s, 'ts': run.ts, 'samples': int(run.t.size),
        'acc_2norm': m['acc_2norm'], 'acc_rms': m['acc_rms'],
        'acc_rms_continuous': m['acc_rms_continuous'], 'power_w': m['power_w'],
        'actuation_delay_s': args.actuation_delay,
        'command_delay_s': settings.command_delay_s,
        'solve_ms': {k: m['solve_ms'][k] for k in ('p50', 'p99', 'max')},
        'fallbacks': m['fallbacks'], 'realtime_factor': m['realtime_factor'],
    }
    if tuner is not None:
        from erva_ros.session.run import segments
        result['tuning'] = segments.block(segments.segments(
            [(k * run.ts, values) for k, values in tuner.sets], run.t, run.sprung_accel,
            run.power, run.ts))
    if out:
        from erva_ros.core.plots.closed_loop import timeseries_figure
        csv_path = os.path.join(out, 'timeseries.csv')
        with open(csv_path, 'w', newline='', encoding='utf-8') as fh:
            wr = csv.writer(fh)
            wr.writerow(['t_s', 'road_m', 'damping_ns_per_m', 'sprung_accel_m_s2', 'power_w',
                         'solve_ms', 'status'] + [f'x_{n}' for n in model.state_names])
            for k in range(run.t.size):
                wr.writerow([f'{run.t[k]:.4f}', f'{run.w[k]:.6g}', f'{run.u[k]:.6g}',
                             f'{run.sprung_accel[k]:.6g}', f'{run.power[k]:.6g}',
                             f'{run.solve_time_s[k] * 1e3:.4f}', run.status[k]]
                            + [f'{v:.6g}' for v in run.x[k]])
        png = timeseries_figure({controller.name: run}, os.path.join(out, 'timeseries.png'),
                                f'{controller.name} on {road.name}, α = '
                                f'({settings.alpha1:g}, {settings.alpha2:g})')
        result['files'] = [csv_path, png]
    if args.json:
        print_json(result)
    else:
        print(f'{controller.name} on {road.name}, {run.t.size} samples of {run.ts:g} s, '
              f'alpha = ({settings.alpha1:g}, {settings.alpha2:g})')
        print(f'  chassis acceleration: 2-norm {m["acc_2norm"]:.4f} m/s², '
              f'RMS {m["acc_rms"]:.4f} m/s² (at the samples), '
              f'{m["acc_rms_continuous"]:.4f} m/s² (continuous)')
        if args.actuation_delay or settings.command_delay_s:
            print(f'  delay:                actuation {args.actuation_delay * 1e3:g} ms, '
                  f'compensated {settings.command_delay_s * 1e3:g} ms')
        print(f'  harvested power:      {m["power_w"]:.4f} W')
        sm = m['solve_ms']
        print(f'  solve time:           p50 {sm["p50"]:.3f} ms, p99 {sm["p99"]:.3f} ms, '
              f'max {sm["max"]:.3f} ms ({sm["samples"]} samples)')
        fb = {k: v for k, v in m['fallbacks'].items() if v}
        print(f'  fallbacks:            {fb or "none"}')
        print(f'  real-time factor:     {m["realtime_factor"]:.1f}x')
        if tuner is not None:
            from erva_ros.session.run.segments import lines
            print('\n'.join(lines(result['tuning'])))
        for f in result.get('files', []):
            print(f'wrote {f}')
    return 0
