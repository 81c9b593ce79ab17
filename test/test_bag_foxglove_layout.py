"""config/foxglove_layout.json only refers to topics and fields that sessions contain."""

import importlib
import json
import os
import re

from conftest import REPO

from erva_ros.core import topics as contract

LAYOUT = os.path.join(REPO, 'config', 'foxglove_layout.json')
SEGMENT = re.compile(r'^([A-Za-z_][A-Za-z0-9_]*)(?:\[(-?\d+|:)\])?$')   # [:]: every element


def _class(type_name):
    pkg, *_, name = type_name.split('/')
    return getattr(importlib.import_module(f'{pkg}.msg'), name)


def _field_type(type_name, path):
    """Return the type at ``path`` (e.g. 'points[0].positions[0]') inside ``type_name``."""
    current = type_name
    for segment in path.split('.'):
        m = SEGMENT.match(segment)
        assert m, f'bad path segment {segment!r}'
        fields = _class(current).get_fields_and_field_types()
        assert m.group(1) in fields, f'{current} has no field {m.group(1)}'
        current = fields[m.group(1)]
        if m.group(2) is not None:
            assert current.startswith('sequence<'), f'{segment} indexes a non-sequence'
            current = current[len('sequence<'):-1]
    return current


def _topic_and_path(value):
    topic, _, path = value.partition('.')
    return topic, path


def test_every_panel_uses_session_topics_and_existing_fields():
    layout = json.load(open(LAYOUT))
    scripts = {}
    for script in layout['userNodes'].values():
        src = script['sourceCode']
        inputs = json.loads(re.search(r'inputs = (\[.*?\]);', src).group(1))
        output = re.search(r'output = "([^"]+)"', src).group(1)
        assert all(t in contract.TOPIC_TYPES for t in inputs), inputs
        fields = re.search(r'type Output = \{(.*?)\}', src).group(1)
        scripts[output] = {f.split(':')[0].strip() for f in fields.split(';') if f.strip()}
    used = set()
    for panel_id, config in layout['configById'].items():
        values = [p['value'] for p in config.get('paths', [])]
        values += [config[k] for k in ('topicPath', 'topicToRender') if k in config]
        assert values, panel_id
        for value in values:
            topic, path = _topic_and_path(value)
            used.add(topic)
            if topic in scripts:
                assert path in scripts[topic], value
                continue
            assert topic in contract.TOPIC_TYPES, f'{panel_id}: {topic} is not a session topic'
            if path:
                leaf = _field_type(contract.TOPIC_TYPES[topic], path)
                assert leaf in ('double', 'float'), f'{value} is a {leaf}, not a number'
    # Every panel of the mosaic exists, and the main topics are shown.
    ids = re.findall(r'"([A-Za-z]+![a-z-]+)"', json.dumps(layout['layout']))
    assert set(ids) == set(layout['configById'])
    assert {'/erva/sprung_accel', '/erva/damping_cmd', '/erva/road/height',
            '/erva/road/preview', '/diagnostics', '/erva/state'} <= used
    # The paper's view: solve time and deadline misses (a script on the NMPC's status).
    assert {'/studio_script/erva/power', '/studio_script/erva/nmpc'} <= used
