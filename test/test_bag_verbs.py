"""`erva bag play / record / reindex` as a ROS user types them, start offset, pause, completion.

The options are checked against the names ``ros2 bag`` (rosbag2 Jazzy, ros2bag/verb/*.py)
gives them where the two overlap.  Playing, recording and pausing run over real DDS:
the recording is read back with the ``mcap`` library's reader, the paused player is
watched by a subscriber here -- counts and order, never timings.
"""

import json
import os
import pty
import queue
import shutil
import signal
import subprocess
import sys
import threading
import time

import pytest

from conftest import REPO, ros_env
from recorder_helpers import SpinningNode

SAMPLE = os.path.join(REPO, 'bags', 'sample')
#: ros2 bag play options (Jazzy) that erva bag play has too, with the same meaning.
ROS2_PLAY = ['-s', '--storage', '-r', '--rate', '--topics', '-e', '--regex', '-x',
             '--exclude-regex', '--exclude-topics', '-l', '--loop', '-m', '--remap', '--clock',
             '-d', '--delay', '--playback-duration', '-p', '--start-paused', '--start-offset',
             '--disable-keyboard-controls', '--wait-for-all-acked', '--read-ahead-queue-size']
#: ros2 bag record options (Jazzy) that erva bag record has too.
ROS2_RECORD = ['-o', '--output', '-s', '--storage', '--topics', '-a', '--all', '--all-topics',
               '-e', '--regex', '--exclude-regex', '--exclude-topics',
               '--include-hidden-topics', '--use-sim-time', '--node-name', '--custom-data',
               '--storage-config-file']
#: ros2 bag info options (Jazzy).
ROS2_INFO = ['-s', '--storage', '-t', '--topic-name', '-v', '--verbose']


def _subparser(parser, *path):
    import argparse
    for name in path:
        action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = action.choices[name]
    return parser


def _options(parser):
    return {s: a.dest for a in parser._actions for s in a.option_strings}


def test_bag_verbs_are_aliases_with_the_options_of_ros2_bag():
    from erva_ros.cli import build_parser
    parser = build_parser()
    play = _subparser(parser, 'bag', 'play')
    record, reindex = _subparser(parser, 'bag', 'record'), _subparser(parser, 'bag', 'reindex')
    assert set(ROS2_PLAY) <= set(_options(play)), set(ROS2_PLAY) - set(_options(play))
    assert set(ROS2_RECORD) <= set(_options(record)), \
        set(ROS2_RECORD) - set(_options(record))
    assert {'-s', '--storage'} <= set(_options(reindex))
    info = _subparser(parser, 'bag', 'info')
    assert set(ROS2_INFO) <= set(_options(info)), set(ROS2_INFO) - set(_options(info))
    assert reindex is _subparser(parser, 'bag', 'repair')          # one command, two names
    # `erva bag play` is `erva replay` playing: the same options, the same values.
    line = ['-r', '2', '-l', '-p', '--start-offset', '1.5', '--topics', '/erva/state',
            '-x', '/diag.*', '-m', '/erva/state:=/other', '-d', '0.5', '--clock', '20',
            '--playback-duration', '3', '--disable-keyboard-controls',
            '--wait-for-all-acked', '100', '-s', 'mcap']
    a = parser.parse_args(['bag', 'play', SAMPLE, *line])
    b = parser.parse_args(['replay', SAMPLE, *line])
    for dest in set(_options(play).values()) - {'help'}:
        assert getattr(a, dest) == getattr(b, dest), dest
    assert (a.rate, a.loop, a.start_paused, a.start_offset, a.playback_duration,
            a.delay, a.clock) == (2.0, True, True, 1.5, 3.0, 0.5, 20.0)
    a = parser.parse_args(['bag', 'record', '-o', 'x', '-a', '-e', 'erva', '--exclude-topics',
                           '/rosout', '--custom-data', 'car=test', '--use-sim-time'])
    assert (a.output, a.all_topics, a.regex, a.exclude_topics, a.custom_data,
            a.use_sim_time) == ('x', True, 'erva', ['/rosout'], ['car=test'], True)
    # Topics as positional arguments too (ros2 bag record takes them, deprecated), not both.
    a = parser.parse_args(['bag', 'record', '/erva/state', 'damping_cmd'])
    assert (a.topics_positional, a.topics) == (['/erva/state', 'damping_cmd'], [])
    with pytest.raises(SystemExit):
        parser.parse_args(['bag', 'record', '/erva/state', '--topics', '/erva/state'])
    a = parser.parse_args(['bag', 'reindex', SAMPLE])
    assert a.bag_command == 'reindex' and a._name == 'bag'


def test_topic_selection_and_playback_clock():
    from erva_ros.core.bag import BagError
    from erva_ros.core.bag.playback import PlaybackClock, select_topics
    bag = ['/diagnostics', '/erva/state', '/erva/damping_cmd', '/erva/road/preview']
    assert select_topics(bag) == sorted(bag)
    assert select_topics(bag, ['/erva/state'], regex='/erva/road/.*') == [
        '/erva/road/preview', '/erva/state']
    with pytest.raises(BagError, match='leaves nothing'):
        select_topics(bag, regex='/erva/road')         # a whole-name match, as rosbag2
    with pytest.raises(BagError, match='leaves nothing'):
        select_topics(bag, exclude_regex='/erva/.*', exclude_topics=['/diagnostics'])
    assert select_topics(bag, exclude_regex='/erva/(state|road/.*)') == [
        '/diagnostics', '/erva/damping_cmd']
    with pytest.raises(BagError, match=r'/nope not in the bag; it has /diagnostics'):
        select_topics(bag, ['/nope'])
    with pytest.raises(BagError, match="--regex '\\(' is not a regular expression"):
        select_topics(bag, regex='(')
    clock = PlaybackClock(1_000, rate=2.0, now=10.0)
    assert clock.bag_ns(10.5) == 1_000 + 1_000_000_000 and clock.due(1_000 + 10**9) == 10.5
    assert clock.pause(11.0) and not clock.pause(11.5)
    assert clock.bag_ns(20.0) == 1_000 + 2 * 10**9 and clock.due(5 * 10**9) is None
    assert clock.resume(30.0) and not clock.resume(31.0)
    assert clock.paused_s == 19.0
    assert clock.due(1_000 + 3 * 10**9) == 30.5     # the schedule continues where it stopped


def test_reach_counts_what_went_out_before_each_topics_last_subscriber_matched():
    from erva_ros.core.bag.playback import Reach
    reach = Reach(['/a', '/b', '/c'])
    reach.start({'/a': 0, '/b': 1, '/c': 0})
    lines = reach.start_lines()
    assert lines[0] == 'subscribers matched at the start: /a 0, /b 1, /c 0'
    assert lines[1].startswith('WARN no subscriber matched /a, /c (2 of 3 topics)')
    assert '--wait-for-subscribers' in lines[1] and reach.end_line() is None
    for i in range(10):   # /a matched from message 4, /b's second from 6, /c never
        reach.publish('/a', 0 if i < 4 else 1)
        reach.publish('/b', 1 if i < 6 else 2)
        reach.publish('/c', 0)
    got = {t: (r['unmatched'], r['before_last_match'], r['most'])
           for t, r in reach.as_dict().items()}
    assert got == {'/a': (4, 4, 1), '/b': (0, 6, 2), '/c': (10, 0, 0)}
    assert reach.end_line() == (
        'WARN of 30 messages, 14 went out with no subscriber matched, 10 before the last '
        'subscriber of their topic matched; a subscriber that matched late does not have '
        'them (/a 4 of 10, /b 6 of 10, /c 10 of 10)')


def test_missing_by_sequence_tells_only_where_one_publisher_numbers_the_topic():
    from types import SimpleNamespace as M
    from erva_ros.core.bag.sequences import Missing, missing_by_sequence
    msgs = [M(topic='/late', sequence=s) for s in (5, 6, 8, 9)] + \
        [M(topic='/two', sequence=s) for s in (1, 2, 1, 3)] + \
        [M(topic='/none', sequence=0)] + [M(topic='/whole', sequence=s) for s in (1, 2, 3)]
    assert missing_by_sequence(msgs) == {'/late': Missing(4, 4, 1), '/two': None,
                                         '/none': None, '/whole': Missing(3, 0, 0)}


def test_record_chooses_topics_as_ros2_bag_record():
    from erva_ros.core.errors import CLIError
    from erva_ros.session.bag.bag_record import choose_topics, RecordOptions
    graph = {'/erva/state': 'sensor_msgs/msg/JointState', '/rosout': 'rcl_interfaces/msg/Log',
             '/erva/_hidden': 'std_msgs/msg/String', '/other/road': 'std_msgs/msg/String'}
    default = ['/erva/state', '/erva/damping_cmd']

    def choose(**kw):
        return choose_topics(RecordOptions(output='x', **kw), graph, default)
    assert choose() == ['/erva/damping_cmd', '/erva/state']       # what erva run records
    assert choose(all_topics=True) == ['/erva/state', '/other/road', '/rosout']
    assert choose(all_topics=True, include_hidden=True)[0] == '/erva/_hidden'
    # -e: the topics containing a match; a relative name lies under /
    assert choose(regex='road|state', topics=['x/y']) == [
        '/erva/state', '/other/road', '/x/y']
    assert choose(all_topics=True, exclude_regex='^/ros', exclude_topics=['other/road']) \
        == ['/erva/state']
    with pytest.raises(CLIError, match='nothing to record'):
        choose(regex='nomatch')


def _one_line(proc, *needles):
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and all(n in lines[0] for n in needles), proc.stderr
    return lines[0]


def test_bad_play_and_record_options_are_one_line_before_anything_starts(erva, tmp_path):
    _one_line(erva('bag', 'play', SAMPLE, '--start-offset', 9),
              'erva bag: error: --start-offset 9 is past the end of the bag (3.980 s')
    _one_line(erva('replay', SAMPLE, '--start-offset', -1),
              'erva replay: error: --start-offset -1 must be >= 0')
    _one_line(erva('bag', 'play', SAMPLE, '--remap', 'a=b'), "--remap 'a=b'")
    _one_line(erva('bag', 'play', SAMPLE, '--topics', '/erva/state', '-m', '/erva/gen:=/g'),
              '--remap /erva/gen: not a played topic (the played ones: /erva/state)')
    _one_line(erva('bag', 'play', SAMPLE, '--topics', '/nope'),
              '/nope not in the bag; it has /diagnostics, /erva/damping_cmd')
    _one_line(erva('bag', 'play', SAMPLE, '-x', '.*'), 'leaves nothing to play')
    _one_line(erva('replay', SAMPLE, '--reevaluate', '--start-offset', 1),
              'do not publish: drop the play options')
    _one_line(erva('replay', SAMPLE, '--reevaluate', '--read-ahead-queue-size', 10),
              'do not publish: drop the play options')
    config = tmp_path / 'mcap.yaml'
    config.write_text('compression: Zstd\nnoChunking: true\n')
    _one_line(erva('bag', 'record', '-o', tmp_path / 'b', '--storage-config-file', config),
              'noChunking not supported by erva\'s recorder (it takes chunkSize, compression)')
    config.write_text('compression: Brotli\n')
    _one_line(erva('bag', 'record', '-o', tmp_path / 'b', '--storage-config-file', config),
              "compression 'Brotli': choose None, Lz4 or Zstd")
    _one_line(erva('bag', 'record', '-o', tmp_path, '--topics', '/erva/state'),
              f'-o {tmp_path}: exists already')
    _one_line(erva('bag', 'record', '-o', tmp_path / 'b', '--custom-data', 'novalue'),
              "--custom-data 'novalue': give KEY=VALUE")
    assert sorted(os.listdir(tmp_path)) == ['mcap.yaml']        # nothing was recorded


def _complete(line):
    """Return bash's candidates for ``line``, completed as the README shows how to enable."""
    script = ('eval "$(register-python-argcomplete erva)"; read -ra COMP_WORDS <<< "$LINE"; '
              '[[ "$LINE" == *" " ]] && COMP_WORDS+=(""); '
              'COMP_CWORD=$((${#COMP_WORDS[@]} - 1)); COMP_LINE="$LINE"; '
              'COMP_POINT=${#LINE}; _python_argcomplete erva; printf "%s\\n" "${COMPREPLY[@]}"')
    bindir = os.path.dirname(sys.executable)
    env = ros_env({'LINE': line, 'PATH': bindir + os.pathsep + os.environ.get('PATH', '')})
    proc = subprocess.run(['bash', '-c', script], capture_output=True, text=True, env=env,
                          cwd=REPO, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return sorted(c.strip() for c in proc.stdout.splitlines() if c.strip())


@pytest.mark.skipif(not shutil.which('bash'), reason='bash completion needs bash')
def test_shell_completion_offers_the_verbs_their_options_and_the_bags_topics():
    assert shutil.which('register-python-argcomplete', path=os.path.dirname(sys.executable))
    assert _complete('erva bag p') == ['play']
    assert _complete('erva bag re') == ['record', 'reindex', 'repair']
    assert '--start-offset' in _complete('erva bag play bags/sample --start-')
    assert _complete('erva bag play bags/sample --topics /erva/s') == [
        '/erva/sprung_accel', '/erva/state']
    assert 'replay' in _complete('erva re')


# -- over DDS ------------------------------------------------------------------------------
class TopicCounter(SpinningNode):
    """Receive one topic's raw messages in this process (rclpy in a thread), in order."""

    def __init__(self, topic):
        from erva_ros.ros import qos as ros_qos
        from sensor_msgs.msg import JointState
        super().__init__('bag_verbs_counter')
        self.received = []
        self.node.create_subscription(JointState, topic, self.received.append,
                                      ros_qos.control_qos(1000), raw=True)

    def wait_for(self, n, timeout=60.0):
        end = time.monotonic() + timeout
        while len(self.received) < n and time.monotonic() < end:
            time.sleep(0.02)
        assert len(self.received) >= n, (len(self.received), n)


def _bag_messages(path, topics):
    """Return [(topic, log time, bytes)] of ``topics`` in log-time order (mcap's reader)."""
    from mcap.reader import make_reader
    mcap = next(os.path.join(path, f) for f in os.listdir(path) if f.endswith('.mcap'))
    with open(mcap, 'rb') as fh:
        return [(c.topic, m.log_time, m.data) for _, c, m in
                make_reader(fh).iter_messages(topics=topics, log_time_order=True)]


def _start(*args, **kw):
    return subprocess.Popen([sys.executable, '-m', 'erva_ros.cli', *map(str, args)],
                            env=ros_env(), cwd=REPO, text=True, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, start_new_session=True, **kw)


def _line_waiter(proc):
    """Return ``wait_line(text)``: the next line of ``proc``'s stderr that contains ``text``."""
    lines, seen = queue.Queue(), []
    threading.Thread(target=lambda: [lines.put(x) for x in proc.stderr], daemon=True).start()

    def wait_line(text, timeout=120.0):
        end = time.monotonic() + timeout
        while True:
            try:
                line = lines.get(timeout=max(0.0, end - time.monotonic()))
            except queue.Empty:
                proc.kill()
                raise AssertionError(f'no "{text}" line in {timeout:g} s: {seen[-5:]}') from None
            seen.append(line)
            if text in line:
                return line
    return wait_line


@pytest.mark.ros
def test_record_what_is_played_from_a_start_offset(tmp_path):
    """Only messages at or after start + offset are played; the recording holds exactly those."""
    topics = ['/erva/damping_cmd', '/erva/state']
    out = tmp_path / 'recorded'
    rec = _start('bag', 'record', '--topics', *topics, '-o', out, '--custom-data',
                 'purpose=test', '--json')
    try:
        end = time.monotonic() + 120
        while not out.is_dir():
            assert rec.poll() is None and time.monotonic() < end, rec.communicate()
            time.sleep(0.05)
        play = subprocess.run([sys.executable, '-m', 'erva_ros.cli', 'bag', 'play', SAMPLE,
                               '--topics', *topics, '--start-offset', '2.5', '--rate', '2',
                               '--wait-for-subscribers', '60', '--wait-for-all-acked',
                               '60000', '--json'], env=ros_env(), cwd=REPO,
                              capture_output=True, text=True, timeout=300)
        assert play.returncode == 0, play.stderr
        stats = json.loads(play.stdout)
        assert stats['acknowledged'] and stats['start_offset_s'] == 2.5
    finally:
        rec.send_signal(signal.SIGINT)
        rec_out, rec_err = rec.communicate(timeout=120)
    assert rec.returncode == 0, rec_err
    result = json.loads(rec_out)
    original = _bag_messages(SAMPLE, topics)
    from erva_ros.core.bag.reader import open_bag
    start = open_bag(SAMPLE).start_ns + 2_500_000_000
    recorded = _bag_messages(str(out), topics)
    for topic in topics:   # in order per topic (two writers' samples may cross in transit)
        expected = [data for t, log, data in original if t == topic and log >= start]
        assert 0 < len(expected) < sum(t == topic for t, _, _ in original)   # a cut
        assert [data for t, _, data in recorded if t == topic] == expected, topic
        assert result['counts'][topic] == stats['published'][topic] == len(expected)
    assert stats['total'] == len(recorded) == result['messages']
    assert result['stopped_by'] == 'signal' and result['exit_status'] == 0
    meta = (out / 'metadata.yaml').read_text()
    assert 'purpose' in meta and 'test' in meta


@pytest.mark.ros
@pytest.mark.parametrize('how', ['signals', 'space key'])
def test_nothing_is_published_while_paused_and_everything_after(how):
    """Pause mid-bag: the subscriber's count stands still; resumed, the rest comes in order.

    With signals, the topic is also remapped (-m): the subscriber listens to the new name.
    """
    topic = '/erva/state'
    remap = ['-m', f'{topic}:=/test/remapped'] if how == 'signals' else []
    counter = TopicCounter('/test/remapped' if remap else topic)
    master = slave = proc = None
    try:
        args = ['bag', 'play', SAMPLE, '--topics', topic, '--rate', '0.5',
                '--wait-for-subscribers', '60', '--json', *remap]
        if how == 'signals':
            proc = _start(*args)
            pause = lambda: proc.send_signal(signal.SIGUSR1)    # noqa: E731
            resume = lambda: proc.send_signal(signal.SIGUSR2)   # noqa: E731
        else:
            master, slave = pty.openpty()
            proc = _start(*args, '--start-paused', stdin=slave)
            pause = resume = lambda: os.write(master, b' ')     # noqa: E731

        wait_line = _line_waiter(proc)
        if how == 'space key':
            assert 'space pauses and resumes' in wait_line('space pauses')
            assert 'paused after 0 messages' in wait_line('paused after')
            time.sleep(1.0)                     # started paused: nothing at all
            assert counter.received == []
            resume()
            wait_line('resumed after 0 messages')
        counter.wait_for(20)
        pause()
        n = int(wait_line('paused after').split('paused after ')[1].split()[0])
        assert 20 <= n < 200
        counter.wait_for(n)                     # what was out before the pause arrives...
        time.sleep(1.0)                         # ...and nothing more (25 at this rate)
        assert len(counter.received) == n
        resume()
        assert f'resumed after {n} messages' in wait_line('resumed after')
        out = proc.stdout.read()
        assert proc.wait(timeout=300) == 0
        stats = json.loads(out)
        counter.wait_for(200)
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        counter.close()
        for fd in (master, slave):
            if fd is not None:
                os.close(fd)
    assert stats['total'] == 200 and stats['pauses'] == 1
    assert [bytes(m) for m in counter.received] == [
        d for _, _, d in _bag_messages(SAMPLE, [topic])]


@pytest.mark.ros
def test_a_recorder_started_after_the_player_both_say_what_it_missed(tmp_path):
    """Play with no subscriber; pause; start `erva bag record TOPIC` (positional); resume.

    The player says no subscriber matched at its start, and at the end how many messages
    went out before the recorder matched; the recorder, by the player's sequence numbers,
    says the same count is not in its bag.  Nothing here depends on timing: the pause
    holds the player while the recorder matches.
    """
    from recorder_helpers import DiagnosticsWatcher, wait_recorded
    topic, out = '/erva/state', tmp_path / 'late'
    play = _start('bag', 'play', SAMPLE, '--topics', topic, '--rate', '0.5', '--json')
    wait_line = _line_waiter(play)
    watcher, rec = DiagnosticsWatcher(), None
    try:
        assert f'subscribers matched at the start: {topic} 0' in wait_line('at the start')
        assert 'WARN no subscriber matched any of the 1 topics' in wait_line('WARN')
        before = 0
        while not before:                  # at least one message out with no subscriber
            play.send_signal(signal.SIGUSR1)
            before = int(wait_line('paused after').split('paused after ')[1].split()[0])
            if not before:
                play.send_signal(signal.SIGUSR2)
                wait_line('resumed after')
        rec = _start('bag', 'record', topic, '-o', out, '--json')
        assert watcher.wait(lambda: any(s.get(f'publishers:{topic}') == '1' for s in
                                        watcher.values('erva_bag_recorder: bag recorder')),
                            120), watcher.values('erva_bag_recorder')
        play.send_signal(signal.SIGUSR2)
        stats = json.loads(play.stdout.read())
        assert play.wait(timeout=300) == 0
        late = wait_line('WARN of 200 messages')
        reach = stats['subscribers'][topic]
        assert (reach['at_start'], reach['most'], reach['published']) == (0, 1, 200)
        # Out before the recorder matched: at least those before the pause.
        assert reach['before_last_match'] >= before and \
            reach['unmatched'] == reach['before_last_match']
        assert f'{topic} {reach["before_last_match"]} of 200' in late
        wait_recorded(watcher, {topic: 200 - reach['before_last_match']},
                      'erva_bag_recorder')
        rec.send_signal(signal.SIGINT)
        rec_out, rec_err = rec.communicate(timeout=120)
    finally:
        for proc in (play, rec):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
        watcher.close()
    assert rec.returncode == 0, rec_err
    result = json.loads(rec_out)
    assert result['topics_requested'] == [topic]          # the positional topic
    assert result['counts'] == {topic: 200 - reach['before_last_match']}
    assert result['missing'] == {topic: {'recorded': result['counts'][topic],
                                         'before_first': reach['before_last_match'],
                                         'holes': 0}}
    assert f'{reach["before_last_match"]} went out before this recorder matched' in rec_err
