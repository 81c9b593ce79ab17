"""The three rings, checked on the source: core never imports ROS, nothing imports upward.

* core (erva_ros/core): plain Python -- no rclpy, no message package, not even inside a
  function or through importlib;
* ros (erva_ros/ros, erva_ros/nodes): may import core and ROS -- the only ring that
  imports rclpy or a message package;
* session (erva_ros/session) and the CLI (erva_ros/commands, erva_ros/cli.py): built on
  core and ros (through erva_ros.ros, never rclpy itself); the CLI may import the
  session, never the other way round.
"""

import ast
import os

import pytest

from conftest import REPO

PKG = os.path.join(REPO, 'erva_ros')
#: What each ring may import of erva_ros (besides itself).
ALLOWED = {
    'core': {'core'},
    'ros': {'core', 'ros'},
    'session': {'core', 'ros', 'session'},
    'cli': {'core', 'ros', 'session', 'cli'},
}


def ring_of(module: str) -> str:
    """Return the ring of a dotted erva_ros module name."""
    parts = module.split('.')
    if len(parts) == 1 or parts[1].startswith('__'):
        return 'core'                       # the package itself: the version only
    return {'core': 'core', 'ros': 'ros', 'nodes': 'ros', 'session': 'session',
            'commands': 'cli', 'cli': 'cli'}[parts[1]]


def is_ros_package(name: str) -> bool:
    top = name.split('.')[0]
    return (top in ('rclpy', 'ament_index_python', 'launch', 'launch_ros')
            or top.endswith(('_msgs', '_interfaces', '_srvs'))
            or top.startswith(('rosidl', 'rmw')))


def imports_of(path: str, module: str):
    """Yield every module ``path`` imports, at any depth, and importlib.import_module('...')."""
    tree = ast.parse(open(path, encoding='utf-8').read(), path)
    package = module if path.endswith('__init__.py') else module.rsplit('.', 1)[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                parts = package.split('.')
                base = '.'.join(parts[:len(parts) - node.level + 1] + ([base] if base else []))
            yield base, node.lineno
            for alias in node.names:            # from erva_ros import session -> a module
                yield f'{base}.{alias.name}', node.lineno
        elif (isinstance(node, ast.Call) and getattr(node.func, 'attr', '') == 'import_module'
              and node.args and isinstance(node.args[0], (ast.Constant, ast.JoinedStr))):
            arg = node.args[0]
            text = arg.value if isinstance(arg, ast.Constant) else ''.join(
                v.value if isinstance(v, ast.Constant) else '{}' for v in arg.values)
            yield text, node.lineno


def modules():
    for dirpath, _, files in os.walk(PKG):
        for f in sorted(files):
            if f.endswith('.py'):
                path = os.path.join(dirpath, f)
                rel = os.path.relpath(path, REPO)[:-3].replace(os.sep, '.')
                yield path, rel[:-len('.__init__')] if rel.endswith('.__init__') else rel


def violations():
    out = []
    for path, module in modules():
        ring = ring_of(module)
        for name, line in imports_of(path, module):
            where = f'{os.path.relpath(path, REPO)}:{line}'
            if ring != 'ros' and (is_ros_package(name) or name.startswith('{}')):
                out.append(f'{where}: {ring} imports {name}')
            if name.startswith('erva_ros.') and ring_of(name) not in ALLOWED[ring]:
                out.append(f'{where}: {ring} imports {name} ({ring_of(name)}, upward)')
    return sorted(set(out))


def test_the_rings_hold():
    assert violations() == []


def test_the_rings_are_folders():
    entries = {e for e in os.listdir(PKG) if not e.startswith(('.', '__pycache__'))}
    assert entries == {'__init__.py', 'cli.py', 'core', 'ros', 'nodes', 'session', 'commands'}


@pytest.mark.parametrize('source, found', [
    ('import rclpy\n', 'core imports rclpy'),
    ('def f():\n    from sensor_msgs.msg import JointState\n', 'core imports sensor_msgs.msg'),
    ('import importlib\nimportlib.import_module(f"{p}.msg")\n', 'core imports {}.msg'),
    ('from erva_ros.session import monitor\n', 'core imports erva_ros.session'),
    ('def f():\n    import rclpy\n', 'session imports rclpy'),
    ('from trajectory_msgs.msg import JointTrajectory\n', 'cli imports trajectory_msgs.msg'),
])
def test_the_check_finds_a_violation(tmp_path, monkeypatch, source, found):
    ring = found.split()[0]
    folder = {'cli': 'commands'}.get(ring, ring)
    pkg = tmp_path / 'erva_ros'
    (pkg / folder).mkdir(parents=True)
    (pkg / folder / 'bad.py').write_text(source)
    monkeypatch.setattr(__import__(__name__), 'PKG', str(pkg))
    monkeypatch.setattr(__import__(__name__), 'REPO', str(tmp_path))
    assert any(found in v for v in violations()), violations()


def import_graph():
    """Return {module: {erva_ros modules it imports}}, imports inside functions included."""
    known = {module: path for path, module in modules()}
    graph = {}
    for module, path in known.items():
        out = set()
        for name, _ in imports_of(path, module):
            while name and name not in known:       # a name from a module: that module
                name = name.rpartition('.')[0]
            if name and name != module and not module.startswith(name + '.'):
                out.add(name)                       # (a package's own __init__: its face)
        graph[module] = out
    return graph


def circles(graph):
    """Return the import circles of ``graph``: its strongly connected parts of two or more."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = []
            while not part or part[-1] != v:
                part.append(stack.pop())
                on.discard(part[-1])
            if len(part) > 1:
                out.append(sorted(part))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_module_imports_itself_through_others():
    # Counting the imports inside functions, which would otherwise hide a circle.
    assert circles(import_graph()) == []


def test_the_circle_check_finds_a_circle_behind_an_import_in_a_function(tmp_path, monkeypatch):
    pkg = tmp_path / 'erva_ros' / 'core'
    pkg.mkdir(parents=True)
    (pkg / 'a.py').write_text('from erva_ros.core.b import x\n')
    (pkg / 'b.py').write_text('x = 1\n\n\ndef f():\n    from erva_ros.core.a import y\n')
    monkeypatch.setattr(__import__(__name__), 'PKG', str(tmp_path / 'erva_ros'))
    monkeypatch.setattr(__import__(__name__), 'REPO', str(tmp_path))
    assert circles(import_graph()) == [['erva_ros.core.a', 'erva_ros.core.b']]


#: Optional dependencies (extras of setup.py, and ROS): a module may import one of them, or
#: a module of ours that needs one, inside the function that uses it.
OPTIONAL = ('rclpy', 'rosidl_runtime_py', 'launch', 'launch_ros', 'ament_index_python',
            'foxglove', 'dask', 'distributed', 'psycopg', 'matplotlib', 'can', 'cantools',
            'argcomplete')


def _optional(name: str) -> bool:
    top = name.split('.')[0]
    return top in OPTIONAL or is_ros_package(name)


def _parents(tree):
    out = {}
    for node in ast.walk(tree):
        for child in ast.iter_child_nodes(node):
            out[child] = node
    return out


def _names(node):
    if isinstance(node, ast.ImportFrom):
        return [node.module or ''] + [f'{node.module}.{a.name}' for a in node.names]
    return [a.name for a in node.names]


def late_imports():
    """Return the imports made inside a function that no rule allows (docs/design.md).

    Allowed: in the CLI (commands/, cli.py: a command imports what it runs when it runs,
    so `erva --help` and the option tables stay light); an optional dependency, or a
    module of ours that needs one at its top (found here); and an import inside a ``try``
    that handles ImportError (an availability check).
    """
    known = {module: path for path, module in modules()}
    trees = {m: ast.parse(open(p, encoding='utf-8').read(), p) for m, p in known.items()}

    def ours(name):
        while name and name not in known:
            name = name.rpartition('.')[0]
        return name
    needs = set()                   # our modules that import an optional one at their top
    grew = True
    while grew:
        grew = False
        for m, tree in trees.items():
            if m in needs:
                continue
            for node in tree.body:
                if isinstance(node, (ast.Import, ast.ImportFrom)) and any(
                        _optional(n) or ours(n) in needs - {m} for n in _names(node)
                        if not n.startswith('erva_ros') or ours(n)):
                    needs.add(m)
                    grew = True
                    break
    out = []
    for m, tree in trees.items():
        if ring_of(m) == 'cli':
            continue
        parent = _parents(tree)
        for node in ast.walk(tree):
            if not isinstance(node, (ast.Import, ast.ImportFrom)) or node in tree.body:
                continue
            chain, up = [], parent.get(node)
            while up is not None:
                chain.append(up)
                up = parent.get(up)
            if not any(isinstance(u, (ast.FunctionDef, ast.AsyncFunctionDef)) for u in chain):
                continue
            names = _names(node)
            if any(_optional(n) or (n.startswith('erva_ros') and ours(n) in needs)
                   for n in names):
                continue
            if any(isinstance(u, ast.Try) and any(
                    'ImportError' in ast.dump(h.type or ast.Name('')) for h in u.handlers)
                    for u in chain):
                continue
            out.append(f'{os.path.relpath(known[m], REPO)}:{node.lineno}: {names[0]}')
    return sorted(out)


def test_imports_are_at_the_top_but_optional_ones():
    assert late_imports() == []


def test_the_late_import_check_finds_one(tmp_path, monkeypatch):
    pkg = tmp_path / 'erva_ros' / 'core'
    pkg.mkdir(parents=True)
    (pkg / 'a.py').write_text('def f():\n    import json\n    import matplotlib\n')
    (pkg / 'b.py').write_text('import cantools\n')
    (pkg / 'c.py').write_text('def f():\n    from erva_ros.core import b\n'
                              '    from erva_ros.core.a import f\n')
    monkeypatch.setattr(__import__(__name__), 'PKG', str(tmp_path / 'erva_ros'))
    monkeypatch.setattr(__import__(__name__), 'REPO', str(tmp_path))
    assert late_imports() == ['erva_ros/core/a.py:2: json',
                              'erva_ros/core/c.py:3: erva_ros.core.a']


def folder_graph(graph):
    """Return {folder: {folders its modules import}} of a module graph.

    A folder and its subfolders contain each other: no edge between them.
    """
    folder = {m: os.path.dirname(os.path.relpath(p, REPO)) for p, m in modules()}
    out = {}
    for module, imported in graph.items():
        here = folder[module]
        for other in imported:
            there = folder[other]
            if not (here == there or here.startswith(there + '/')
                    or there.startswith(here + '/')):
                out.setdefault(here, set()).add(there)
    return out


def test_no_folder_imports_itself_through_others():
    assert circles(folder_graph(import_graph())) == []


def test_the_folder_check_finds_a_circle(tmp_path, monkeypatch):
    for folder, source in (('a', 'from erva_ros.core.b.y import x\n'),
                           ('b', 'x = 1\n\n\ndef f():\n    from erva_ros.core.a.z import w\n')):
        pkg = tmp_path / 'erva_ros' / 'core' / folder
        pkg.mkdir(parents=True)
        (pkg / ('z.py' if folder == 'a' else 'y.py')).write_text(source)
    monkeypatch.setattr(__import__(__name__), 'PKG', str(tmp_path / 'erva_ros'))
    monkeypatch.setattr(__import__(__name__), 'REPO', str(tmp_path))
    assert circles(folder_graph(import_graph())) == [['erva_ros/core/a', 'erva_ros/core/b']]
