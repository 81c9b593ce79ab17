"""Recover a bag whose recorder died: ``erva bag repair DIR`` (like ``ros2 bag reindex``).

A recorder killed with SIGKILL (or a full disk) leaves an MCAP file without summary
and indexes, perhaps ending inside a chunk, and no metadata.yaml.  Every chunk that
was flushed is intact; repair copies all readable records (schemas, channels, session
metadata, messages up to the last complete chunk) into a new, properly closed file in
the same place, keeps the original as ``<file>.orig`` unless told not to, and writes
metadata.yaml.  A bag that is complete but lacks metadata.yaml only gets the file.
"""

import os
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


def repair_bag(path: str, keep_original: bool = True) -> Dict:
    """Make ``path`` a complete, indexed bag with metadata.yaml; return what was done."""
    from mcap.writer import CompressionType, Writer

    bag_dir, mcap_path = _mcap_of(path)
    scan = scan_mcap(mcap_path)
    file_name = os.path.basename(mcap_path)
    info = _topics_and_times(scan)
    custom = {}
    for rec in scan.metadata:
        if rec.name == 'erva_session':
            custom.update({k: v for k, v in rec.metadata.items()})
    meta = bag_meta.bag_metadata(file_name, info['topics'], info['start'], info['end'],
                                 custom or None)
    result = {'bag': bag_dir, 'file': mcap_path, 'messages': len(scan.messages),
              'topics': {t['topic_metadata']['name']: t['message_count']
                         for t in info['topics']},
              'was_complete': scan.complete, 'stopped_at': scan.stopped_at,
              'start_ns': info['start'], 'end_ns': info['end'], 'original': None}
    if scan.complete:
        bag_meta.write_metadata(bag_dir, meta)
        result['action'] = 'wrote metadata.yaml (the MCAP file was complete)'
        return result

    tmp = mcap_path + '.repair'
    try:
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
            result['original'] = mcap_path + '.orig'
            os.replace(mcap_path, result['original'])
        os.replace(tmp, mcap_path)
    except OSError as exc:
        try:
            os.remove(tmp)
        except OSError:
            pass
        raise BagError(f'cannot write the repaired bag in {bag_dir}: '
                       f'{exc.strerror or exc}') from None
    bag_meta.write_metadata(bag_dir, meta)
    result['action'] = 'rewrote the MCAP file with summary and indexes, wrote metadata.yaml'
    return result


__all__ = ['repair_bag']
