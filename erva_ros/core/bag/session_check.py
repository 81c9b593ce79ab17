"""Is a bag one whole session, and only its own?  The checks behind `erva bag info`'s warnings.

* **The end.**  `erva run` writes how its session ended into the bag's metadata.yaml
  (custom_data ``erva_session_end``: completed or not, and why; ``erva_loop_start``: the
  stamp of the loop's first sample) once the recorder has finished the file
  (:func:`mark_session_end`).  A bag of `erva run` without that record
  was cut short: the supervisor was killed before it could say.  A repaired bag says so
  (``erva_repaired``, :mod:`erva_ros.core.bag.repair`).
* **Only its own.**  A bag records a session's namespace, and ``/diagnostics``, which every
  node on the DDS domain shares.  Reports (:mod:`erva_ros.core.reports`) carry their
  session's id: a report in the bag's namespace with another id means another session ran
  on the same topics (the loops merged); a stamp repeated on a data topic is the same
  sign in the data.  Reports of other namespaces are another session's business and are
  only counted.
"""

import json
from typing import Dict, List, Optional, Sequence

from erva_ros.core import contract, topics
from erva_ros.core.bag.metadata import read_metadata, write_metadata
from erva_ros.core.reports import report_from_status
from erva_ros.core.wire import header_stamp_ns

#: custom_data keys of metadata.yaml.
END_KEY = 'erva_session_end'
REPAIRED_KEY = 'erva_repaired'
LOOP_KEY = 'erva_loop_start'
#: Data topics whose stamps a session publishes once each.
ONCE_PER_STAMP = (topics.STATE, topics.SPRUNG_ACCEL, topics.GENERATOR, topics.ROAD_HEIGHT,
                  topics.ROAD_PREVIEW)


def mark_session_end(bag_dir: str, completed: bool, reason: str = '',
                     loop_start_ns: Optional[int] = None, yielded: Sequence[str] = ()) -> None:
    """Record in ``bag_dir``'s metadata.yaml how the session ended (``completed`` or why not).

    ``loop_start_ns``: the stamp of the loop's first sample (t_0 of sample 0, as the
    session's monitor took it), for ``erva bag play --start-offset loop``;
    ``yielded``: ids of sessions that started on the namespace too and stood down before
    any of their nodes was configured (their nodes' statuses are in the bag; no
    warning for them).
    """
    meta = read_metadata(bag_dir)
    custom = dict(meta.get('custom_data') or {})
    end = {'completed': bool(completed), 'reason': reason}
    if yielded:
        end['yielded'] = sorted(yielded)
    custom[END_KEY] = json.dumps(end, sort_keys=True)
    if loop_start_ns is not None:
        custom[LOOP_KEY] = str(int(loop_start_ns))
    meta['custom_data'] = custom
    write_metadata(bag_dir, meta)


def loop_start_ns(bag) -> Optional[int]:
    """Return the stamp (ns) of the loop's first sample, None if the bag has no mark."""
    text = ((bag.metadata_yaml or {}).get('custom_data') or {}).get(LOOP_KEY)
    try:
        return int(text) if text else None
    except ValueError:
        return None


def loop_offset_s(bag) -> Optional[float]:
    """Return how far (s) into the bag the loop's first sample is (None: no mark).

    The offset of ``--start-offset`` (from the bag's first message, as ros2 bag play):
    playing from it starts with sample 0, the bring-up before it left out.
    """
    t0 = loop_start_ns(bag)
    if t0 is None or bag.start_ns is None:
        return None
    return max(0.0, (t0 - bag.start_ns) * 1e-9)


def session_end(bag) -> Optional[Dict]:
    """Return the recorded end of the session ({'completed', 'reason'}), None if absent."""
    text = ((bag.metadata_yaml or {}).get('custom_data') or {}).get(END_KEY)
    if not text:
        return None
    try:
        return json.loads(text)
    except ValueError:
        return {'completed': False, 'reason': f'unreadable end record {text!r}'}


def session_warnings(bag) -> List[str]:
    """Return one line per way the bag is not one whole session of its own (module doc)."""
    out = []
    custom = (bag.metadata_yaml or {}).get('custom_data') or {}
    if custom.get(REPAIRED_KEY):
        out.append(f'repaired: {custom[REPAIRED_KEY]}; the session may end early')
    own_id = bag.session.get('session_id', '')
    end = session_end(bag)
    yielded = set((end or {}).get('yielded') or ())
    if own_id:                      # recorded by `erva run`
        if end is None:
            out.append('the session was cut short: no end record (erva run was killed '
                       'before it finished the bag)')
        elif not end.get('completed'):
            out.append(f'the session was cut short: {end.get("reason") or "not completed"}')
    namespace = _namespace(bag)
    others: Dict[str, set] = {}
    repeated: Dict[str, int] = {}
    seen: Dict[str, set] = {}
    wanted = {f'{namespace}/{t}' for t in ONCE_PER_STAMP} | {topics.DIAGNOSTICS}
    for m in bag.messages([t for t in bag.topics if t in wanted]):
        try:
            if m.topic == topics.DIAGNOSTICS:
                for status in contract.decode_diagnostics(m.data)[1]:
                    if status.name.startswith(namespace + '/'):
                        sid = report_from_status(status).session
                        if own_id and sid and sid != own_id and sid not in yielded:
                            others.setdefault(sid, set()).add(status.name)
                continue
            stamp = header_stamp_ns(m.data)
        except contract.MessageRejected:
            continue
        stamps = seen.setdefault(m.topic, set())
        if stamp in stamps:
            repeated[m.topic] = repeated.get(m.topic, 0) + 1
        stamps.add(stamp)
    for sid, names in sorted(others.items()):
        out.append(f'holds reports of another session ({sid}) in {namespace}: '
                   f'{", ".join(sorted(names)[:4])}; two sessions ran on the same topics')
    for topic, n in sorted(repeated.items() if own_id else ()):
        out.append(f'{n} messages on {topic} repeat a stamp: another loop published on '
                   'the same topic')
    return out


def _namespace(bag) -> str:
    """Return the namespace of the session in ``bag`` (where its state topic is)."""
    for suffix in (topics.DAMPING_CMD, topics.STATE):
        for name in sorted(bag.topics):
            if name.endswith('/' + suffix):
                return name[:-len(suffix) - 1]
    return topics.NAMESPACE


__all__ = ['END_KEY', 'REPAIRED_KEY', 'LOOP_KEY', 'mark_session_end', 'loop_start_ns',
           'loop_offset_s', 'session_end', 'session_warnings']
