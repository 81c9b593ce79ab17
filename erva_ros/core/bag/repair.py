"""Recover a bag whose recorder died: ``erva bag repair DIR`` (like ``ros2 bag reindex``).

A recorder killed with SIGKILL (or a full disk) leaves an MCAP file without summary
and indexes, perhaps ending inside a chunk, and no metadata.yaml.  Every chunk that
was flushed is intact; repair copies all readable records (schemas, channels, session
metadata, messages up to the last complete chunk) into a new, properly closed file in
the same place, keeps the original as ``<file>.orig`` unless told not to, and writes
metadata.yaml.  A bag that is complete but lacks metadata.yaml only gets the file.
With ``out_dir`` the repaired bag is a new directory there and the original is not
touched: the way out when its own disk is full.
"""

import errno
import os
import shutil
from typing import Dict, Optional

from erva_ros import __version__
from erva_ros.core.bag import BagError
from erva_ros.core.bag import metadata as bag_meta
from erva_ros.core.bag.qos import load_profiles
from erva_ros.core.bag.reader import resolve_bag_path, scan_mcap
from erva_ros.core.bag.writer import PROFILE, ROSBAG2_RECORD


def _mcap_of(path: str):
    """Return (bag directory, .mcap path) without trusting a damaged metadata.yaml."""
    try:
        bag_dir, mcap_path, _ = resolve_bag_path(path)
        return bag_dir or os.path.dirname(os.path.abspath(mcap_path)), mcap_path
    except BagError:
        if not os.path.isdir(path):
            raise
        found = sorted(f for f in os.listdir(path) if f.endswith('.mcap'))
        if len(found) != 1:
            raise BagError(f'{path}: need exactly one .mcap file to repair, '
                           f'found {len(found)}') from None
        return path, os.path.join(path, found[0])


def _topics_and_times(scan) -> Dict:
    counts: Dict[int, int] = {}
    start: Optional[int] = None
    end: Optional[int] = None
    for m in scan.messages:
        counts[m.channel_id] = counts.get(m.channel_id, 0) + 1
        start = m.log_time if start is None else min(start, m.log_time)
        end = m.log_time if end is None else max(end, m.log_time)
    topics = []
    for cid, ch in scan.channels.items():
        schema = scan.schemas.get(ch.schema_id)
        try:
            qos = load_profiles(ch.metadata.get('offered_qos_profiles', ''))
        except Exception:  # noqa: BLE001 -- keep the topic, lose its QoS
            qos = []
        topics.append(bag_meta.topic_entry(ch.topic, schema.name if schema else '', qos,
                                           ch.metadata.get('topic_type_hash', ''),
                                           counts.get(cid, 0), ch.message_encoding))
    return {'topics': topics, 'start': start, 'end': end}


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

    ``out_dir``: write the repaired bag (its MCAP file, same name, and metadata.yaml) to
    that new or empty directory instead, leaving ``path`` as it is.
    """
    from mcap.writer import CompressionType, Writer

    bag_dir, mcap_path = _mcap_of(path)
    target = bag_dir if out_dir is None else _out_dir(out_dir, bag_dir)
    scan = scan_mcap(mcap_path)
    file_name = os.path.basename(mcap_path)
    target_file = os.path.join(target, file_name)
    info = _topics_and_times(scan)
    custom = {}
    for rec in scan.metadata:
        if rec.name == 'erva_session':
            custom.update({k: v for k, v in rec.metadata.items()})
    meta = bag_meta.bag_metadata(file_name, info['topics'], info['start'], info['end'],
                                 custom or None)
    result = {'bag': target, 'file': target_file, 'messages': len(scan.messages),
              'topics': {t['topic_metadata']['name']: t['message_count']
                         for t in info['topics']},
              'was_complete': scan.complete, 'stopped_at': scan.stopped_at,
              'start_ns': info['start'], 'end_ns': info['end'], 'original': None,
              'source': bag_dir}
    if scan.complete:
        if out_dir is not None:
            _write(target, lambda: shutil.copyfile(mcap_path, target_file), target_file)
        _write(target, lambda: bag_meta.write_metadata(target, meta))
        result['action'] = ('wrote metadata.yaml (the MCAP file was complete)' if out_dir is None
                            else 'copied the MCAP file (it was complete), wrote metadata.yaml')
        return result

    tmp = target_file + '.repair'

    def rewrite() -> None:
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
        if out_dir is None and keep_original:
            result['original'] = mcap_path + '.orig'
            os.replace(mcap_path, result['original'])
        os.replace(tmp, target_file)

    _write(target, rewrite, tmp)
    _write(target, lambda: bag_meta.write_metadata(target, meta))
    result['action'] = 'rewrote the MCAP file with summary and indexes, wrote metadata.yaml'
    return result


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
