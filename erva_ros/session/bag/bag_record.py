"""`erva bag record`: record a running ROS graph with erva's recorder, as ``ros2 bag record``.

recorder_node runs as its own process (:mod:`erva_ros.session.processes`), driven by its
parameters only: the bag directory, the topics, the session metadata (``--custom-data``),
the MCAP chunk size and compression (``--storage-config-file``, rosbag2_storage_mcap's
keys), the split (``-d/--max-bag-duration``, ``-b/--max-bag-size``), ``use_sim_time``.
The topics, as ``ros2 bag record`` chooses them (rosbag2 Jazzy):

* ``--topics`` are recorded whenever they appear (the recorder subscribes to a topic of
  the erva contract at once and to any other once the graph shows its type);
* ``-a/--all`` and ``-e/--regex`` (a topic containing a match) choose from the topics
  the graph shows after ``discovery_s`` -- once, at the start: unlike rosbag2, a topic
  that appears later is not added (as ``ros2 bag record --no-discovery``); hidden topics
  (a name part starting with ``_``) only with ``--include-hidden-topics``;
* ``--exclude-topics`` and ``--exclude-regex`` remove from the above;
* nothing chosen: the topics an `erva run` session records (the contract and the HIL
  topics), absolute, so the recording matches `erva run --record`.

The recording stops on SIGINT/SIGTERM (or ``duration_s`` after the recorder opened the
bag): the recorder is sent SIGINT, takes what was delivered to it (recorder_node's
drain: while publishers go on, for up to 5 s, and what arrives meanwhile is recorded
too), finishes the file (summary, index, metadata.yaml) and exits; the bag is then read
back and counted per topic, and the publishers' sequence numbers say what it lacks: what
went out before the recorder matched a publisher (a recorder started after ``erva bag
play``), and holes (:mod:`erva_ros.core.bag.sequences`).
"""

from dataclasses import asdict, dataclass, field
import os
import re
import shutil
import tempfile
import time
from typing import Callable, Dict, List, Mapping, Optional

import yaml

from erva_ros.core.bag import BagError
from erva_ros.core.bag.reader import open_bag
from erva_ros.core.bag.sequences import missing_by_sequence
from erva_ros.core.bag.session import recorder_ros_args
from erva_ros.core.errors import CLIError
from erva_ros.ros.context import RosContext
from erva_ros.session.processes import ChildProcess, child_env, module_argv

#: Keys of rosbag2_storage_mcap's writer configuration that recorder_node implements.
STORAGE_KEYS = ('chunkSize', 'compression')
#: rosbag2_storage_mcap's compression names -> recorder_node's.
COMPRESSION = {'none': 'none', '': 'none', 'zstd': 'zstd', 'lz4': 'lz4'}
#: How often the wait loop looks at the recorder and the stop flag (s).
POLL_S = 0.05


@dataclass
class RecordOptions:
    """What `erva bag record` records, where, and how."""

    output: str
    topics: List[str] = field(default_factory=list)
    all_topics: bool = False
    regex: str = ''
    exclude_topics: List[str] = field(default_factory=list)
    exclude_regex: str = ''
    include_hidden: bool = False
    node_name: str = 'erva_bag_recorder'
    use_sim_time: bool = False
    custom_data: Dict[str, str] = field(default_factory=dict)
    storage: Dict[str, object] = field(default_factory=dict)   # recorder parameters
    duration_s: Optional[float] = None
    discovery_s: float = 2.0
    command: str = ''

    @property
    def needs_graph(self) -> bool:
        """Return whether the topics are chosen from the running graph."""
        return self.all_topics or bool(self.regex)


def absolute(topic: str) -> str:
    """Return ``topic`` resolved against the root namespace (as ros2 bag record does)."""
    return topic if topic.startswith('/') else '/' + topic


def _regex(pattern: str, option: str):
    try:
        return re.compile(pattern) if pattern else None
    except re.error as exc:
        raise CLIError(f'{option} {pattern!r} is not a regular expression ({exc})') from None


def hidden(topic: str) -> bool:
    """Tell whether a part of the topic name starts with an underscore (a hidden topic)."""
    return any(part.startswith('_') for part in topic.split('/'))


def choose_topics(opts: RecordOptions, graph: Mapping[str, str],
                  default: List[str]) -> List[str]:
    """Return the topics to record, sorted (rules in the module doc)."""
    include, exclude = _regex(opts.regex, '--regex'), _regex(opts.exclude_regex,
                                                             '--exclude-regex')
    chosen = {absolute(t) for t in opts.topics}
    for topic in graph:
        if hidden(topic) and not opts.include_hidden:
            continue
        if opts.all_topics or (include is not None and include.search(topic)):
            chosen.add(topic)
    if not (opts.topics or opts.needs_graph):
        chosen = {absolute(t) for t in default}
    excluded = {absolute(t) for t in opts.exclude_topics}
    out = sorted(t for t in chosen if t not in excluded
                 and not (exclude is not None and exclude.search(t)))
    if not out:
        raise CLIError('nothing to record: no topic of the graph is chosen'
                       + (f' (it shows {", ".join(sorted(graph))})' if graph else
                          ' (the graph shows none; is the system running, on this '
                          'ROS_DOMAIN_ID?)'))
    return out


def storage_parameters(path: Optional[str]) -> Dict[str, object]:
    """Return recorder parameters from a rosbag2_storage_mcap configuration file."""
    if not path:
        return {}
    try:
        with open(path, encoding='utf-8') as fh:
            config = yaml.safe_load(fh) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise CLIError(f'--storage-config-file {path}: cannot be read ({exc})') from None
    if not isinstance(config, dict):
        raise CLIError(f'--storage-config-file {path}: not a mapping of writer options')
    unknown = sorted(set(config) - set(STORAGE_KEYS))
    if unknown:
        raise CLIError(f'--storage-config-file {path}: {", ".join(unknown)} not supported by '
                       f'erva\'s recorder (it takes {", ".join(STORAGE_KEYS)})')
    out: Dict[str, object] = {}
    if 'chunkSize' in config:
        size = config['chunkSize']
        if not isinstance(size, int) or isinstance(size, bool) or not \
                1024 <= size <= 64 * 1024 * 1024:
            raise CLIError(f'--storage-config-file {path}: chunkSize {size!r} must be an '
                           'integer 1024..67108864 (bytes)')
        out['chunk_size'] = size
    if 'compression' in config:
        name = str(config['compression'] or '').lower()
        if name not in COMPRESSION:
            raise CLIError(f'--storage-config-file {path}: compression '
                           f'{config["compression"]!r}: choose None, Lz4 or Zstd')
        out['compression'] = COMPRESSION[name]
    return out


def check_output(path: str) -> None:
    """Raise CLIError unless a bag directory can be created at ``path``."""
    if os.path.exists(path):
        raise CLIError(f'-o {path}: exists already; give a new directory')
    parent = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(parent) or not os.access(parent, os.W_OK):
        raise CLIError(f'-o {path}: cannot create it ({parent} is not a writable directory)')


def graph_topics(discovery_s: float) -> Dict[str, str]:
    """Return {topic: type} as the ROS graph shows them after ``discovery_s``."""
    ros = RosContext()
    try:
        node = ros.create_node('erva_bag_record_discovery')
        end = time.monotonic() + discovery_s
        while time.monotonic() < end:
            ros.spin_once(0.05)
        return {name: types[0] for name, types in node.get_topic_names_and_types()
                if types}
    finally:
        ros.close()


def record(opts: RecordOptions, topics: List[str], should_stop: Callable[[], bool],
           log: Callable[[str], None]) -> Dict:
    """Record ``topics`` into ``opts.output`` until stopped; return what the bag holds."""
    metadata = {'scenario': 'record', 'source': 'erva bag record', **opts.custom_data}
    if opts.command:
        metadata['command'] = opts.command
    argv = module_argv('erva_ros.nodes.recorder_node', *recorder_ros_args(
        opts.output, metadata, topics=topics, namespace='/', node_name=opts.node_name,
        use_sim_time=opts.use_sim_time, parameters=opts.storage))
    logs = tempfile.mkdtemp(prefix='erva_bag_record_')
    try:
        status, stopped_by, tail, wall_s = _run(opts, argv, logs, should_stop, log,
                                                len(topics))
    finally:
        shutil.rmtree(logs, ignore_errors=True)
    result = {'bag': opts.output, 'topics_requested': topics, 'exit_status': status,
              'stopped_by': stopped_by, 'wall_s': wall_s}
    if status != 0:
        result['recorder_log'] = tail
    try:
        bag = open_bag(opts.output)
        info = bag.info()
        missing = missing_by_sequence(bag.messages())
    except (BagError, OSError) as exc:
        result['error'] = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        return result
    result.update({'messages': info['message_count'], 'duration_s': info['duration_s'],
                   'counts': {t['name']: t['count'] for t in info['topics']},
                   'warnings': info['warnings'],
                   'missing': {t: None if m is None else asdict(m)
                               for t, m in sorted(missing.items())}})
    return result


def missing_line(result: Mapping) -> Optional[str]:
    """Return a WARN line on what the publishers' numbers say the bag lacks (or None)."""
    missing = {t: m for t, m in (result.get('missing') or {}).items()
               if m and m['before_first'] + m['holes']}
    if not missing:
        return None
    before = sum(m['before_first'] for m in missing.values())
    holes = sum(m['holes'] for m in missing.values())
    parts = ([f'{before} went out before this recorder matched their publisher'] if before
             else []) + ([f'{holes} are holes in between'] if holes else [])
    topics = ', '.join(f'{t} {m["before_first"] + m["holes"]}'
                       for t, m in list(missing.items())[:4])
    more = f', and {len(missing) - 4} more topics' if len(missing) > 4 else ''
    return (f'WARN by their publishers\' sequence numbers, {before + holes} messages are not '
            f'in the bag: {" and ".join(parts)} ({topics}{more})')


def _run(opts: RecordOptions, argv: List[str], logs: str, should_stop: Callable[[], bool],
         log: Callable[[str], None], n_topics: int):
    """Run the recorder until a stop; return (exit status, why it stopped, log tail, s)."""
    proc = ChildProcess('recorder_node', argv, child_env(),
                        os.path.join(logs, 'recorder_node.log'))
    started = time.monotonic()
    recording: Optional[float] = None    # since the recorder opened the bag
    stopped_by = 'signal'
    try:
        while proc.poll() is None:
            if recording is None and os.path.isdir(opts.output):
                log(f'recording {n_topics} topics to {opts.output} (Ctrl-C stops)')
                recording = time.monotonic()
            if should_stop():
                break
            if opts.duration_s is not None and recording is not None and \
                    time.monotonic() - recording >= opts.duration_s:
                stopped_by = 'duration'
                break
            time.sleep(POLL_S)
        else:
            stopped_by = 'recorder exited'
        proc.stop()
        return proc.popen.returncode, stopped_by, proc.tail(5), time.monotonic() - started
    finally:
        proc.close()


__all__ = ['RecordOptions', 'STORAGE_KEYS', 'absolute', 'hidden', 'choose_topics',
           'storage_parameters', 'check_output', 'graph_topics', 'record', 'missing_line']
