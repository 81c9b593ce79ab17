"""``erva bench-hil``: latency of the HIL bridge and estimator; the estimator in closed loop."""

import contextlib
import os
import sys

from erva_ros.commands._common import (add_json_option, add_params_option, positive_float,
                                       positive_int, print_json, realtime_priority)
from erva_ros.core.errors import CLIError
from erva_ros.core.progress import Progress
from erva_ros.ros.realtime import DEFAULT_PRIORITY

COMMAND = 'bench-hil'
HELP = 'HIL benchmark: bridge and estimator latency (live), estimator closed loop (offline)'
DESCRIPTION = """\
Live (default): runs the real HIL loop for --duration seconds -- `erva ecu-sim`,
ecu_bridge_node and state_estimator_node as separate processes on loopback UDP
CAN and local DDS, with this process as road source and control law -- and
prints the latency each stage adds (p50 / p99 / max in ms, sample counts):

  bridge ROS->CAN   damping_cmd received (DDS receive time) -> CAN frame sent
  bridge CAN->ROS   CAN frame received (kernel time)       -> its topic published
  estimator         last sensor message received          -> /erva/state published
  estimator (outside)  last sensor message published -> state published (DDS stamps)
  sensor->state     first CAN frame of the ECU cycle       -> state received here
  "of which processing": the node's time inside its callbacks (the rest is waiting
  for the CPU / the executor).

Target: <= 1 ms p99 for the bridge and the estimator each.  The first 0.5 s are not
counted.  Also prints the estimation error RMS against the ECU's ground truth.

--cores: the same stages without ROS and DDS (bridge encode + E2E + send on loopback
UDP, receive + E2E + decode, one EKF cycle): their pure CPU cost.

--estimator-eval: offline (no ROS) closed loop of each controller of
--controllers with the full true state and with the EKF's estimate from the ECU's
noisy, quantised sensors, over --seeds paper roads; prints comfort and power of
both and their relative change (erva_ros/core/hil/evaluation.py).  A third run, the
true state plus 0.01 mm / 0.1 mm/s noise ("perturbed"), shows how sensitive the
controller itself is to any state error."""


def add_arguments(parser):
    add_params_option(parser)
    parser.add_argument('--hil-config', metavar='FILE', default=None,
                        help='HIL params file (default: the shipped config/hil.yaml)')
    parser.add_argument('--duration', type=positive_float, default=40.0, metavar='S',
                        help='live run length (s, default 40 = 2000 ECU cycles)')
    parser.add_argument('--law', choices=('skyhook', 'passive'), default='skyhook',
                        help='control law of the stand-in controller (default skyhook)')
    parser.add_argument('--seed', type=int, default=0, help='paper road seed (default 0)')
    parser.add_argument('--realtime-priority',
                        type=realtime_priority,
                        default=DEFAULT_PRIORITY, metavar='P',
                        help='SCHED_FIFO priority of the ECU sim, bridge and estimator, 0 = '
                             'normal scheduling (default %(default)s, as config/live.yaml)')
    parser.add_argument('--cores', action='store_true',
                        help='instead: time the plain-Python cores alone (no ROS): bridge '
                             'encode+send, receive+decode, one EKF cycle; --samples of each')
    parser.add_argument('--samples', type=positive_int, default=2000,
                        help='--cores: samples per stage (default 2000)')
    parser.add_argument('--estimator-eval', action='store_true',
                        help='instead: offline closed loop on estimated vs true state')
    parser.add_argument('--controllers', default='skyhook,preview',
                        help='--estimator-eval: comma-separated controllers '
                             '(passive, skyhook, no_preview, preview, preview_long)')
    parser.add_argument('--weights', default='1,0;0,1',
                        help='--estimator-eval: weight pairs "a1,a2;a1,a2" of the NMPC '
                             'controllers (default "1,0;0,1")')
    parser.add_argument('--seeds', type=positive_int, default=3,
                        help='--estimator-eval: paper-road seeds 0..n-1 (default 3)')
    parser.add_argument('--eval-duration', type=positive_float, default=4.0, metavar='S',
                        help='--estimator-eval: run length (s, default 4 = the paper\'s)')
    add_json_option(parser)


def _weights(text):
    out = []
    for pair in text.split(';'):
        try:
            a1, a2 = (float(v) for v in pair.split(','))
        except ValueError:
            raise CLIError(f'--weights: {pair!r} is not "a1,a2"') from None
        out.append((a1, a2))
    return out


@contextlib.contextmanager
def _c_stdout_to_stderr(enabled: bool):
    """Send what C libraries print on fd 1 (solver banners) to stderr, keeping --json clean."""
    if not enabled:
        yield
        return
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    try:
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def _estimator_eval(args):
    with _c_stdout_to_stderr(args.json):
        result = _evaluate(args)
    if args.json:
        print_json(result)
        return 0
    _print_eval(args, result)
    return 0


def _evaluate(args):
    import numpy as np

    from erva_ros.core.controllers import ControllerSettings, make_controller
    from erva_ros.core.settings.controller import CONTROLLER_NAMES
    from erva_ros.core.hil.ecu_sim import SensorNoise
    from erva_ros.core.hil.evaluation import evaluate_estimator
    from erva_ros.core.hil.settings import (load_ecu_sim_section, load_estimator_section,
                                            noise_of)
    from erva_ros.core.model.quarter_car import make_model
    from erva_ros.core.model.params import load_erva_params
    from erva_ros.core.road.profiles import make_road

    model = make_model(load_erva_params(args.params))
    est = load_estimator_section(args.hil_config)
    sim = load_ecu_sim_section(args.hil_config)
    noise = noise_of(est)
    names = [c.strip() for c in args.controllers.split(',') if c.strip()]
    for c in names:
        if c not in CONTROLLER_NAMES:
            raise CLIError(f'--controllers: unknown {c!r}; choose from '
                           f'{", ".join(CONTROLLER_NAMES)}')
    runs = []
    for name in names:
        for w in (_weights(args.weights) if name not in ('passive', 'skyhook') else [None]):
            # Offline: judge the law itself, not this machine's solve time.
            s = ControllerSettings().with_(time_budget_s=10.0)
            if w is not None:
                s = s.with_(alpha1=w[0], alpha2=w[1])
            runs.append((name, w, s))
    progress = Progress('erva bench-hil --estimator-eval: runs', enabled=not args.json)
    rows = []
    total = len(runs) * args.seeds
    done = 0
    for name, w, settings in runs:
        ctrl = make_controller(name, model, settings)
        per_seed = []
        for seed in range(args.seeds):
            sensor = SensorNoise(sim['noise_sprung_accel'], sim['noise_deflection'],
                                 sim['noise_speed'], sim['noise_current'],
                                 sim['noise_voltage'], seed)
            road = make_road('paper', args.eval_duration, seed=seed)
            per_seed.append(evaluate_estimator(model, ctrl, road, args.eval_duration,
                                               settings.ts, noise, sensor,
                                               u_max=est['u_max']))
            done += 1
            progress(done, total)
        row = {'controller': name, 'weights': list(w) if w else None, 'seeds': args.seeds}
        for part in ('full', 'estimated'):
            row[part] = {k: float(np.mean([r[part][k] for r in per_seed]))
                         for k in ('acc_2norm', 'acc_rms', 'power_w')}
        for key in ('change_pct', 'perturbed_change_pct'):
            row[key] = {k: float(np.mean([r[key][k] for r in per_seed]))
                        for k in per_seed[0][key]}
            row[key + '_worst'] = {k: float(max((r[key][k] for r in per_seed), key=abs))
                                   for k in per_seed[0][key]}
        row['estimation_rms'] = {k: float(np.mean([r['estimation_rms'][k] for r in per_seed]))
                                 for k in per_seed[0]['estimation_rms']}
        row['state_rms'] = {k: float(np.mean([r['state_rms'][k] for r in per_seed]))
                            for k in per_seed[0]['state_rms']}
        rows.append(row)
    return {'mode': 'estimator_eval', 'duration_s': args.eval_duration,
            'noise': noise.as_dict(), 'rows': rows}


def _print_eval(args, result):
    rows = result['rows']
    print(f'estimator closed loop, paper road, {args.eval_duration:g} s, seeds 0..'
          f'{args.seeds - 1}: mean (worst seed); "perturbed" = true state + 0.01 mm / '
          '0.1 mm/s noise, the controller\'s own sensitivity')
    print(f'{"controller":<18} {"acc 2-norm full/est":<20} {"est. change %":<17} '
          f'{"perturbed %":<17} {"power full/est (W)":<20} {"est. change %":<17} perturbed %')
    for r in rows:
        label = r['controller'] + (f' ({r["weights"][0]:g},{r["weights"][1]:g})'
                                   if r['weights'] else '')
        f, e = r['full'], r['estimated']

        def pct(key, m, r=r):
            return f'{r[key][m]:+6.1f} ({r[key + "_worst"][m]:+6.1f})'
        print(f'{label:<18} {f["acc_2norm"]:>7.3f} / {e["acc_2norm"]:<10.3f} '
              f'{pct("change_pct", "acc_2norm"):<17} '
              f'{pct("perturbed_change_pct", "acc_2norm"):<17} '
              f'{f["power_w"]:>7.4f} / {e["power_w"]:<10.4f} {pct("change_pct", "power_w"):<17} '
              f'{pct("perturbed_change_pct", "power_w")}')
    rel = {k: rows[0]['estimation_rms'][k] / rows[0]['state_rms'][k]
           for k in rows[0]['state_rms'] if rows[0]['state_rms'][k] > 0}
    print('estimation error RMS / state RMS (' + rows[0]['controller'] + '): '
          + ', '.join(f'{k} {v:.3f}' for k, v in rel.items()))


def main(args) -> int:
    if args.seed < 0:
        raise CLIError(f'--seed must be >= 0, got {args.seed}')
    if args.estimator_eval:
        return _estimator_eval(args)
    if args.cores:
        from erva_ros.session.bench.hil_bench import run_core_bench
        result = run_core_bench(args.samples)
        if args.json:
            print_json(result)
            return 0
        print('HIL cores alone, no ROS (p50 / p99 / max ms, samples)')
        for key, s in result.items():
            print(f'  {key:<22} {s["p50"]:7.3f} {s["p99"]:7.3f} {s["max"]:7.3f} '
                  f'{int(s["samples"]):6d}')
        return 0
    from erva_ros.session.bench.hil_bench import run_live_bench
    from erva_ros.core.model.params import default_params_file, load_erva_params

    params_file = args.params or default_params_file()
    load_erva_params(params_file)      # a bad file fails here, in one line
    from erva_ros.core.hil.settings import load_bridge_section, load_estimator_section
    load_bridge_section(args.hil_config)
    load_estimator_section(args.hil_config)
    result = run_live_bench(params_file, args.hil_config, args.duration, args.law, args.seed,
                            realtime_priority=args.realtime_priority,
                            log=lambda s: print(f'erva bench-hil: {s}', file=sys.stderr,
                                                flush=True))
    if args.json:
        print_json(result)
    else:
        print(f'HIL loop latency, {args.duration:g} s live, {result["states"]} states, '
              f'law {args.law} (p50 / p99 / max ms, samples)')
        labels = {'bridge_ros_to_can': 'bridge ROS->CAN',
                  'bridge_ros_to_can_processing': '  of which processing',
                  'bridge_can_to_ros': 'bridge CAN->ROS',
                  'bridge_can_to_ros_processing': '  of which processing',
                  'estimator': 'estimator',
                  'estimator_processing': '  of which processing',
                  'estimator_seen_outside': 'estimator (outside)',
                  'sensor_to_state': 'sensor->state'}
        for key, label in labels.items():
            s = result['latency_ms'].get(key) or {}
            if s.get('samples'):
                print(f'  {label:<22} {s["p50"]:7.3f} {s["p99"]:7.3f} {s["max"]:7.3f} '
                      f'{int(s["samples"]):6d}')
            else:
                print(f'  {label:<22} (no samples)')
        if 'estimation_rms' in result:
            print('  estimation error RMS: ' + ', '.join(
                f'{k} {v:.3g}' for k, v in result['estimation_rms'].items()))
        print('  counters: ' + ', '.join(f'{k} {v}' for k, v in result['counters'].items()))
        for e in result['errors']:
            print(f'  error: {e}')
    return 1 if result['errors'] else 0
