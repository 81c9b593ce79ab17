"""One contract between nodes and session, checked on the source.

* The session reads what nodes report as typed reports (erva_ros/core/reports.py), never
  by a diagnostic key: no ``published:``/``count:`` strings, no key lookups of status
  values, no number parsing of them in erva_ros/session.
* Every loop message is decoded by one function of erva_ros/core/contract.py: nothing
  else deserializes a message or reads CDR.
* Every node is built on the skeleton (erva_ros/ros/loop_node.py) and holds its wiring only.
"""

import ast
import os
import re

import pytest

from conftest import REPO

PKG = os.path.join(REPO, 'erva_ros')

#: What reading a node's report by key would look like.
KEY_LOOKUPS = re.compile(r"""['"](published|subscribers|count|publishers|offered):|"""
                         r"""\bvalues\.get\(|\bvalue_(int|float)\(|\bdiag_values\b|"""
                         r"""\bparse_status\b|['"]status_seq['"]""")


def _sources(*parts):
    top = os.path.join(PKG, *parts)
    for dirpath, _, files in os.walk(top):
        for name in sorted(files):
            if name.endswith('.py'):
                path = os.path.join(dirpath, name)
                yield os.path.relpath(path, REPO), open(path, encoding='utf-8').read()


def test_the_session_reads_typed_reports_never_diagnostic_keys():
    found = [f'{path}:{text[:m.start()].count(chr(10)) + 1}: {m.group(0)}'
             for path, text in _sources('session') for m in KEY_LOOKUPS.finditer(text)]
    assert found == []


def test_the_lookup_pattern_finds_what_it_should():
    # The check above can fail: this is what it refuses.
    for bad in ("v = values.get('commands')", "n = status['published:/erva/state']",
                "value_int(x)", "r.diag_values('nmpc_node')"):
        assert KEY_LOOKUPS.search(bad), bad


def test_one_decoder_per_message_family():
    # (core/bag/reader.py reads MCAP records, not messages.)
    homes = {'erva_ros/core/contract.py', 'erva_ros/core/wire.py'}
    offenders = []
    for path, text in _sources():
        if path in homes:
            continue
        for needle in ('deserialize_message', 'import Reader', 'wire.Reader'):
            if needle in text:
                offenders.append(f'{path}: {needle}')
    assert offenders == []


@pytest.mark.parametrize('name', sorted(f[:-3] for f in os.listdir(os.path.join(PKG, 'nodes'))
                                        if f.endswith('_node.py')))
def test_nodes_are_built_on_the_skeleton_and_hold_wiring_only(name):
    path = os.path.join(PKG, 'nodes', f'{name}.py')
    text = open(path, encoding='utf-8').read()
    tree = ast.parse(text)
    classes = [n for n in tree.body if isinstance(n, ast.ClassDef)]
    assert [c.bases[0].id for c in classes] == ['LoopNode'], name
    assert len(text.splitlines()) <= 200, name       # wiring: the logic is in core/
