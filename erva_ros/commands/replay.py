"""``erva replay``: publish a session bag with its original timing, or drive a what-if run."""

import argparse
import contextlib
import os
import sys

from erva_ros.commands._common import (add_json_option, add_params_option, bag_warner,
                                       positive_float, positive_int, print_json)
from erva_ros.commands.run import FOXGLOVE_DEFAULT
from erva_ros.core.errors import CLIError
from erva_ros.core.progress import Progress

#: What `erva bag play` and `erva replay` print about pausing (also in --help).
PLAY_CONTROLS = """\
Pause and resume: on a terminal the space bar toggles (as ros2 bag play; off with
--disable-keyboard-controls); from another process kill -USR1 PID pauses and
kill -USR2 PID resumes.  While paused nothing is published and the playback time (and
/clock) stands still; the schedule continues where it stopped.  Ctrl-C stops."""


COMMAND = 'replay'
HELP = 'play a bag like "ros2 bag play", or drive a fresh plant with its road (--drive-plant)'
DESCRIPTION = """\
Play (default; also `erva bag play`): publishes every recorded message at its
original time offset (receive times, scaled by --rate), as raw CDR from publishers
offering the recorded QoS, like "ros2 bag play" (same options where they overlap).
Nodes and tools subscribed to the topics see the session again.  --clock publishes
the playback time on /clock (then a recorded /clock is not replayed).  Uses
$ROS_DOMAIN_ID.  --foxglove [HOST:]PORT also serves the played messages to Foxglove
as `erva run --foxglove` does (same channels, schemas and layout; log times as
recorded); playing starts once a viewer subscribes.

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
  erva replay bags/sample --loop --clock 100 --start-offset 1.5
  erva replay bags/sample --reevaluate
  erva replay bags/sample --drive-plant --controller skyhook

""" + PLAY_CONTROLS


def add_play_arguments(parser) -> None:
    """Add BAG and the options of playing, named as ``ros2 bag play``'s (rosbag2 Jazzy)."""
    parser.add_argument('bag', metavar='BAG', help='bag directory or .mcap file')
    parser.add_argument('-s', '--storage', choices=('mcap',), default=None,
                        help='storage of the bag (only mcap; default: detected)')
    parser.add_argument('--read-ahead-queue-size', type=positive_int, default=None,
                        metavar='N', help='accepted as ros2 bag play\'s, but changes nothing '
                                          'here: the player reads the bag chunk by chunk as '
                                          'it plays, with no queue of messages to size')
    parser.add_argument('-r', '--rate', type=positive_float, default=1.0,
                        help='playback speed factor (default 1 = original timing)')
    parser.add_argument('--topics', nargs='+', metavar='TOPIC', default=None,
                        help='play these topics (with --regex: these and the matching ones; '
                             'default: all)').completer = _bag_topics
    parser.add_argument('-e', '--regex', default='', metavar='REGEX',
                        help='play the topics whose whole name matches REGEX')
    parser.add_argument('-x', '--exclude-regex', default='', metavar='REGEX',
                        help='do not play the topics whose whole name matches REGEX')
    parser.add_argument('--exclude-topics', nargs='+', metavar='TOPIC', default=(),
                        help='do not play these topics').completer = _bag_topics
    parser.add_argument('-l', '--loop', action='store_true', help='play again until Ctrl-C')
    parser.add_argument('-m', '--remap', nargs='+', metavar='OLD:=NEW', default=(),
                        help='publish recorded topic OLD as NEW')
    parser.add_argument('--clock', nargs='?', type=positive_float, const=40.0, default=None,
                        metavar='HZ', help='publish the playback time on /clock at HZ '
                                           '(default 40 when given without a value)')
    parser.add_argument('-d', '--delay', type=float, default=0.0, metavar='S',
                        help='wait S seconds before the first message (discovery)')
    parser.add_argument('--start-offset', type=_start_offset, default=0.0, metavar='S|loop',
                        help='start S seconds after the bag\'s first message (default 0); '
                             'loop: at the loop\'s first sample (a bag of erva run: its '
                             'bring-up left out; erva bag info shows where)')
    parser.add_argument('--playback-duration', type=float, default=None, metavar='S',
                        help='play only S seconds of the bag from the start point')
    parser.add_argument('-p', '--start-paused', action='store_true',
                        help='start paused (space or kill -USR2 resumes)')
    parser.add_argument('--disable-keyboard-controls', action='store_true',
                        help='do not read the space bar from the terminal')
    parser.add_argument('--wait-for-all-acked', type=int, default=5000, metavar='MS',
                        help='at the end, wait up to MS ms until every reliable subscriber '
                             'acknowledged every message (default 5000)')
    parser.add_argument('--wait-for-subscribers', type=float, default=0.0, metavar='S',
                        help='wait up to S seconds until every topic (and /clock with --clock) '
                             'has a subscriber')
    parser.add_argument('--foxglove', nargs='?', const=FOXGLOVE_DEFAULT, default=None,
                        metavar='[HOST:]PORT',
                        help='also serve the messages to Foxglove on this address (default '
                             f'{FOXGLOVE_DEFAULT}: this machine only; PORT 0 = any free '
                             'port); playing starts when a viewer subscribes')


#: --start-offset's word for the loop's first sample (erva run marks it in the bag).
LOOP_START = 'loop'


def _start_offset(text: str):
    """Parse --start-offset: seconds, or 'loop' (argparse type)."""
    if text == LOOP_START:
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r}: seconds (>= 0) or {LOOP_START}') from None


def resolve_start_offset(value, bag) -> float:
    """Return --start-offset in seconds; 'loop' is where the bag marks sample 0."""
    if value != LOOP_START:
        return value
    from erva_ros.core.bag.session_check import loop_offset_s
    offset = loop_offset_s(bag)
    if offset is None:
        raise CLIError(f'--start-offset loop: {bag.path} does not mark the loop\'s first '
                       'sample (erva run marks it); give seconds instead')
    return offset


def _bag_topics(prefix, parsed_args, **_):
    """Complete a topic name from the bag on the command line (shell completion)."""
    from erva_ros.core.bag.reader import open_bag
    try:
        return [t for t in open_bag(parsed_args.bag).topics if t.startswith(prefix)]
    except Exception:  # noqa: BLE001 -- no bag (yet): no candidates
        return []


def add_arguments(parser):
    add_play_arguments(parser)
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
    from erva_ros.session.bag.whatif import drive_plant
    from erva_ros.session.bag.bag_report import compute_report, load_session
    from erva_ros.session.run.report import jsonable
    from erva_ros.core.bag.session import new_bag_dir
    from erva_ros.core.controllers import load_controller_settings
    from erva_ros.core.model.quarter_car import make_model
    from erva_ros.core.model.params import load_erva_params

    params = load_erva_params(args.params)
    settings = load_controller_settings(args.settings, {'controller': args.controller,
                                                        'alpha1': args.alpha1,
                                                        'alpha2': args.alpha2})
    name = settings.controller
    data = load_session(bag)
    before = compute_report(data)
    out_dir = new_bag_dir(args.record_dir, f'whatif-{name}')
    with _native_stdout_to_stderr():   # the plant and the controller: the recorded model
        result, meta = drive_plant(bag, out_dir, name, make_model(params, data.model),
                                   settings, session_extra={'alpha1': settings.alpha1,
                                                            'alpha2': settings.alpha2},
                                   duration_s=args.duration)
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
    from erva_ros.session.bag.reevaluate import controller_from_session, reevaluate, summarize
    from erva_ros.session.bag.bag_report import load_session
    from erva_ros.session.run.report import jsonable
    from erva_ros.core.controllers import make_controller
    from erva_ros.core.model.quarter_car import make_model

    params, settings = controller_from_session(bag, args.controller)
    data = load_session(bag)
    with _native_stdout_to_stderr():
        controller = make_controller(settings.controller, make_model(params, data.model),
                                     settings)
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


def _play(args, bag, warnings) -> int:
    import signal
    import time

    from erva_ros.ros.context import RosContext
    from erva_ros.ros.replay import Player

    from erva_ros.session.bag.play_controls import PlayControls

    prog = getattr(args, 'prog', 'erva replay')
    server = None
    stop = {'flag': False}
    ros = RosContext()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.update(flag=True))
    try:
        node = ros.create_node('erva_replay')
        player = Player(node, bag, rate=args.rate, topics=args.topics, loop=args.loop,
                        clock_hz=args.clock or 0.0, start_offset_s=args.start_offset,
                        playback_duration_s=args.playback_duration,
                        start_paused=args.start_paused, regex=args.regex,
                        exclude_topics=args.exclude_topics,
                        exclude_regex=args.exclude_regex, remap=_remaps(args.remap))
        if args.foxglove is not None:
            server = _serve(args.foxglove, bag, player, lambda: stop['flag'])
        if args.wait_for_subscribers > 0:
            player.wait_for_subscribers(args.wait_for_subscribers)
        player.on_start = lambda reach: [print(f'{prog}: {line}', file=sys.stderr, flush=True)
                                         for line in reach.start_lines()]
        end = time.monotonic() + max(0.0, args.delay)
        while time.monotonic() < end and not stop['flag']:
            time.sleep(0.02)
        with PlayControls(player, prog, keyboard=not args.disable_keyboard_controls):
            stats = player.run(lambda: stop['flag'])
        stats['acknowledged'] = player.finish(args.wait_for_all_acked / 1000.0)
        if server is not None:
            stats['foxglove'] = server.stats()
    finally:
        if server is not None:
            server.close()
        ros.close()
    late = player.reach.end_line()
    if late:
        print(f'{prog}: {late}', file=sys.stderr)
    stats['warnings'] = warnings + ([late] if late else [])
    if args.json:
        from erva_ros.session.run.report import jsonable
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

    from erva_ros.session.bag.bag_report import guess_namespace
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


def _remaps(items):
    """Return {old: new} of ``--remap OLD:=NEW ...``; CLIError for a malformed one."""
    out = {}
    for item in items or ():
        old, sep, new = item.partition(':=')
        if not sep or not old.startswith('/') or not new.startswith('/'):
            raise CLIError(f'--remap {item!r}: give /old/topic:=/new/topic')
        out[old] = new
    return out


def check_play_options(args, bag=None) -> None:
    """Raise CLIError for play options out of range (before anything starts)."""
    for name in ('delay', 'wait_for_subscribers', 'start_offset'):
        value = getattr(args, name)
        if value == LOOP_START:     # resolved once the bag is open
            continue
        if not value >= 0 or value == float('inf'):
            raise CLIError(f'--{name.replace("_", "-")} {value:g} must be >= 0 and finite')
    if args.playback_duration is not None and not args.playback_duration > 0:
        raise CLIError(f'--playback-duration {args.playback_duration:g} must be positive')
    if args.wait_for_all_acked < 0:
        raise CLIError(f'--wait-for-all-acked {args.wait_for_all_acked} must be >= 0 ms')
    _remaps(args.remap)
    if bag is not None:
        args.start_offset = resolve_start_offset(args.start_offset, bag)
    if bag is not None and args.start_offset > bag.duration_s:
        raise CLIError(f'--start-offset {args.start_offset:g} is past the end of the bag '
                       f'({bag.duration_s:.3f} s long)')


def play_main(args, prog: str) -> int:
    """Play a bag (`erva bag play`, `erva replay` without a what-if)."""
    from erva_ros.core.bag.playback import select_topics
    from erva_ros.core.bag.reader import open_bag

    args.prog = prog
    check_play_options(args)
    if args.read_ahead_queue_size is not None:
        print(f'{prog}: note: --read-ahead-queue-size {args.read_ahead_queue_size} changes '
              'nothing: the bag is read chunk by chunk as it plays', file=sys.stderr)
    if args.foxglove is not None:
        from erva_ros.session.run.foxglove_process import check_address
        check_address(args.foxglove)
    warnings = []
    bag = open_bag(args.bag, bag_warner(prog, warnings))
    check_play_options(args, bag)
    # A bad selection: one line before any node starts.
    played = select_topics(bag.topics, args.topics or (), args.regex, args.exclude_topics,
                           args.exclude_regex)
    unknown = sorted(set(_remaps(args.remap)) - set(played))
    if unknown:
        raise CLIError(f'--remap {", ".join(unknown)}: not a played topic (the played ones: '
                       f'{", ".join(played)})')
    return _play(args, bag, warnings)


def main(args) -> int:
    from erva_ros.core.bag.reader import open_bag

    what_if = (args.alpha1, args.alpha2, args.settings, args.duration)
    if not args.drive_plant and any(v is not None for v in what_if):
        raise CLIError('--alpha1/2, --settings and --duration need --drive-plant')
    if args.controller is not None and not (args.drive_plant or args.reevaluate):
        raise CLIError('--controller needs --drive-plant or --reevaluate')
    if args.max_commands is not None and (not args.reevaluate or args.max_commands < 1):
        raise CLIError('--max-commands needs --reevaluate and a positive count')
    if not (args.drive_plant or args.reevaluate):
        return play_main(args, 'erva replay')
    if args.drive_plant and args.reevaluate:
        raise CLIError('choose one of --drive-plant and --reevaluate')
    playing = (args.loop, args.clock, args.topics, args.regex, args.exclude_regex,
               args.exclude_topics, args.remap, args.start_offset, args.start_paused,
               args.playback_duration is not None, args.delay, args.wait_for_subscribers,
               args.read_ahead_queue_size is not None)
    if any(playing):
        raise CLIError('--drive-plant and --reevaluate do not publish: drop the play options '
                       '(--loop, --clock, --topics, --start-offset, ...)')
    if args.foxglove is not None:
        raise CLIError('--foxglove serves what is played: drop --drive-plant/--reevaluate')
    bag = open_bag(args.bag, bag_warner('erva replay'))
    if args.reevaluate:
        return _reevaluate(args, bag)
    if os.path.exists(args.record_dir) and not os.path.isdir(args.record_dir):
        raise CLIError(f'--record-dir {args.record_dir} is not a directory')
    return _drive_plant(args, bag)
