"""``erva replay``: publish a session bag with its original timing, or drive a what-if run."""

import contextlib
import os
import sys

from erva_ros.commands._common import (add_json_option, add_params_option, positive_float,
                                       print_json)
from erva_ros.commands.run import FOXGLOVE_DEFAULT
from erva_ros.core.errors import CLIError
from erva_ros.core.progress import Progress

COMMAND = 'replay'
HELP = 'play a bag like "ros2 bag play", or drive a fresh plant with its road (--drive-plant)'
DESCRIPTION = """\
Play (default): publishes every recorded message at its original time offset
(receive times, scaled by --rate), as raw CDR from publishers offering the
recorded QoS, like "ros2 bag play".  Nodes and tools subscribed to the topics see
the session again.  --clock publishes the playback time on /clock (then a
recorded /clock is not replayed).  Uses $ROS_DOMAIN_ID.  --foxglove [HOST:]PORT also
serves the played messages to Foxglove as `erva run --foxglove` does (same channels,
schemas and layout; log times as recorded); playing starts once a viewer subscribes.

Re-evaluation (--reevaluate): nothing is published.  The recorded states and
previews are fed, in order, to a fresh controller built from the parameters stored
in the session (wall-clock budget lifted, as in lock-step); it prints how many of
the recorded commands it reproduces (exit status 3 if not all of them).

What-if (--drive-plant): nothing is published.  The road recorded at the tyre
(/erva/road/height) drives a fresh offline closed loop with --controller (and
--alpha1/--alpha2, --settings); the run is written as a new session bag under
--record-dir and compared with the recorded one.

Examples:
  erva replay bags/sample --rate 2 --topics /erva/state /erva/damping_cmd
  erva replay bags/sample --loop --clock 100
  erva replay bags/sample --reevaluate
  erva replay bags/sample --drive-plant --controller skyhook"""


def add_arguments(parser):
    parser.add_argument('bag', metavar='BAG', help='bag directory or .mcap file')
    parser.add_argument('--rate', type=positive_float, default=1.0,
                        help='playback speed factor (default 1 = original timing)')
    parser.add_argument('--topics', nargs='+', metavar='TOPIC', default=None,
                        help='play only these topics (default: all)')
    parser.add_argument('--loop', action='store_true', help='play again until Ctrl-C')
    parser.add_argument('--clock', nargs='?', type=positive_float, const=40.0, default=None,
                        metavar='HZ', help='publish the playback time on /clock at HZ '
                                           '(default 40 when given without a value)')
    parser.add_argument('--delay', type=float, default=0.0, metavar='S',
                        help='wait S seconds before the first message (discovery)')
    parser.add_argument('--wait-for-subscribers', type=float, default=0.0, metavar='S',
                        help='wait up to S seconds until every topic (and /clock with --clock) '
                             'has a subscriber')
    parser.add_argument('--foxglove', nargs='?', const=FOXGLOVE_DEFAULT, default=None,
                        metavar='[HOST:]PORT',
                        help='also serve the messages to Foxglove on this address (default '
                             f'{FOXGLOVE_DEFAULT}: this machine only; PORT 0 = any free '
                             'port); playing starts when a viewer subscribes')
    again = parser.add_argument_group('re-evaluation (--reevaluate)')
    again.add_argument('--reevaluate', action='store_true',
                       help='recompute the recorded commands with a fresh controller')
    again.add_argument('--max-commands', type=int, default=None, metavar='N',
                       help='re-evaluate only the first N commands')
    what = parser.add_argument_group('what-if on the recorded road (--drive-plant)')
    what.add_argument('--drive-plant', action='store_true',
                      help='run a fresh closed loop on the recorded road instead of playing')
    what.add_argument('--controller', default=None,
                      help='controller of the what-if run or the re-evaluation (passive, '
                           'skyhook, no_preview, preview, preview_long; default: from '
                           '--settings, resp. the session)')
    what.add_argument('--alpha1', type=float, default=None,
                      help='comfort weight alpha1 (paper eq. (12))')
    what.add_argument('--alpha2', type=float, default=None,
                      help='energy weight alpha2 (paper eq. (12))')
    what.add_argument('--settings', metavar='FILE', default=None,
                      help='controller settings (default config/nmpc.yaml)')
    add_params_option(what)
    what.add_argument('--record-dir', metavar='DIR', default='bags',
                      help='parent directory of the new session bag (default bags)')
    what.add_argument('--duration', type=positive_float, default=None, metavar='S',
                      help='simulate only the first S seconds of the recorded road')
    add_json_option(parser)


@contextlib.contextmanager
def _native_stdout_to_stderr():
    """Send what native libraries print to stdout (the qpOASES banner) to stderr.

    Keeps ``--json`` output parseable; Python-level prints are unaffected once restored.
    """
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def _drive_plant(args, bag) -> int:
    from erva_ros.session.whatif import drive_plant
    from erva_ros.session.bag_report import compute_report, load_session
    from erva_ros.session.report import jsonable
    from erva_ros.core.bag.session import new_bag_dir
    from erva_ros.core.controllers import load_controller_settings
    from erva_ros.core.params import load_erva_params

    params = load_erva_params(args.params)
    settings = load_controller_settings(args.settings, {'controller': args.controller,
                                                        'alpha1': args.alpha1,
                                                        'alpha2': args.alpha2})
    name = settings.controller
    data = load_session(bag)
    before = compute_report(data)
    out_dir = new_bag_dir(args.record_dir, f'whatif-{name}')
    with _native_stdout_to_stderr():   # the plant and the controller: the recorded model
        result, meta = drive_plant(bag, out_dir, name, params, settings,
                                   session_extra={'alpha1': settings.alpha1,
                                                  'alpha2': settings.alpha2},
                                   kind=data.model, duration_s=args.duration)
    m = result.metrics
    summary = {'bag': bag.path, 'new_bag': out_dir, 'controller': name,
               'weights': [settings.alpha1, settings.alpha2],
               'recorded': {'controller': bag.session.get('controller', ''),
                            'duration_s': before['duration_s'],
                            'acc_2norm': before['comfort']['acc_2norm'],
                            'acc_rms': before['comfort']['acc_rms'],
                            'power_w': before['power']['power_w']},
               'what_if': {'duration_s': result.duration_s, 'acc_2norm': m['acc_2norm'],
                           'acc_rms': m['acc_rms'], 'power_w': m['power_w'],
                           'solve_ms': m['solve_ms'], 'fallbacks': m['fallbacks']},
               'messages': meta['message_count']}
    if args.json:
        print_json(jsonable(summary))
        return 0
    r, w = summary['recorded'], summary['what_if']
    print(f'what-if on the road of {bag.path} ({w["duration_s"]:.2f} s simulated)')
    print(f'{"":<28}{"acc 2-norm":>12}{"acc RMS":>10}{"power (W)":>11}')
    print(f'{"recorded (" + (r["controller"] or "?") + ")":<28}{r["acc_2norm"]:12.4f}'
          f'{r["acc_rms"]:10.4f}{r["power_w"]:11.4f}')
    print(f'{"what-if (" + name + ")":<28}{w["acc_2norm"]:12.4f}{w["acc_rms"]:10.4f}'
          f'{w["power_w"]:11.4f}')
    if abs(r['duration_s'] - w['duration_s']) > 1e-6:
        print(f'note: the recorded session lasted {r["duration_s"]:.2f} s; the 2-norm grows '
              'with the number of samples')
    print(f'wrote {out_dir} ({meta["message_count"]} messages)')
    return 0


def _reevaluate(args, bag) -> int:
    from erva_ros.session.reevaluate import controller_from_session, reevaluate, summarize
    from erva_ros.session.bag_report import load_session
    from erva_ros.session.report import jsonable
    from erva_ros.core.controllers import make_controller

    params, settings = controller_from_session(bag, args.controller)
    data = load_session(bag)
    with _native_stdout_to_stderr():
        controller = make_controller(settings.controller, params, settings, kind=data.model)
        total = len(data.cmd.stamp_ns[:args.max_commands])
        with Progress('erva replay --reevaluate: commands', total,
                      enabled=not args.json) as progress:
            result = summarize(reevaluate(data, controller, args.max_commands, progress))
    result.update({'bag': bag.path, 'controller': settings.controller})
    if args.json:
        print_json(jsonable(result))
    else:
        print(f'{bag.path}: {result["reproduced"]} of {result["commands"]} recorded commands '
              f'reproduced by a fresh {settings.controller} (max |du| '
              f'{result["max_abs_difference"]:.3g} Ns/m, tolerance {result["tolerance"]:g}); '
              f'statuses {result["statuses"]}')
    return 0 if result['identical'] else 3


def _play(args, bag) -> int:
    import signal
    import time

    from erva_ros.ros.context import RosContext
    from erva_ros.ros.replay import Player

    server = None
    stop = {'flag': False}
    ros = RosContext()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.update(flag=True))
    try:
        node = ros.create_node('erva_replay')
        player = Player(node, bag, rate=args.rate, topics=args.topics, loop=args.loop,
                        clock_hz=args.clock or 0.0)
        if args.foxglove is not None:
            server = _serve(args.foxglove, bag, player, lambda: stop['flag'])
        if args.wait_for_subscribers > 0 and not player.wait_for_subscribers(
                args.wait_for_subscribers):
            print('erva replay: warning: not every topic has a subscriber; playing anyway',
                  file=sys.stderr)
        end = time.monotonic() + max(0.0, args.delay)
        while time.monotonic() < end and not stop['flag']:
            time.sleep(0.02)
        stats = player.run(lambda: stop['flag'])
        stats['acknowledged'] = player.finish()
        if server is not None:
            stats['foxglove'] = server.stats()
    finally:
        if server is not None:
            server.close()
        ros.close()
    if args.json:
        from erva_ros.session.report import jsonable
        print_json(jsonable(stats))
    else:
        state = 'stopped' if stats['stopped'] else 'done'
        print(f'{state}: published {stats["total"]} messages on {len(stats["published"])} '
              f'topics in {stats["wall_s"]:.2f} s (rate {stats["rate"]:g}, '
              f'{stats["passes"]} pass(es)); lateness p99 '
              f'{stats["lateness_ms"]["p99"]:.2f} ms')
        if 'foxglove' in stats:
            fox = stats['foxglove']
            print(f'Foxglove: forwarded {fox["forwarded_total"]} messages; '
                  f'{fox["clients_seen"]} viewer(s)')
    return 130 if stats['stopped'] and not args.loop else 0


#: A viewer's subscriptions are complete when no new one came for this long (s).
SETTLE_S = 0.5


def _serve(address, bag, player, should_stop):
    """Start the Foxglove server of a replay; wait until a viewer subscribes (or a stop)."""
    import time

    from erva_ros.session.bag_report import guess_namespace
    from erva_ros.ros.foxglove_server import FoxgloveServer, parse_address, ReplaySink

    host, port = parse_address(address)
    try:
        server = FoxgloveServer(host, port, name=f'erva replay {bag.path}',
                                session=bag.session, namespace=guess_namespace(bag),
                                with_time=True)
    except RuntimeError as exc:   # the port was taken since check_address
        raise CLIError(f'--foxglove: {exc}') from None
    for topic in player.topics:
        server.add_topic(topic, bag.topics[topic].type)
    player.sink = ReplaySink(server)
    print(f'erva replay: Foxglove: open {server.url} (layout config/foxglove_layout.json); '
          'playing once a viewer subscribes (Ctrl-C to stop)', file=sys.stderr, flush=True)
    # A viewer subscribes its panels' topics together: play once none came for SETTLE_S.
    last, since = 0, time.monotonic()
    while not should_stop():
        seen = server.stats()['subscriptions']
        if seen != last:
            last, since = seen, time.monotonic()
        elif seen and time.monotonic() - since > SETTLE_S:
            break
        time.sleep(0.02)
    return server


def main(args) -> int:
    from erva_ros.core.bag.reader import open_bag

    if args.delay < 0 or args.wait_for_subscribers < 0:
        raise CLIError('--delay and --wait-for-subscribers must be >= 0')
    what_if = (args.alpha1, args.alpha2, args.settings, args.duration)
    if not args.drive_plant and any(v is not None for v in what_if):
        raise CLIError('--alpha1/2, --settings and --duration need --drive-plant')
    if args.controller is not None and not (args.drive_plant or args.reevaluate):
        raise CLIError('--controller needs --drive-plant or --reevaluate')
    if args.drive_plant and args.reevaluate:
        raise CLIError('choose one of --drive-plant and --reevaluate')
    if (args.drive_plant or args.reevaluate) and (args.loop or args.clock or args.topics):
        raise CLIError('--drive-plant and --reevaluate do not publish: drop --loop, --clock '
                       'and --topics')
    if args.max_commands is not None and (not args.reevaluate or args.max_commands < 1):
        raise CLIError('--max-commands needs --reevaluate and a positive count')
    if args.foxglove is not None:
        if args.drive_plant or args.reevaluate:
            raise CLIError('--foxglove serves what is played: drop --drive-plant/--reevaluate')
        from erva_ros.session.foxglove_process import check_address
        check_address(args.foxglove)
    bag = open_bag(args.bag)
    if args.reevaluate:
        return _reevaluate(args, bag)
    if args.drive_plant:
        if os.path.exists(args.record_dir) and not os.path.isdir(args.record_dir):
            raise CLIError(f'--record-dir {args.record_dir} is not a directory')
        return _drive_plant(args, bag)
    return _play(args, bag)
