"""``erva fr``: approximate frequency response of the passive ERVA and the benchmark (Fig. 4)."""

import csv
import os
import time

from erva_ros.commands._common import (add_json_option, add_out_option, add_params_option,
                                       ensure_out_dir, positive_float, print_json)
from erva_ros.core.errors import CLIError
from erva_ros.core.progress import Progress

COMMAND = 'fr'
HELP = 'frequency response road -> chassis acceleration and harvested power (paper Fig. 4)'
DESCRIPTION = """\
Approximate frequency response (paper §IV.A, Fig. 4).  For each sinusoidal road
tone the nonlinear ERVA (and the linear benchmark) is simulated with constant
damping u = c_e0 until its response is periodic; the chassis-acceleration
amplitude (m/s²) and the mean harvested power (W) are measured over whole periods.
--out writes them as fr.csv, on linear axes as the paper's Fig. 4 (fr.png), and as a
Bode magnitude plot (fr_bode.png: log frequency; |z̈_s|/|w| in dB re 1 s⁻², power per
squared road amplitude in dB re 1 W/m²).

Paper resonances: passive ERVA 1.7 Hz and 5.8 Hz; benchmark 3.7 Hz."""

PAPER_RESONANCES_HZ = {'erva': [1.7, 5.8], 'benchmark': [3.7]}


def add_arguments(parser):
    add_params_option(parser)
    parser.add_argument('--f-min', type=positive_float, default=1.0, metavar='HZ',
                        help='lowest tone (Hz, default 1)')
    parser.add_argument('--f-max', type=positive_float, default=10.0, metavar='HZ',
                        help='highest tone (Hz, default 10)')
    parser.add_argument('--f-step', type=positive_float, default=0.1, metavar='HZ',
                        help='tone spacing (Hz, default 0.1)')
    parser.add_argument('--amplitude', type=positive_float, default=1e-3, metavar='M',
                        help='road tone amplitude (m, default 0.001 = 1 mm)')
    parser.add_argument('--damping', type=positive_float, default=None, metavar='NS_PER_M',
                        help='constant electrical damping u (Ns/m, default c_e0 from the params)')
    parser.add_argument('--models', default='erva,benchmark',
                        help='comma-separated models to sweep (erva, benchmark)')
    add_out_option(parser, 'fr.csv, fr.png (linear axes, as paper Fig. 4) and fr_bode.png '
                           '(log frequency, dB)')
    add_json_option(parser)


def main(args) -> int:
    import numpy as np

    from erva_ros.core.studies import fr
    from erva_ros.core.model.quarter_car import make_model
    from erva_ros.core.settings.loop import MODEL_KINDS
    from erva_ros.core.model.params import load_erva_params

    if args.f_max < args.f_min:
        raise CLIError(f'--f-max {args.f_max} is below --f-min {args.f_min}')
    models = [m.strip() for m in args.models.split(',') if m.strip()]
    for m in models:
        if m not in MODEL_KINDS:
            raise CLIError(f'--models: unknown model {m!r}; choose from {", ".join(MODEL_KINDS)}')
    out = ensure_out_dir(args.out)
    params = load_erva_params(args.params)
    damping = params.c_e0 if args.damping is None else args.damping
    n = int(np.floor((args.f_max - args.f_min) / args.f_step + 1e-9)) + 1
    freqs = np.round(args.f_min + args.f_step * np.arange(n), 6)

    t0 = time.perf_counter()
    curves = {}
    for kind in models:
        with Progress(f'erva fr: {kind}, tones', len(freqs), enabled=not args.json) as progress:
            curves[kind] = fr.sweep(make_model(params, kind), freqs, args.amplitude, damping,
                                    progress=progress)
    elapsed = time.perf_counter() - t0

    result = {kind: {'accel_peaks_hz': [round(f, 3) for f in fr.find_peaks(c.freqs, c.accel)],
                     'power_peaks_hz': [round(f, 3) for f in fr.find_peaks(c.freqs, c.power)]}
              for kind, c in curves.items()}
    result['amplitude_m'] = args.amplitude
    result['damping_ns_per_m'] = damping
    result['paper_resonances_hz'] = {k: v for k, v in PAPER_RESONANCES_HZ.items() if k in curves}
    result['elapsed_s'] = round(elapsed, 2)

    if out:
        from erva_ros.core.plots.figures import fr_figure
        csv_path = os.path.join(out, 'fr.csv')
        with open(csv_path, 'w', newline='', encoding='utf-8') as fh:
            wr = csv.writer(fh)
            wr.writerow(['model', 'freq_hz', 'accel_amp_m_s2', 'accel_rms_m_s2',
                         'power_mean_w', 'settle_s'])
            for kind, c in curves.items():
                for t in c.tones:
                    wr.writerow([kind, f'{t.freq_hz:g}', f'{t.accel_amp:.6g}',
                                 f'{t.accel_rms:.6g}', f'{t.power_mean_w:.6g}',
                                 f'{t.settle_s:g}'])
        marks = sorted({f for k in curves for f in PAPER_RESONANCES_HZ.get(k, [])})
        png = fr_figure(curves, os.path.join(out, 'fr.png'), marks)
        bode = fr_figure(curves, os.path.join(out, 'fr_bode.png'), marks, bode=True)
        result['files'] = [csv_path, png, bode]

    if args.json:
        print_json(result)
    else:
        print(f'frequency response, {n} tones {freqs[0]:g}-{freqs[-1]:g} Hz, amplitude '
              f'{args.amplitude * 1e3:g} mm, u = {damping:g} Ns/m ({elapsed:.1f} s)')
        print(f'{"model":<10} {"accel peaks (Hz)":<22} {"power peaks (Hz)":<22} paper (Hz)')
        for kind in curves:
            acc = ', '.join(f'{f:.2f}' for f in result[kind]['accel_peaks_hz']) or '-'
            pw = ', '.join(f'{f:.2f}' for f in result[kind]['power_peaks_hz']) or '-'
            paper = ', '.join(f'{f:g}' for f in PAPER_RESONANCES_HZ.get(kind, [])) or '-'
            print(f'{kind:<10} {acc:<22} {pw:<22} {paper}')
        for f in result.get('files', []):
            print(f'wrote {f}')
    return 0
