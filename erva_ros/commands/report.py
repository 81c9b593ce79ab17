"""``erva report``: comfort, power, timing, deadline misses and fallbacks from a bag alone."""

import sys

from erva_ros.commands._common import (add_json_option, add_out_option, ensure_out_dir,
                                       print_json)

COMMAND = 'report'
HELP = 'figures of a recorded session from its bag alone (metrics, timing, plots)'
DESCRIPTION = """\
Everything is computed from the bag (no parameters, no re-simulation):

  comfort    chassis-acceleration 2-norm and RMS (paper §IV.B) on /erva/sprung_accel
  power      average harvested power E_h/T: E_h from the plant's /diagnostics
             (harvested_j) when present, else the sum of P = effort·velocity on
             /erva/generator times Ts
  timing     damping_cmd period and jitter |Δ - Ts| from publish times (publisher
             clock) and log times (recorder clock); state -> command latency =
             command publish/log time - stamp of the state it answers
  solver     solve times, deadline misses and fallbacks as the controller reports
             them on /diagnostics; late commands (> 1.5 Ts after the previous one)
             and states that never got a command, from the messages themselves
  prediction the plan's predicted z̈_s, power and states (/erva/prediction) against
             what the bag shows at t_k + h·Ts, h = 1, 5 and N: RMS and max error
  params     a run whose live parameters changed (erva param set, erva run --set):
             its segments by parameter set, from nmpc_node's recorded reports -- from
             when to when, what changed, RMS of z̈_s and mean P at the samples of each --
             and the changes as /parameter_events recorded them

--out DIR writes acceleration.png, damping_cmd.png, power.png, road_preview.png,
prediction.png (predicted vs actual z̈_s and power, 1, 5 and N steps ahead) and,
for realtime sessions, timing.png (command period and latency histograms)."""


def add_arguments(parser):
    parser.add_argument('bag', metavar='BAG', help='bag directory or .mcap file')
    parser.add_argument('--namespace', default=None, metavar='NS',
                        help='namespace of the session topics (default: found in the bag)')
    add_out_option(parser, 'the PNG plots')
    add_json_option(parser)


def _fmt(p, unit='ms'):
    if not p or not p.get('samples'):
        return '-'
    return (f'p50 {p["p50"]:.3f} / p99 {p["p99"]:.3f} / max {p["max"]:.3f} {unit} '
            f'({p["samples"]} samples)')


#: How the report prints each predicted signal: label, unit, scale.
_PREDICTED = {'sprung_accel': ('z̈_s', 'm/s²', 1.0), 'power': ('P', 'W', 1.0),
              'z_s': ('z_s', 'mm', 1e3), 'zdot_s': ('ż_s', 'mm/s', 1e3),
              'z_us': ('z_us', 'mm', 1e3), 'zdot_us': ('ż_us', 'mm/s', 1e3),
              'z_d': ('z_d', 'mm', 1e3), 'zdot_d': ('ż_d', 'mm/s', 1e3)}


def prediction_lines(pred):
    """Return the report's prediction lines (one line when the bag has none)."""
    if pred is None:
        return ['prediction: none in this bag (nmpc_node publishes it with '
                'publish_prediction true)']
    out = [f'prediction: {pred["messages"]} plans, horizon N = {pred["horizon"]}; error '
           'predicted - actual at t_k + h·Ts, RMS / max']
    for h, signals in pred['steps'].items():
        cells = []
        for name, e in signals.items():
            label, unit, scale = _PREDICTED.get(name, (name, '', 1.0))
            cells.append(f'{label} {e["rms"] * scale:.3g} / {e["max"] * scale:.3g} {unit}'
                         if e['samples'] else f'{label} -')
        n = max((e['samples'] for e in signals.values()), default=0)
        out.append(f'  h = {int(h):>2}: ' + ', '.join(cells) + f' ({n} samples)')
    return out


def main(args) -> int:
    from erva_ros.core.bag.reader import open_bag
    from erva_ros.session.bag.bag_report import compute_report, load_session, write_plots
    from erva_ros.session.run.report import jsonable

    opened: list = []       # the bag's own warnings: said at once, before anything can fail

    def warn(line):
        opened.append(line)
        print(f'erva report: warning: {line}', file=sys.stderr)

    bag = open_bag(args.bag, warn=warn)
    out = ensure_out_dir(args.out)
    data = load_session(bag, args.namespace)
    report = compute_report(data)
    if out:
        report['files'] = write_plots(data, out, report['timing']['clock'] == 'wall')
    if args.json:
        print_json(jsonable(report))
        return 0
    s = report['session']
    print(f'session {bag.path}: scenario {s.get("scenario") or "-"}, controller '
          f'{s.get("controller") or "-"}, seed {s.get("seed") or "-"}, '
          f'{report["duration_s"]:.3f} s at Ts = '
          f'{report["ts_s"] * 1e3:.1f} ms' if report['ts_s'] else f'session {bag.path}')
    for w in report['warnings']:
        if w not in opened:
            print(f'warning: {w}')
    c, p = report['comfort'], report['power']
    if not report['samples']['sprung_accel']:
        print('comfort:  no samples (the bag has no sprung_accel messages)')
    else:
        print(f'comfort:  acc 2-norm {c["acc_2norm"]:.4f} m/s², RMS {c["acc_rms"]:.4f} m/s² '
              f'({report["samples"]["sprung_accel"]} samples)')
    if report['samples']['generator'] or p['source'] != 'none':
        print(f'power:    {p["power_w"]:.4f} W average, {p["harvested_j"]:.4f} J harvested '
              f'[{p["source"]}]; mean of P samples {p["power_mean_samples_w"]:.4f} W')
    else:
        print('power:    no samples (neither generator messages nor the plant\'s energy)')
    t = report['timing']
    if t['clock'] == 'offline':
        print('timing:   offline session (simulated, no transport): not measured')
    elif t['clock'] == 'sim':
        print('timing:   lock-step session (stamps in sim time); wall time per step: '
              f'{_fmt(t["wall_per_step_ms"])}')
    elif t['clock'] == 'wall':
        print(f'command period (publish): {_fmt(t["publish"]["period_ms"])}')
        print(f'command jitter (publish): {_fmt(t["publish"]["jitter_ms"])}')
        print(f'command jitter (log):     {_fmt(t["log"]["jitter_ms"])}')
        print(f'state -> command publish: {_fmt(t["latency_publish_ms"])}')
        print(f'state -> command log:     {_fmt(t["latency_log_ms"])}')
        print(f'late commands (> 1.5 Ts): {t["late_commands"]}, states without a command: '
              f'{t["unanswered_states"]}')
    for key, value in sorted(report['solve_ms'].items()):
        print(f'solver:   {key} = {value:.4g}')
    d, f = report['deadline_misses'], report['fallbacks']
    print('deadline misses: ' + (', '.join(f'{k} = {v:g}' for k, v in
                                           sorted(d['reported'].items())) or 'not reported'))
    print('fallbacks:       ' + (', '.join(f'{k} = {v:g}' for k, v in
                                           sorted(f['reported'].items())) or 'not reported'))
    for line in prediction_lines(report['prediction']):
        print(line)
    from erva_ros.session.run.segments import lines as segment_lines
    for line in segment_lines(report.get('tuning')):      # live changes: the segments
        print(line.strip() if line.startswith('  params') else line)
    for e in report['diagnostics_errors']:
        print(f'ERROR diagnostic: {e}')
    outside = report.get('diagnostics_errors_outside') or {}
    if outside:     # start-up and shut-down by design (bag_report.errors_by_span)
        n = sum(len(v) for v in outside.values())
        print(f'outside the loop (before its first sample, after its last): {n} ERROR '
              f'status{"es" if n > 1 else ""} of {", ".join(sorted(outside))} (start-up '
              'and shut-down: waiting for the ECU, the safe command after the last one)')
    for path in report.get('files', []):
        print(f'wrote {path}')
    return 0
