"""Offered QoS profiles in rosbag2's form (bag format version 9), and back to rclpy QoS.

rosbag2 records, per topic, the QoS that each publisher offered (from the ROS graph,
``get_publishers_info_by_topic``).  Version 9 names the policies
(``rmw_qos_*_policy_to_str``: ``keep_last``, ``reliable``, ``volatile``,
``automatic``, ``unknown`` ...) and writes durations as ``{sec, nsec}`` with the
infinite duration as sec 9223372036, nsec 854775807.  The MCAP channel carries the
list as one YAML string (``offered_qos_profiles``); ``metadata.yaml`` as a YAML list.

For playback rosbag2 offers the recorded profile when all publishers agreed on the
policies that matter for compatibility, with history reset to keep-last 10
(``Rosbag2QoS::adapt_offer_to_recorded_offers``), and its default profile otherwise.
"""

from typing import Dict, List, Sequence

import yaml

#: rmw's "infinite" duration, as rosbag2 writes it.
INFINITE = {'sec': 9223372036, 'nsec': 854775807}
#: Key order of one profile, as rosbag2 writes it.
QOS_KEYS = ('history', 'depth', 'reliability', 'durability', 'deadline', 'lifespan',
            'liveliness', 'liveliness_lease_duration', 'avoid_ros_namespace_conventions')
#: History depth rosbag2 offers on playback (rmw_qos_profile_default.depth).
PLAYBACK_DEPTH = 10


def control_profile(depth: int = 10) -> Dict:
    """Return the loop's offered QoS (reliable, volatile, keep-last ``depth``) as a profile.

    What ``profile_to_dict(erva_ros.ros.qos.control_qos(depth))`` gives (tested), for
    writers of bags that run without ROS (the offline sessions).
    """
    zero = {'sec': 0, 'nsec': 0}
    return {'history': 'keep_last', 'depth': int(depth), 'reliability': 'reliable',
            'durability': 'volatile', 'deadline': dict(zero), 'lifespan': dict(zero),
            'liveliness': 'system_default', 'liveliness_lease_duration': dict(zero),
            'avoid_ros_namespace_conventions': False}


def _duration_dict(duration) -> Dict[str, int]:
    ns = int(duration.nanoseconds)
    return {'sec': ns // 1_000_000_000, 'nsec': ns % 1_000_000_000}


def profile_to_dict(qos) -> Dict:
    """Return an rclpy ``QoSProfile`` as rosbag2 (version 9) writes one offered profile."""
    return {
        'history': qos.history.name.lower(),
        'depth': int(qos.depth),
        'reliability': qos.reliability.name.lower(),
        'durability': qos.durability.name.lower(),
        'deadline': _duration_dict(qos.deadline),
        'lifespan': _duration_dict(qos.lifespan),
        'liveliness': qos.liveliness.name.lower(),
        'liveliness_lease_duration': _duration_dict(qos.liveliness_lease_duration),
        'avoid_ros_namespace_conventions': bool(qos.avoid_ros_namespace_conventions),
    }


def dump_profiles(profiles: Sequence[Dict], indent: int = 0) -> str:
    """Return ``profiles`` as yaml-cpp prints a sequence (the MCAP channel string form)."""
    if not profiles:
        return '[]'
    pad = ' ' * indent
    lines: List[str] = []
    for p in profiles:
        first = True
        for key in QOS_KEYS:
            value = p[key]
            lead = pad + ('- ' if first else '  ')
            first = False
            if isinstance(value, dict):
                lines.append(f'{lead}{key}:')
                lines.append(f'{pad}    sec: {int(value["sec"])}')
                lines.append(f'{pad}    nsec: {int(value["nsec"])}')
            elif isinstance(value, bool):
                lines.append(f'{lead}{key}: {"true" if value else "false"}')
            else:
                lines.append(f'{lead}{key}: {value}')
    return '\n'.join(lines)


def load_profiles(text) -> List[Dict]:
    """Parse an offered-QoS YAML string (or an already parsed list) into profile dicts."""
    data = yaml.safe_load(text) if isinstance(text, str) else text
    if data is None:
        return []
    if not isinstance(data, list) or not all(isinstance(p, dict) for p in data):
        raise ValueError('offered_qos_profiles is not a list of QoS profiles')
    return data


__all__ = ['control_profile', 'profile_to_dict', 'dump_profiles', 'load_profiles', 'INFINITE',
           'PLAYBACK_DEPTH']
