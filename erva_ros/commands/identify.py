"""``erva identify``: fit the model's physical parameters to recorded sessions."""

import os

from erva_ros.commands._common import add_json_option, bag_warner, positive_float, print_json
from erva_ros.core.errors import CLIError

COMMAND = 'identify'
HELP = "fit the ERVA's physical parameters to recorded sessions (grey box, shared model)"
DESCRIPTION = """\
Grey-box identification of the physical parameters (paper Table I) of the device that
made the sessions, on the one CasADi model every node uses: output error by multiple
shooting (segments of --segment s, each from its own initial state), Levenberg-Marquardt
with exact derivatives, each signal weighted by its residual noise.

Input: bags of `erva run --ecu ...` (the ECU's measurements ecu/measurements: c_e applied
and its cycle mean, chassis acceleration, suspension deflection, rotor speed) or of a
full-state session (state, sprung_accel, generator).  The road height at the tyre must
be in the bag (road/height: a rig's known road, or the road model); without preview on
a vehicle give a road estimate's topic with --road-topic.  A session with a varying
c_e is needed: record one with the excite controller (controller: excite in the
--nmpc file of `erva run`, a PRBS or chirp over the actuator's range).

Prints which parameters the data determine and from which signal (Fisher information:
the relative standard deviation each signal alone would give), which keep their prior
value and why (undetermined: relative sd > --max-rel-std, or not in the dynamics),
95 % intervals (Gauss-Newton covariance), and the fit (normalised RMS, %) on held-out
data (--validate BAG, else the last --holdout of each bag) for the identified and the
prior model.  --out writes a params file in the layout of config/erva_paper.yaml, which
every node, `erva sim --params` and `erva run --params` take as it is.

Exit status: 0 ok; 2 bad input (no usable topics, too short, no excitation, a parameter
asked for with --estimate that the data do not determine)."""


def _keys(text: str):
    from erva_ros.core.settings.erva import ERVA_SPECS
    keys = [k.strip() for k in text.split(',') if k.strip()]
    for k in keys:
        if k not in ERVA_SPECS:
            import argparse
            raise argparse.ArgumentTypeError(
                f'unknown parameter {k!r}; known: {", ".join(ERVA_SPECS)}')
    return keys


def _fraction(text: str) -> float:
    import argparse
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
    if not 0 <= v < 1:
        raise argparse.ArgumentTypeError(f'{text!r} must be in [0, 1)')
    return v


def add_arguments(parser):
    parser.add_argument('bags', nargs='+', metavar='BAG', help='session bags to fit')
    parser.add_argument('--out', metavar='FILE', default=None,
                        help='write the identified parameters to this params file')
    parser.add_argument('--prior', metavar='FILE', default=None,
                        help='params file of the start values, and of the values of fixed '
                             'parameters (default: the shipped config/erva_paper.yaml)')
    parser.add_argument('--validate', nargs='+', metavar='BAG', default=None,
                        help='held-out bags for the fit report (default: the last --holdout '
                             'of each bag)')
    parser.add_argument('--holdout', type=_fraction, default=0.2, metavar='F',
                        help='share of each bag held out when --validate is not given '
                             '(default 0.2; 0: none)')
    parser.add_argument('--fix', type=_keys, default=[], metavar='K1,K2',
                        help='keep these parameters at the prior (e.g. a weighed M_s)')
    parser.add_argument('--estimate', type=_keys, default=None, metavar='K1,K2',
                        help='fit only these (no automatic fixing: an undetermined one is '
                             'an error naming it)')
    parser.add_argument('--max-rel-std', type=positive_float, default=None, metavar='R',
                        help='relative standard deviation above which a parameter is fixed '
                             'to its prior (default 0.1: a 95 %% interval wider than ±20 %%)')
    parser.add_argument('--segment', type=positive_float, default=1.0, metavar='S',
                        help='multiple-shooting segment length in s (default 1)')
    parser.add_argument('--road-topic', default='road/height', metavar='TOPIC',
                        help='the road height at the tyre, geometry_msgs/PointStamped point.z '
                             '(default road/height, relative to the namespace)')
    parser.add_argument('--namespace', default=None,
                        help='namespace of the session topics (default: found in the bag)')
    add_json_option(parser)


def _split(recs, fraction):
    fit, held = [], []
    for r in recs:
        cut = int(round(r.n * (1 - fraction)))
        fit.append(r.part(0, cut))
        if cut < r.n:
            held.append(r.part(cut, r.n, ' (held out)'))
    return fit, held


def main(args) -> int:
    from erva_ros.core.identify.fit import identify, MAX_REL_STD
    from erva_ros.core.identify.report import as_dict, params_yaml, table
    from erva_ros.core.model.quarter_car import make_model
    from erva_ros.core.model.params import load_erva_params
    from erva_ros.core.identify.bag import load_recordings

    prior = load_erva_params(args.prior)
    if args.out and os.path.isdir(args.out):
        raise CLIError(f'--out {args.out!r} is a directory; give a file name')
    warn = bag_warner('erva identify')
    recs = load_recordings(args.bags, args.namespace, args.road_topic, warn)
    if args.validate:
        fit, held = list(recs), list(load_recordings(args.validate, args.namespace,
                                                     args.road_topic, warn))
    else:
        fit, held = _split(recs, args.holdout)

    def say(text):
        if not args.json:
            print(f'erva identify: {text}', flush=True)

    result = identify(fit, make_model(prior), heldout=held, segment_s=args.segment, fix=args.fix,
                      estimate=args.estimate, max_rel_std=args.max_rel_std or MAX_REL_STD,
                      progress=say)
    sources = [os.path.basename(os.path.normpath(b)) for b in args.bags]
    if args.out:
        try:
            with open(args.out, 'w', encoding='utf-8') as fh:
                fh.write(params_yaml(result, sources))
        except OSError as exc:
            raise CLIError(f'cannot write {args.out!r}: {exc.strerror or exc}') from None
    if args.json:
        out = as_dict(result, sources)
        out['out'] = args.out
        print_json(out)
    else:
        print(table(result))
        if args.out:
            print(f'wrote {args.out}')
    return 0
