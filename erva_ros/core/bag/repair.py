"""Recover a bag whose recorder died: ``erva bag repair DIR`` (like ``ros2 bag reindex``).

A recorder killed with SIGKILL (or a full disk) leaves its last MCAP file without
summary and indexes, perhaps ending inside a chunk, and a metadata.yaml that does not
list that file (a split bag: the finished files) or none at all.  Every chunk that was
flushed is intact; repair copies all readable records of each unfinished file
(schemas, channels, session metadata, messages up to the last complete chunk) into a
new, properly closed file in the same place, keeps the original as ``<file>.orig``
unless told not to, and writes metadata.yaml listing every file.  A bag whose files
are complete only gets metadata.yaml.
With ``out_dir`` the repaired bag is a new directory there and the original is not
touched: the way out when its own disk is full.
"""

import errno
import functools
import os
import shutil
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

from mcap.writer import CompressionType, Writer

from erva_ros import __version__
from erva_ros.core.bag import BagError
from erva_ros.core.bag import metadata as bag_meta
from erva_ros.core.bag.reader import BagFile, dir_files, resolve_bag_path, topics_of
from erva_ros.core.bag.session_check import END_KEY, end_file_record, REPAIRED_KEY
from erva_ros.core.bag.writer import PROFILE, ROSBAG2_RECORD, SESSION_RECORD


def _files_of(path: str) -> Tuple[str, List[str]]:
    """Return (bag directory, its .mcap paths in order); a damaged metadata.yaml is ignored."""
    try:
        bag_dir, paths, _ = resolve_bag_path(path)
        return bag_dir or os.path.dirname(os.path.abspath(paths[0])), paths
    except BagError:
        if not os.path.isdir(path):
            raise
        try:
            return path, dir_files(path)
        except BagError:
            found = [f for f in os.listdir(path) if f.endswith('.mcap')]
            raise BagError(f'{path}: need one .mcap file or the <bag>_<i>.mcap files of one '
                           f'bag to repair, found {len(found)} .mcap files') from None


def _topics(files: Sequence[BagFile]) -> List[Dict]:
    """Return the ``topics_with_message_count`` of ``files``: counts summed, in first use."""
    return [bag_meta.topic_entry(t.name, t.type, t.offered_qos, t.type_hash, t.count,
                                 t.serialization_format) for t in topics_of(files).values()]


def _metadata(files: Sequence[BagFile], custom: Mapping[str, str]) -> Dict:
    """Return the BagMetadata of ``files`` (read or scanned), in their order."""
    entries = [bag_meta.file_entry(os.path.basename(f.path), f.start_ns, f.end_ns,
                                   f.message_count) for f in files]
    return bag_meta.bag_metadata(entries, _topics(files), custom or None)


def _out_dir(out_dir: str, bag_dir: str) -> str:
    """Return ``out_dir`` made (empty, not the bag itself); BagError (one line) otherwise."""
    out_dir = os.path.abspath(out_dir)
    if os.path.realpath(out_dir) == os.path.realpath(bag_dir):
        raise BagError(f'--out {out_dir}: that is the bag itself; leave --out out to repair '
                       'in place')
    if os.path.exists(out_dir) and (not os.path.isdir(out_dir) or os.listdir(out_dir)):
        raise BagError(f'--out {out_dir}: exists and is not an empty directory')
    try:
        os.makedirs(out_dir, exist_ok=True)
    except OSError as exc:
        raise BagError(f'--out {out_dir}: cannot create it ({exc.strerror or exc})') from None
    return out_dir


def repair_bag(path: str, keep_original: bool = True, out_dir: Optional[str] = None) -> Dict:
    """Make ``path`` a complete, indexed bag with metadata.yaml; return what was done.

    Every file not closed properly (in a split bag: the one being written when the
    recorder died) is rewritten; metadata.yaml then lists all files.  ``out_dir``: write
    the repaired bag (its MCAP files, same names, and metadata.yaml) to that new or empty
    directory instead, leaving ``path`` as it is.
    """
    bag_dir, paths = _files_of(path)
    target = bag_dir if out_dir is None else _out_dir(out_dir, bag_dir)
    files = [BagFile(p).open() for p in paths]
    custom: Dict[str, str] = {}
    for f in files:
        for rec in f.metadata:
            if rec.name == SESSION_RECORD and not custom:
                custom.update(rec.metadata)
    broken = [f for f in files if not f.complete]
    # How the session ended (erva run's record) stays with the bag, and the bag says it
    # was repaired (core/bag/session_check.py).
    end = _end_record(bag_dir)
    if end:
        custom[END_KEY] = end
    if broken:
        custom[REPAIRED_KEY] = (f'{", ".join(os.path.basename(f.path) for f in broken)} '
                                f'not closed ({"; ".join(f.stopped_at for f in broken)}), '
                                'rewritten with what was readable')
    meta = _metadata(files, custom)
    result = {'bag': target, 'files': [os.path.join(target, os.path.basename(p))
                                       for p in paths],
              'messages': meta['message_count'],
              'topics': {t['topic_metadata']['name']: t['message_count']
                         for t in meta['topics_with_message_count']},
              'was_complete': not broken,
              'stopped_at': '; '.join(f.stopped_at for f in broken) or None,
              'repaired': [os.path.basename(f.path) for f in broken],
              'start_ns': meta['starting_time']['nanoseconds_since_epoch'] if meta['message_count']
              else None,
              'end_ns': (meta['starting_time']['nanoseconds_since_epoch']
                         + meta['duration']['nanoseconds']) if meta['message_count'] else None,
              'originals': [], 'source': bag_dir}
    for i, f in enumerate(files):
        target_file = os.path.join(target, os.path.basename(f.path))
        if f.complete:
            if out_dir is not None:
                _write(target, functools.partial(shutil.copyfile, f.path, target_file),
                       target_file)
            continue
        # Its rosbag2 record describes the bag up to this file, as the recorder's would.
        record = meta if i == len(files) - 1 else _metadata(files[:i + 1], custom)
        _write(target, functools.partial(_rewrite, f, target_file, record,
                                         keep_original and out_dir is None, result),
               target_file + '.repair')
    _write(target, lambda: bag_meta.write_metadata(target, meta))
    result['action'] = _action(len(files), result['repaired'], out_dir is not None)
    return result


def _end_record(bag_dir: str) -> Optional[str]:
    """Return how the session ended, as metadata.yaml or the bag's end file has it."""
    try:
        custom = bag_meta.read_metadata(bag_dir).get('custom_data') or {}
    except BagError:
        custom = {}
    return custom.get(END_KEY) or end_file_record(bag_dir)


def _action(n_files: int, repaired: List[str], elsewhere: bool) -> str:
    """Return what repair did, in words."""
    if n_files == 1:
        if repaired:
            return 'rewrote the MCAP file with summary and indexes, wrote metadata.yaml'
        return ('copied the MCAP file (it was complete), wrote metadata.yaml' if elsewhere
                else 'wrote metadata.yaml (the MCAP file was complete)')
    if repaired:
        return (f'rewrote {", ".join(repaired)} with summary and indexes, wrote metadata.yaml '
                f'of {n_files} files')
    return (f'copied the {n_files} MCAP files (they were complete), wrote metadata.yaml'
            if elsewhere else f'wrote metadata.yaml (the {n_files} MCAP files were complete)')


def _rewrite(part: BagFile, target_file: str, meta: Dict, keep_original: bool,
             result: Dict) -> None:
    """Copy every readable record of the scanned ``part`` into a finished ``target_file``."""
    scan = part.scan
    tmp = target_file + '.repair'
    with open(tmp, 'wb') as fh:
        out = Writer(fh, compression=CompressionType.NONE)
        header = scan.header
        out.start(profile=header.profile or PROFILE,
                  library=f'{header.library}; repaired by erva_ros/{__version__}')
        for rec in scan.metadata:
            if rec.name != ROSBAG2_RECORD:
                out.add_metadata(rec.name, dict(rec.metadata))
        schema_ids = {sid: out.register_schema(s.name, s.encoding, s.data)
                      for sid, s in sorted(scan.schemas.items())}
        channel_ids = {cid: out.register_channel(c.topic, c.message_encoding,
                                                 schema_ids.get(c.schema_id, 0),
                                                 dict(c.metadata))
                       for cid, c in sorted(scan.channels.items())}
        for m in scan.messages:
            if m.channel_id in channel_ids:
                out.add_message(channel_ids[m.channel_id], m.log_time, m.data,
                                m.publish_time, m.sequence)
        out.add_metadata(ROSBAG2_RECORD,
                         {'serialized_metadata': bag_meta.dump_yaml(meta, False)})
        out.finish()
    if keep_original:
        original = part.path + '.orig'
        os.replace(part.path, original)
        result['originals'].append(original)
    os.replace(tmp, target_file)


def _write(target: str, write, partial: Optional[str] = None) -> None:
    """Run ``write``; on an OSError remove ``partial`` and raise one line (BagError)."""
    try:
        write()
    except OSError as exc:
        if partial is not None:
            try:
                os.remove(partial)
            except OSError:
                pass
        hint = ('; give --out DIR on another disk' if exc.errno == errno.ENOSPC else '')
        raise BagError(f'cannot write the repaired bag in {target}: '
                       f'{exc.strerror or exc}{hint}', exit_code=1) from None


__all__ = ['repair_bag']
