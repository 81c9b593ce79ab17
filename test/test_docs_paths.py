"""Every repository path the docs, docstrings and comments name exists.

Read: docs/*.md, README.md, bags/README.md, and the comments and docstrings of every
module in erva_ros/, test/ and launch/.  A *name* is, and nothing else is (so that prose
and output file names never count):

* a path from a top folder of the repository or of the package -- ``erva_ros/``,
  ``core/``, ``ros/``, ``nodes/``, ``session/``, ``commands/``, ``config/``, ``docs/``,
  ``test/``, ``launch/``, ``bags/``, ``.ci/`` -- found relative to the repository or to
  erva_ros/.  It may end in ``/`` (a folder), hold a ``*`` (a glob that must match), name
  a module without its ``.py``, or a module's attribute (``session/run/recording.record_topics``:
  the module exists and names ``record_topics``).  Placeholders (``<...>``) are skipped, and
  so are sessions below bags/ other than the tracked ``bags/sample`` and ``bags/README.md``
  (the rest of bags/ is ignored by git: what ``erva run`` writes);
* any other relative ``.py`` path (``hil/settings.py``), found relative to the
  repository, erva_ros/ or erva_ros/core/;
* a dotted module (``erva_ros.core.model.quarter_car``,
  ``erva_ros.core.controllers.make_controller``):
  the modules exist, and a first attribute is named in its module (a package: in its
  ``__init__.py``);
* a test file ``test_*.py``, optionally with ``::name`` (a def or class in it), and in the
  docs a test named in backticks (`` `test_...` ``): defined in test/;
* an upper-case Markdown name (``README.md``): in the repository's top folder;
* a bare module name in backticks (`` `warmup.py` ``, the docs' shorthand beside a path):
  some file of that name in the repository (outside .venv/ and .git/).
"""

import ast
import glob
import io
import os
import re
import tokenize

from conftest import REPO

PKG = os.path.join(REPO, 'erva_ros')
DOCS = ['README.md', 'bags/README.md'] + sorted(
    os.path.relpath(p, REPO) for p in glob.glob(os.path.join(REPO, 'docs', '*.md')))
CODE_DIRS = ('erva_ros', 'test', 'launch')
ROOTS = ('erva_ros', 'core', 'ros', 'nodes', 'session', 'commands', 'config', 'docs', 'test',
         'launch', 'bags', '.ci')
_NOT_AFTER = r'(?<![\w./:~$@-])'        # not inside a longer path, a URL or $(...)/...
ROOT_PATH = re.compile(_NOT_AFTER + r'((?:' + '|'.join(re.escape(r) for r in ROOTS)
                       + r')/[\w.*/<>-]*?)\.?(?:::(\w+))?(?![\w.*/<>-])')
PY_PATH = re.compile(_NOT_AFTER + r'((?:[\w-]+/)+\w+\.py)(?:::(\w+))?\b')
MODULE = re.compile(r'(?<![\w./-])(erva_ros(?:\.\w+)+)')
TEST_FILE = re.compile(_NOT_AFTER + r'(test_\w+\.py)(?:::(\w+))?\b')
TEST_NAME = re.compile(r'`(?:[\w/]+\.py::)?(test_\w+)(?:\[[^\]`]*\])?`')
UPPER_MD = re.compile(r'(?<![\w./-])([A-Z][A-Z_]*\.md)\b')
BARE_PY = re.compile(r'`([\w-]+\.py)(?:::\w+)?`')
#: bags/ holds sessions that commands write (ignored by git), except these.
TRACKED_BAGS = ('sample', 'README.md')


def code_texts(path):
    """Yield (line, text) of each comment and docstring of a Python file."""
    src = open(path, encoding='utf-8').read()
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT:
            yield tok.start[0], tok.string
    for node in ast.walk(ast.parse(src, path)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            doc = ast.get_docstring(node, clean=False)
            if doc is not None:
                yield node.body[0].lineno, doc


def sources():
    """Yield (file relative to the repository, line, text) of everything read."""
    for rel in DOCS:
        text = open(os.path.join(REPO, rel), encoding='utf-8').read()
        yield rel, 1, text
    for top in CODE_DIRS:
        for path in sorted(glob.glob(os.path.join(REPO, top, '**', '*.py'), recursive=True)):
            for line, text in code_texts(path):
                yield os.path.relpath(path, REPO), line, text


def _names(path, name):
    """Whether the file (or package ``__init__.py``) at ``path`` names ``name``."""
    if os.path.isdir(path):
        path = os.path.join(path, '__init__.py')
    if not os.path.isfile(path):
        return False
    text = open(path, encoding='utf-8').read()
    return re.search(r'\b(def|class)\s+' + name + r'\b|\b' + name + r'\b', text) is not None


def _defines(path, name):
    text = open(path, encoding='utf-8').read()
    return re.search(r'^\s*(?:async\s+)?(?:def|class)\s+' + name + r'\b', text, re.M) is not None


def _find(rel, bases):
    """Return the existing path ``rel`` names under one of ``bases``, else None."""
    for base in bases:
        full = os.path.join(base, rel)
        if '*' in rel:
            if glob.glob(full):
                return full
        elif os.path.exists(full) and (not rel.endswith('/') or os.path.isdir(full)):
            return full
    return None


def check_root_path(token, test=None):
    """Return why a root path does not exist, or None if it does (or is not checked)."""
    if '<' in token or '>' in token:
        return None                                     # a placeholder
    if token.startswith('bags/') and token[5:] and token[5:].split('/')[0] not in TRACKED_BAGS:
        return None                                     # a session some command writes
    bases = (REPO, PKG)
    found = _find(token, bases) or _find(token + '.py', bases)
    head, _, attr = token.rpartition('/')[2].partition('.')
    if found is None and attr and not re.fullmatch(r'[\w.]*\.(py|md|ya?ml|xml|json|dbc|txt|'
                                                   r'mcap|sh|csv|toml|cfg|png)', '.' + attr):
        stem = token.rsplit('/', 1)[0] + '/' + head if '/' in token else head
        module = _find(stem + '.py', bases) or _find(stem, bases)
        if module is not None:
            return None if _names(module, attr.split('.')[0]) else (
                f'{token}: {os.path.relpath(module, REPO)} does not name {attr.split(".")[0]}')
    if found is None:
        return f'{token}: no such file or folder'
    if test and not (found.endswith('.py') and _defines(found, test)):
        return f'{token}::{test}: not defined there'
    return None


def check_py_path(token, test=None):
    """Return why another relative .py path does not exist, or None."""
    if token.split('/')[0] in ROOTS:
        return None                                     # check_root_path's
    found = _find(token, (REPO, PKG, os.path.join(PKG, 'core')))
    if found is None:
        return f'{token}: no such module'
    if test and not _defines(found, test):
        return f'{token}::{test}: not defined there'
    return None


def check_module(dotted):
    """Return why a dotted erva_ros module (and its first attribute) does not exist."""
    path = REPO
    for i, part in enumerate(dotted.split('.')):
        if os.path.isdir(os.path.join(path, part)):
            path = os.path.join(path, part)
        elif os.path.isfile(os.path.join(path, part + '.py')) and os.path.isdir(path):
            path = os.path.join(path, part + '.py')
        elif i == 0 or not _names(path, part):
            return f'{dotted}: {part} not found in {os.path.relpath(path, REPO)}'
        else:
            return None
    return None


def check_test_file(name, test=None):
    path = os.path.join(REPO, 'test', name)
    if not os.path.isfile(path):
        return f'{name}: no such test file'
    if test and not _defines(path, test):
        return f'{name}::{test}: not defined there'
    return None


def _all_tests():
    tests = set()
    for path in glob.glob(os.path.join(REPO, 'test', '*.py')):
        tests.update(re.findall(r'^\s*def (test_\w+)', open(path, encoding='utf-8').read(),
                                re.M))
    return tests


def _py_basenames():
    names = set()
    for dirpath, dirs, files in os.walk(REPO):
        dirs[:] = [d for d in dirs if d not in ('.venv', '.git', 'build', 'install')]
        names.update(f for f in files if f.endswith('.py'))
    return names


def problems(items, known=frozenset()):
    """Return (missing names as 'file:line: why', known entries used) for the given texts."""
    missing, used, tests, basenames = [], set(), None, None
    for rel, line, text in items:
        found = []
        for m in ROOT_PATH.finditer(text):
            found.append((m, check_root_path(*m.groups())))
        for m in PY_PATH.finditer(text):
            found.append((m, check_py_path(*m.groups())))
        for m in MODULE.finditer(text):
            found.append((m, check_module(m.group(1))))
        for m in TEST_FILE.finditer(text):
            found.append((m, check_test_file(*m.groups())))
        for m in UPPER_MD.finditer(text):
            ok = os.path.isfile(os.path.join(REPO, m.group(1)))
            found.append((m, None if ok else f'{m.group(1)}: not in the repository'))
        for m in BARE_PY.finditer(text):
            basenames = _py_basenames() if basenames is None else basenames
            if m.group(1) not in basenames and not m.group(1).startswith('test_'):
                found.append((m, f'{m.group(1)}: no file of that name'))
        if rel.endswith('.md'):
            tests = _all_tests() if tests is None else tests
            for m in TEST_NAME.finditer(text):
                if m.group(1) not in tests and not os.path.isfile(
                        os.path.join(REPO, 'test', m.group(1) + '.py')):
                    found.append((m, f'{m.group(1)}: no such test'))
        for m, why in found:
            if why is None:
                continue
            if (rel, m.group(1)) in known:
                used.add((rel, m.group(1)))
            else:
                missing.append(f'{rel}:{line + text.count(chr(10), 0, m.start())}: {why}')
    return missing, used


def test_every_named_path_exists():
    missing, _ = problems(sources())
    assert not missing, 'named but missing:\n' + '\n'.join(missing)


def test_the_check_finds_what_is_missing():
    # Each kind of name, once present and once missing: the check must tell them apart.
    good = ('`erva_ros/core/model/quarter_car.py`, core/loop/, ros/runtime, config/*.yaml, '
            'session/run/recording.record_topics, test/test_model.py::test_plant_integrator_'
            'converges, erva_ros.core.controllers.make_controller, hil/settings.py, '
            'test_rings.py, README.md, bags/<session>, bags/20261122T101500Z_paper, '
            '`test_flake8`, https://example.org/live/x.py, docs/model.md, `warmup.py`.')
    assert problems([('docs/x.md', 1, good)]) == ([], set())
    bad = ['erva_ros/core/modle.py', 'core/loops/', 'ros/runtimes', 'config/*.yml',
           'session/run/recording.record_topic', 'test/test_model.py::test_nothing',
           'erva_ros.core.controllers.make_controler', 'live/realtime.py', 'test_ring.py',
           'NOTE.md', 'bags/sample/sampel_0.mcap', '`test_flake9`', '`cdr.py`']
    for name in bad:
        missing, _ = problems([('docs/x.md', 1, f'see {name} here')])
        assert len(missing) == 1, (name, missing)
    missing, used = problems([('erva_ros/a.py', 3, 'live/realtime.py')],
                             {('erva_ros/a.py', 'live/realtime.py')})
    assert missing == [] and used == {('erva_ros/a.py', 'live/realtime.py')}
