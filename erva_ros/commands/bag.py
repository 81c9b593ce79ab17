"""``erva bag``: inspect, repair and benchmark session bags (rosbag2 directories with MCAP)."""

import math
import os

from erva_ros.commands._common import (add_json_option, positive_float, positive_int,
                                       print_json)
from erva_ros.core.errors import CLIError
from erva_ros.core.progress import Progress

COMMAND = 'bag'
HELP = ('session bags: info (topics, counts, session), repair (after a crash), bench '
        '(recorder), soak (loss under load); play, record, reindex as ros2 bag')
DESCRIPTION = """\
Session bags are rosbag2 directories (metadata.yaml, bag format version 9) holding one
MCAP file (profile ros2, ros2msg schemas, cdr messages), as ros2 bag record writes
them: ros2 bag info/play and Foxglove open them directly.

  erva bag info BAG      as ros2 bag info (-t, -v): topics, types, counts, duration,
                         and the session metadata (scenario, parameters, seed,
                         controller, version, host, ...)
  erva bag repair BAG    after the recorder was killed: rebuild the MCAP summary and
                         index from every flushed chunk and write metadata.yaml
  erva bag bench         recorder throughput and the latency it adds to a 50 Hz loop
  erva bag soak          many `erva run` sessions on a loaded machine: anything lost?

The verbs of ros2 bag (rosbag2 Jazzy), with its options where they overlap:

  erva bag play BAG      = erva replay BAG (-r, --topics, -e, -x, -l, --clock, -d,
                         --start-offset, -p, --playback-duration, -m, ...); space
                         pauses, kill -USR1/-USR2 pause/resume; says how many
                         subscribers each topic had and what went out before they matched
  erva bag record        record a running graph with erva's recorder (TOPIC ..., -o,
                         --topics, -a, -e, --exclude-*, --use-sim-time, --custom-data,
                         ...); says what it lacks by the publishers' sequence numbers
  erva bag reindex BAG   = erva bag repair BAG

BAG is a bag directory or its .mcap file."""

#: Session values longer than this are shortened in the text output (see --json).
LONG_VALUE = 100


def add_arguments(parser):
    sub = parser.add_subparsers(dest='bag_command', metavar='ACTION')
    sub.required = True
    p = sub.add_parser('info', help='topics, counts, duration and session metadata of a bag',
                       description='Show what a bag holds, like "ros2 bag info" (its layout '
                                   'and time format; times in local time), plus each '
                                   'topic\'s rate, the files of a split bag and the session '
                                   'metadata the recorder stored.')
    p.add_argument('bag', metavar='BAG', help='bag directory or .mcap file')
    p.add_argument('-s', '--storage', choices=('mcap',), default=None,
                   help='storage of the bag (only mcap; default: detected)')
    p.add_argument('-t', '--topic-name', action='store_true',
                   help='only the topic names, one per line (as ros2 bag info -t)')
    p.add_argument('-v', '--verbose', action='store_true',
                   help='as ros2 bag info -v, the recorded services with their request and '
                        'response counts (erva records none: "Service: 0"); and every '
                        'session value in full')
    add_json_option(p)
    p = sub.add_parser('repair', aliases=['reindex'],
                       help='make a bag whose recorder died complete again (alias: reindex, '
                            'as ros2 bag reindex)',
                       description='Copy every readable record (all flushed chunks) of a '
                                   'bag into a new, indexed MCAP file and write '
                                   'metadata.yaml; the original file is kept as '
                                   '<file>.orig unless --no-backup.  --out DIR writes the '
                                   'repaired bag there instead.')
    p.add_argument('bag', metavar='BAG', help='bag directory or .mcap file')
    p.add_argument('-s', '--storage', choices=('mcap',), default=None,
                   help='storage of the bag (only mcap; default: detected)')
    p.add_argument('--no-backup', action='store_true',
                   help='do not keep the damaged original as <file>.orig')
    p.add_argument('--out', metavar='DIR', default=None,
                   help='write the repaired bag to DIR (new or empty) and leave BAG as it is, '
                        'e.g. when BAG\'s disk is full')
    add_json_option(p)
    p = sub.add_parser('bench', help='recorder throughput and added control-loop latency',
                       description='Run a 50 Hz echo control loop (state -> command '
                                   'latency p50/p99/max) while the recorder is started and '
                                   'stopped in alternating windows, then flood the recorder '
                                   'with states to measure the message rate it sustains.  '
                                   'Uses $ROS_DOMAIN_ID, local discovery only.')
    p.add_argument('--window', type=positive_float, default=10.0, metavar='S',
                   help='seconds of each recorder-off / recorder-on window (default 10)')
    p.add_argument('--pairs', type=positive_int, default=3,
                   help='number of off/on window pairs (default 3)')
    p.add_argument('--contract-rates', default='250,500,1000', metavar='HZ[,HZ...]',
                   help='rates at which the whole contract (8 topics) is published '
                        '(default 250,500,1000; live: 50)')
    p.add_argument('--flood-rates', default='1000,0', metavar='HZ[,HZ...]',
                   help='single-topic flood rates in msg/s, 0 = as fast as possible '
                        '(default 1000,0)')
    p.add_argument('--recorder-nice', type=int, default=None, metavar='N',
                   help='recorder CPU niceness 0..19 (default: the node\'s, 10)')
    p.add_argument('--flood-duration', type=positive_float, default=4.0, metavar='S',
                   help='seconds of each throughput run (default 4)')
    add_json_option(p)
    _add_soak(sub)
    _add_rosbag2_verbs(sub)


def _add_soak(sub) -> None:
    import os
    p = sub.add_parser('soak', help='consecutive erva run sessions under load: messages lost?',
                       description='Run N consecutive `erva run --record` sessions while K '
                                   'busy processes load the cores, read every bag back '
                                   '(mcap\'s reader) and compare each topic with what the '
                                   'nodes published.  Exit status 1 if any message is '
                                   'missing or any run failed.  Uses $ROS_DOMAIN_ID.')
    p.add_argument('--runs', type=positive_int, default=30, help='sessions (default 30)')
    p.add_argument('--duration', type=positive_float, default=5.0, metavar='S',
                   help='scenario length of each session (default 5 s)')
    p.add_argument('--busy', type=int, default=os.cpu_count() or 1, metavar='K',
                   help='busy-looping processes beside the runs (default: one per core, '
                        f'{os.cpu_count()}); 0 for a quiet machine')
    p.add_argument('--ecu', choices=('none', 'virtual'), default='none',
                   help='virtual: the hardware-in-the-loop session (erva run --ecu virtual)')
    p.add_argument('--live', metavar='FILE', default=None,
                   help='live parameter file for the runs (erva run --live), e.g. a smaller '
                        'publisher_history_s to see what the writers\' history buys')
    p.add_argument('--keep-bags', metavar='DIR', default=None,
                   help='keep the bags under DIR (default: deleted after each run)')
    p.add_argument('--rss-every', type=positive_float, default=None, metavar='S',
                   help='sample each process\'s resident memory (VmRSS) every S seconds and '
                        'report its growth (the trace is in --json)')
    p.add_argument('--rss-settle', type=float, default=60.0, metavar='S',
                   help='with --rss-every: count the growth from S seconds into each run '
                        '(start-up allocations before; default 60)')
    add_json_option(p)


def _add_rosbag2_verbs(sub) -> None:
    """Add `erva bag play` and `erva bag record`, named and optioned as ros2 bag's."""
    from erva_ros.commands.replay import add_play_arguments, PLAY_CONTROLS
    import argparse
    p = sub.add_parser('play', help='play a bag, as ros2 bag play (= erva replay)',
                       description='Publish a bag\'s messages with their original timing, '
                                   'as "ros2 bag play" does, with its options where they '
                                   'overlap (the same as `erva replay BAG`).  Uses '
                                   '$ROS_DOMAIN_ID.\n\n' + PLAY_CONTROLS,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    add_play_arguments(p)
    add_json_option(p)
    _add_record(sub)


def _add_record(sub) -> None:
    from erva_ros.commands.run import add_bag_split_arguments
    from erva_ros.session.bag.bag_record import STORAGE_KEYS
    p = sub.add_parser('record', help='record a running graph, as ros2 bag record',
                       description='Record topics of the running ROS graph into a new bag '
                                   '(rosbag2 layout, MCAP) with erva\'s recorder '
                                   '(recorder_node, its own process), as "ros2 bag record" '
                                   'does, with its options where they overlap.  Without '
                                   'topics (TOPIC ... or --topics), -a or -e: the topics '
                                   '`erva run` records.  '
                                   '-a and -e choose among the topics the graph shows '
                                   'after --discovery-wait (once: as ros2 bag record '
                                   '--no-discovery).  Ctrl-C (or --duration) stops: the '
                                   'recorder takes what was delivered to it (up to 5 s '
                                   'while publishers go on), closes the bag, which is '
                                   'then read back and counted; the publishers\' sequence '
                                   'numbers say what it lacks (sent before it matched a '
                                   'publisher, holes).  Uses $ROS_DOMAIN_ID.')
    p.add_argument('-o', '--output', metavar='DIR', default=None,
                   help='bag directory to create (default: bags/<UTC time>_record)')
    p.add_argument('-s', '--storage', choices=('mcap',), default='mcap',
                   help='storage (only mcap, the default)')
    chosen = p.add_mutually_exclusive_group()
    chosen.add_argument('topics_positional', nargs='*', metavar='TOPIC', default=[],
                        help='record these topics (as --topics; ros2 bag record takes them '
                             'so too)').completer = _known_topics
    chosen.add_argument('--topics', nargs='+', metavar='TOPIC', default=[],
                        help='record these topics (relative names: under /)'
                        ).completer = _known_topics
    p.add_argument('-a', '--all', action='store_true', dest='all_topics',
                   help='record every topic the graph shows (except hidden ones)')
    p.add_argument('--all-topics', action='store_true', dest='all_topics',
                   help='the same as --all (erva records no services)')
    p.add_argument('-e', '--regex', default='', metavar='REGEX',
                   help='record the topics containing a match of REGEX')
    p.add_argument('--exclude-regex', default='', metavar='REGEX',
                   help='do not record the topics containing a match of REGEX')
    p.add_argument('--exclude-topics', nargs='+', metavar='TOPIC', default=[],
                   help='do not record these topics').completer = _known_topics
    p.add_argument('--include-hidden-topics', action='store_true',
                   help='-a and -e also choose hidden topics')
    p.add_argument('--use-sim-time', action='store_true',
                   help='log times from /clock (the recorder\'s use_sim_time)')
    p.add_argument('--node-name', default='erva_bag_recorder',
                   help='name of the recorder node (default erva_bag_recorder)')
    p.add_argument('--custom-data', nargs='+', metavar='KEY=VALUE', default=[],
                   help='stored with the bag (metadata.yaml custom_data and the session)')
    p.add_argument('--storage-config-file', metavar='FILE', default=None,
                   help='MCAP writer options as rosbag2_storage_mcap takes them (here: '
                        f'{", ".join(STORAGE_KEYS)})')
    p.add_argument('--duration', type=positive_float, default=None, metavar='S',
                   help='stop after S seconds (default: at Ctrl-C)')
    add_bag_split_arguments(p, short=True)
    p.add_argument('--discovery-wait', type=positive_float, default=2.0, metavar='S',
                   help='-a, -e: look at the graph this long before choosing (default 2)')
    add_json_option(p)


def _known_topics(prefix, **_):
    """Complete a topic of the erva contract (shell completion; no graph is asked)."""
    from erva_ros.core import topics
    return [t for t in sorted(topics.TOPIC_TYPES) if t.startswith(prefix)]


def _play(args) -> int:
    from erva_ros.commands.replay import play_main
    return play_main(args, 'erva bag play')


def _record(args) -> int:
    import shlex
    import signal
    import sys

    from erva_ros.commands.run import bag_split_parameters
    from erva_ros.core import topics as contract
    from erva_ros.core.bag.session import new_bag_dir
    from erva_ros.session.bag import bag_record
    from erva_ros.session.run.recording import record_topics

    custom = {}
    for item in args.custom_data:
        key, sep, value = item.partition('=')
        if not sep or not key:
            raise CLIError(f'--custom-data {item!r}: give KEY=VALUE')
        custom[key] = value
    opts = bag_record.RecordOptions(
        output=args.output or new_bag_dir('bags', 'record'),
        topics=args.topics or args.topics_positional,
        all_topics=args.all_topics, regex=args.regex, exclude_topics=args.exclude_topics,
        exclude_regex=args.exclude_regex, include_hidden=args.include_hidden_topics,
        node_name=args.node_name, use_sim_time=args.use_sim_time, custom_data=custom,
        storage={**bag_record.storage_parameters(args.storage_config_file),
                 **bag_split_parameters(args)},
        duration_s=args.duration, discovery_s=args.discovery_wait,
        command=' '.join(shlex.quote(a) for a in ['erva', 'bag', *sys.argv[2:]]))
    if args.output is None:
        os.makedirs('bags', exist_ok=True)
    bag_record.check_output(opts.output)
    default = [t if t.startswith('/') else f'{contract.NAMESPACE}/{t}'
               for t in record_topics(hil=True)]
    graph = bag_record.graph_topics(opts.discovery_s) if opts.needs_graph else {}
    chosen = bag_record.choose_topics(opts, graph, default)
    stop = {'flag': False}
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.update(flag=True))
    result = bag_record.record(opts, chosen, lambda: stop['flag'],
                               lambda line: print(f'erva bag record: {line}',
                                                  file=sys.stderr, flush=True))
    missing = bag_record.missing_line(result)
    for line in result.get('warnings', []):
        print(f'erva bag record: warning: {line}', file=sys.stderr)
    if missing:
        print(f'erva bag record: {missing}', file=sys.stderr)
    if args.json:
        print_json(result)
    elif 'error' in result:
        print(f'erva bag record: the recorder wrote no readable bag: {result["error"]}')
    else:
        print(f'{result["bag"]}: {result["messages"]} messages on {len(result["counts"])} '
              f'topics, {result["duration_s"]:.3f} s (stopped by {result["stopped_by"]})')
        for topic, n in sorted(result['counts'].items()):
            lack = result['missing'].get(topic)
            print(f'  {topic}: {n}' + ('' if lack is None else
                                       f' (not in the bag: {lack["before_first"]} before '
                                       f'this recorder matched the publisher, '
                                       f'{lack["holes"]} in between)'
                                       if lack['before_first'] + lack['holes'] else ''))
    if result.get('recorder_log'):
        print(f'erva bag record: recorder_node exited {result["exit_status"]}:\n'
              f'{result["recorder_log"]}', file=sys.stderr)
    return 0 if result['exit_status'] == 0 and 'error' not in result else 1


def _soak(args) -> int:
    from erva_ros.session.bench import soak
    if args.busy < 0:
        raise CLIError(f'--busy {args.busy}: give 0 or more processes')
    import os
    run_args = ['--ecu', args.ecu] if args.ecu != 'none' else []
    if args.live:
        if not os.path.isfile(args.live):
            raise CLIError(f'--live {args.live}: no such file')
        run_args += ['--live', os.path.abspath(args.live)]
    if not args.rss_settle >= 0:
        raise CLIError(f'--rss-settle {args.rss_settle}: give 0 or more seconds')
    progress = Progress('erva bag soak: runs', args.runs, enabled=not args.json)
    result = soak.soak(args.runs, args.duration, args.busy, run_args, args.keep_bags,
                       progress=lambda line: progress.advance(note=line),
                       rss_every_s=args.rss_every or 0.0, rss_settle_s=args.rss_settle)
    progress.close()
    if args.json:
        print_json(result)
    else:
        print(f'{result["runs"]} runs x {result["duration_s"]:g} s'
              f'{(" " + " ".join(run_args)) if run_args else ""}, '
              f'{result["busy_processes"]} busy '
              f'processes on {result["cores"]} cores ({result["wall_s"]:.0f} s)')
        print(f'  messages published {result["published"]}, in the bags {result["in_bags"]}, '
              f'lost {result["lost"]} ({result["runs_with_loss"]} runs with a loss)')
        print(f'  runs failed (exit status != 0): {result["runs_failed"]}')
        if args.rss_every:
            _print_rss(result)
        for i, r in enumerate(result['per_run'], 1):
            if r['exit_status'] != 0 or r.get('lost'):
                print(f'  run {i}: exit {r["exit_status"]}; '
                      + '; '.join(r.get('errors') or [r.get('error', '')]))
    return 1 if result['lost'] or result['runs_failed'] else 0


def _print_rss(result) -> None:
    """Print each process's resident memory over the run with the largest growth."""
    growth = result.get('rss_growth_kb') or {}
    if not growth:
        print('  RSS: no samples (no /proc?)')
        return
    print(f'  RSS (VmRSS every {result["per_run"][0]["rss"]["every_s"]:g} s; growth from '
          f'{result["per_run"][0]["rss"]["settle_s"]:g} s into a run to its end, the '
          f'largest of the runs):')
    for name in sorted(growth):
        worst = max((r['rss']['processes'][name] for r in result['per_run']
                     if name in (r.get('rss') or {}).get('processes', {})),
                    key=lambda p: p['growth_kb'])
        print(f'    {name:<22} {worst["first_kb"] / 1024:8.1f} MiB at {worst["from_s"]:g} s '
              f'-> {worst["last_kb"] / 1024:8.1f} MiB {worst["span_s"]:g} s later: '
              f'{worst["growth_kb"] / 1024:+.2f} MiB (max {worst["max_kb"] / 1024:.1f} MiB)')


def _size(n: int) -> str:
    for unit in ('B', 'KiB', 'MiB', 'GiB'):
        if n < 1024 or unit == 'GiB':
            return f'{n:.1f} {unit}' if unit != 'B' else f'{n} B'
        n /= 1024.0
    return f'{n} B'


def _info(args) -> int:
    from erva_ros.core.bag.metadata import format_duration, format_time_point
    from erva_ros.core.bag.reader import open_bag
    info = open_bag(args.bag).info()
    if args.json:
        print_json(info)
        return 0
    if args.topic_name and args.verbose:       # as ros2 bag info
        print("Warning! You have set both the '-t' and '-v' parameters. The '-t' parameter "
              'will be ignored.')
    elif args.topic_name:
        for t in info['topics']:
            print(t['name'])
        return 0
    files = info['files']
    names = [os.path.basename(f['path']) for f in files]
    if len(files) > 1:    # a split bag: each file's share
        names = [f'{n}  ({f["message_count"]} messages, {f["duration_s"]:.3f} s'
                 f'{"" if f["complete"] else ", not closed properly"})'
                 for n, f in zip(names, files)]
        names.insert(0, f'{len(files)} files')
    start, end = info['start_ns'], info['end_ns']
    rows = [('Files', ('\n' + ' ' * 19).join(names)),
            ('Bag size', _size(info['size_bytes'])),
            ('Storage id', f'mcap (profile {info["profile"]}, {info["library"]})'),
            ('ROS Distro', info['ros_distro'] or 'unknown'),
            ('Duration', f'{format_duration(end - start)}s' if start is not None
             else 'unknown'),
            ('Start', format_time_point(start)),
            ('End', format_time_point(end)),
            ('Messages', str(info['message_count']))]
    if info['loop_offset_s'] is not None:     # erva run: where the loop's sample 0 is
        rows.append(('Loop start', f'{info["loop_offset_s"]:.3f} s into the bag, sample 0 '
                                   f'stamped {info["loop_start_ns"]} (bag play '
                                   '--start-offset loop)'))
    for key, value in rows:
        print(f'{key + ":":<19}{value}')
    for i, t in enumerate(info['topics']):
        rate = f'{t["rate_hz"]:.2f} Hz' if t['rate_hz'] else 'unknown'
        print(f'{"Topic information:" if i == 0 else "":<19}Topic: {t["name"]} | Type: '
              f'{t["type"]} | Count: {t["count"]} | Rate: {rate} | Serialization Format: '
              f'{t["serialization_format"]}')
    if not info['topics']:
        print('Topic information: ')
    print(f'{"Service:":<19}0')        # erva records no service events
    print('Service information: ')
    for i, (key, value) in enumerate(sorted(info['session'].items())):
        lines = value.splitlines() or ['']
        if args.verbose:      # in full; a multi-line value (the params file) indented
            value = ('\n' + ' ' * (21 + len(key))).join(lines)
        elif len(lines) > 1:
            value = f'{lines[0]} ... ({len(lines)} lines; see -v or --json)'
        elif len(value) > LONG_VALUE:
            value = value[:LONG_VALUE] + f'... ({len(value)} chars; see -v or --json)'
        print(f'{"Session:" if i == 0 else "":<19}{key}: {value}')
    for w in info['warnings']:
        print(f'warning: {w}')
    return 0


def _repair(args) -> int:
    from erva_ros.core.bag.repair import repair_bag
    if args.out is not None and args.no_backup:
        raise CLIError('--no-backup applies to a repair in place; --out leaves BAG untouched')
    result = repair_bag(args.bag, keep_original=not args.no_backup, out_dir=args.out)
    if args.json:
        print_json(result)
        return 0
    span = ''
    if result['start_ns'] is not None:
        span = f', {(result["end_ns"] - result["start_ns"]) * 1e-9:.3f} s'
    print(f'{result["bag"]}: {result["action"]}')
    print(f'recovered {result["messages"]} messages on {len(result["topics"])} topics{span}')
    if result['stopped_at']:
        print(f'the damaged file ended with: {result["stopped_at"]}')
    for original in result['originals']:
        print(f'original kept as {original}')
    return 0


def _bench(args) -> int:
    import sys

    from erva_ros.session.bench import recorder_bench as bench

    def rates(text, option, zero_ok):
        try:
            values = [float(x) for x in text.split(',') if x.strip()]
        except ValueError:
            raise CLIError(f'{option} {text!r}: give numbers like 1000,0') from None
        if any(not math.isfinite(r) or r < 0 or (r == 0 and not zero_ok) for r in values):
            raise CLIError(f'{option} must be ' + ('>= 0 (0 = as fast as possible)'
                                                   if zero_ok else 'positive'))
        return values
    if args.recorder_nice is not None:
        if not 0 <= args.recorder_nice <= 19:
            raise CLIError(f'--recorder-nice {args.recorder_nice} is outside 0..19')
        bench.RECORDER_PARAMS.append(f'nice:={args.recorder_nice}')
    result = bench.run(args.window, args.pairs, rates(args.flood_rates, '--flood-rates', True),
                       args.flood_duration,
                       rates(args.contract_rates, '--contract-rates', False),
                       progress=lambda s: print(f'erva bag bench: {s}', file=sys.stderr,
                                                flush=True))
    if args.json:
        from erva_ros.session.run.report import jsonable
        print_json(jsonable(result))
        return 0

    def row(name, p):
        return (f'{name:<34}{p["p50"]:8.3f}{p["p99"]:9.3f}{p["max"]:9.3f}'
                f'{p["samples"]:9d}')
    print('50 Hz echo control loop, recorder off/on in alternating windows '
          '(ms; shared 2-core machine)')
    print(f'{"":<34}{"p50":>8}{"p99":>9}{"max":>9}{"samples":>9}')
    for name, what in (('command', 'state stamp -> command published'),
                       ('round_trip', 'state stamp -> command received')):
        res = result[name]
        print(f'{what}:')
        print(row('  without recorder', res['without_recorder_ms']))
        print(row('  with recorder', res['with_recorder_ms']))
        a = res['added_ms']
        print(f'{"  added by recording":<34}{a["p50"]:8.3f}{a["p99"]:9.3f}{a["max"]:9.3f}')
    print('recording throughput, the whole contract (8 topics, keep-last 10 each)')
    for c in result['contract']:
        print(f'  at {c["rate_hz"]:>6g} Hz: published {c["published"]}, recorded '
              f'{c["recorded"]} ({c["recorded_per_s"]:.0f}/s), lost {c["lost"]}')
    print('recording throughput, one topic (sensor_msgs/JointState, keep-last 10)')
    for f in result['flood']:
        req = f'{f["requested_hz"]:g}/s' if f['requested_hz'] else 'max'
        print(f'  requested {req:>8}: published {f["published"]} '
              f'({f["published_per_s"]:.0f}/s), recorded {f["recorded"]} '
              f'({f["recorded_per_s"]:.0f}/s), lost {f["lost"]}')
    sustained = result['sustained_msgs_per_s']
    print(f'sustained without loss: {sustained:.0f} msg/s' if sustained else
          'sustained without loss: none of the rates')
    return 0


def main(args) -> int:
    handler = {'info': _info, 'repair': _repair, 'reindex': _repair, 'bench': _bench,
               'soak': _soak, 'play': _play, 'record': _record}[args.bag_command]
    return handler(args)
