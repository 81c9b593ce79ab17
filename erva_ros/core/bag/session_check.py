"""Is a bag one whole session, and only its own?  The checks behind `erva bag info`'s warnings.

* **The end.**  `erva run` records how its session ended (completed or not, and why):
  in the bag's metadata.yaml (custom_data ``erva_session_end``) once the recorder has
  finished the file, and always in the bag's end file (:data:`END_FILE`), which it writes
  as the loop starts (:func:`begin_session_end`, saying "erva run stopped before it
  recorded the end") and overwrites in place at the end (:func:`mark_session_end`): in
  place, so a disk the recording filled still takes it.  The recorder dead or its disk
  full, the end file is what says so; `erva bag repair` carries it into the repaired
  bag's metadata and says it repaired (``erva_repaired``, :mod:`erva_ros.core.bag.repair`).
  A bag of `erva run` without either record says what the bag itself shows.  The end
  record also keeps the stamp of the loop's first sample (custom_data ``erva_loop_start``
  too): the bag begins with the bring-up, and `erva bag play --start-offset loop` starts
  at sample 0.
* **Only its own.**  A bag records a session's namespace, and ``/diagnostics``, which every
  node on the DDS domain shares.  Reports (:mod:`erva_ros.core.reports`) carry their
  session's id: a report in the bag's namespace with another id means another session ran
  on the same topics (the loops merged); a stamp repeated on a data topic is the same
  sign in the data.  Reports of other namespaces are another session's business and are
  only counted.
"""

import json
import os
from typing import Any, Dict, List, Optional, Sequence

from erva_ros.core import contract, topics
from erva_ros.core.bag import BagError
from erva_ros.core.bag.metadata import METADATA_FILE, read_metadata, write_metadata
from erva_ros.core.reports import report_from_status
from erva_ros.core.wire import header_stamp_ns

#: custom_data keys of metadata.yaml.
END_KEY = 'erva_session_end'
REPAIRED_KEY = 'erva_repaired'
LOOP_KEY = 'erva_loop_start'
#: The end record's own file in the bag directory (JSON; other tools ignore it).
END_FILE = 'erva_session_end.json'
#: Its size, reserved as the loop starts: the end is written into it in place.
END_FILE_BYTES = 4096
#: What the end file says until `erva run` records the end.
NOT_RECORDED = 'erva run stopped before it recorded how the session ended (killed?)'
#: Data topics whose stamps a session publishes once each.
ONCE_PER_STAMP = (topics.STATE, topics.SPRUNG_ACCEL, topics.GENERATOR, topics.ROAD_HEIGHT,
                  topics.ROAD_PREVIEW)


def _end_text(end: Dict[str, Any]) -> bytes:
    """Return the end record as END_FILE_BYTES of JSON (a long reason cut to fit)."""
    reason = end.get('reason', '')
    for cut in range(len(reason), -1, -64):
        text = json.dumps(dict(end, reason=reason[:cut]), sort_keys=True).encode('utf-8')
        if len(text) < END_FILE_BYTES:
            return text.ljust(END_FILE_BYTES - 1) + b'\n'
    raise ValueError('the end record does not fit')     # not reached: '' fits


def begin_session_end(bag_dir: str) -> None:
    """Reserve the bag's end file, saying the end is not recorded yet (OSError: could not)."""
    with open(os.path.join(bag_dir, END_FILE), 'wb') as fh:
        fh.write(_end_text({'completed': False, 'reason': NOT_RECORDED}))
        fh.flush()
        os.fsync(fh.fileno())


def mark_session_end(bag_dir: str, completed: bool, reason: str = '',
                     loop_start_ns: Optional[int] = None, yielded: Sequence[str] = ()
                     ) -> List[str]:
    """Record in ``bag_dir`` how the session ended (``completed`` or why not).

    Into the end file in place (reserved by :func:`begin_session_end`; written new if it
    was not), and into metadata.yaml if the recorder wrote one.  ``loop_start_ns``: the
    stamp of the loop's first sample (t_0 of sample 0, as the session's monitor took it);
    ``yielded``: ids of sessions that started on the namespace too and stood down before
    any of their nodes was configured (their nodes' statuses are in the bag; no warning
    for them).  Returns what could not be written, one line each ([]: all of it).
    """
    end: Dict[str, Any] = {'completed': bool(completed), 'reason': reason}
    if yielded:
        end['yielded'] = sorted(yielded)
    if loop_start_ns is not None:
        end['loop_start_ns'] = int(loop_start_ns)
    failed = []
    path = os.path.join(bag_dir, END_FILE)
    try:
        with open(path, 'r+b' if os.path.exists(path) else 'wb') as fh:
            fh.write(_end_text(end))
    except OSError as exc:
        failed.append(f'cannot write {path}: {exc.strerror or exc}')
    if not os.path.exists(os.path.join(bag_dir, METADATA_FILE)):
        return failed
    try:
        meta = read_metadata(bag_dir)
        custom = dict(meta.get('custom_data') or {})
        custom[END_KEY] = json.dumps(end, sort_keys=True)
        if loop_start_ns is not None:
            custom[LOOP_KEY] = str(int(loop_start_ns))
        meta['custom_data'] = custom
        write_metadata(bag_dir, meta)
    except BagError as exc:
        failed.append(str(exc))
    return failed


def loop_start_ns(bag) -> Optional[int]:
    """Return the stamp (ns) of the loop's first sample, None if the bag has no mark."""
    text = ((bag.metadata_yaml or {}).get('custom_data') or {}).get(LOOP_KEY)
    if not text:
        text = (session_end(bag) or {}).get('loop_start_ns')
    try:
        return int(text) if text else None
    except (TypeError, ValueError):
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


def end_file_record(bag_dir: Optional[str]) -> Optional[str]:
    """Return the end file's record as metadata's custom_data value (None: no such file)."""
    if bag_dir is None:
        return None
    try:
        with open(os.path.join(bag_dir, END_FILE), 'rb') as fh:
            text = fh.read(END_FILE_BYTES).decode('utf-8', errors='replace').strip()
    except OSError:
        return None
    return text or None


def session_end(bag) -> Optional[Dict]:
    """Return the recorded end of the session ({'completed', 'reason'}), None if absent.

    metadata.yaml's record, else the end file's.
    """
    text = (((bag.metadata_yaml or {}).get('custom_data') or {}).get(END_KEY)
            or end_file_record(bag.bag_dir))
    if not text:
        return None
    try:
        return json.loads(text)
    except ValueError:
        return {'completed': False, 'reason': f'unreadable end record {text[:80]!r}'}


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
            out.append('the session was cut short: no end record, ' + (
                'and the recorder did not finish the bag (killed, or its disk was full)'
                if not bag.complete or custom.get(REPAIRED_KEY) else
                'though the recorder finished the bag (erva run was stopped before it '
                'recorded the end)'))
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


__all__ = ['END_KEY', 'REPAIRED_KEY', 'LOOP_KEY', 'END_FILE', 'NOT_RECORDED',
           'begin_session_end', 'mark_session_end', 'loop_start_ns', 'loop_offset_s',
           'end_file_record', 'session_end', 'session_warnings']
