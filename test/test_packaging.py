"""ROS packaging: colcon build in a throw-away workspace installs what `ros2 run` needs."""

import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET

import pytest

from conftest import REPO

SETUP_NODES = ['plant_sim_node', 'road_preview_node', 'nmpc_node', 'recorder_node',
               'ecu_bridge_node', 'state_estimator_node', 'foxglove_node']


def test_package_xml_is_format3_ament_python():
    root = ET.parse(os.path.join(REPO, 'package.xml')).getroot()
    assert root.get('format') == '3'
    assert root.findtext('name') == 'erva_ros'
    assert root.find('export/build_type').text == 'ament_python'
    deps = {e.text for e in root.findall('exec_depend')}
    assert {'rclpy', 'std_msgs', 'sensor_msgs', 'diagnostic_msgs', 'trajectory_msgs'} <= deps


def test_every_entry_point_module_exists():
    import importlib.util
    for name in SETUP_NODES:
        assert importlib.util.find_spec(f'erva_ros.nodes.{name}') is not None, name


@pytest.mark.slow
def test_colcon_build_installs_nodes_config_and_launch(tmp_path):
    colcon = shutil.which('colcon') or os.path.join(os.path.dirname(sys.executable), 'colcon')
    if not os.path.exists(colcon):
        pytest.skip('colcon not installed (pip install .[test])')
    src = tmp_path / 'src' / 'erva_ros'
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(
        '.git', '.venv', 'venv', 'build', 'install', 'log', '__pycache__', '*.egg-info',
        '.pytest_cache', 'bags', 'out'))
    env = dict(os.environ, AMENT_PREFIX_PATH=sys.prefix)
    proc = subprocess.run([colcon, 'build', '--event-handlers', 'console_direct-'],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    inst = tmp_path / 'install' / 'erva_ros'
    share = inst / 'share' / 'erva_ros'
    assert (share / 'package.xml').is_file()
    assert (share / 'config' / 'erva_paper.yaml').is_file()
    for cfg in os.listdir(os.path.join(REPO, 'config')):
        assert (share / 'config' / cfg).is_file(), cfg
    for launch in os.listdir(os.path.join(REPO, 'launch')):
        assert (share / 'launch' / launch).is_file(), launch
    assert (inst / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'erva_ros').exists()
    for exe in SETUP_NODES + ['erva']:
        path = inst / 'lib' / 'erva_ros' / exe
        assert path.is_file() and os.access(path, os.X_OK), exe
    # The installed tool runs from the install space alone (as after `source install/setup.bash`).
    site = next((inst / 'lib').glob('python3*/site-packages'))
    run = subprocess.run([sys.executable, str(inst / 'lib' / 'erva_ros' / 'erva'), '--help'],
                         env=dict(env, PYTHONPATH=str(site)), cwd=tmp_path,
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    assert 'usage: erva' in run.stdout


#: rosdep key (package.xml) of every third-party module erva_ros imports; None: no key,
#: installed with pip (README) or an optional extra.  Keys checked against rosdistro's
#: rosdep/python.yaml and jazzy/distribution.yaml.
ROSDEP_KEYS = {
    'rclpy': 'rclpy', 'rcl_interfaces': 'rcl_interfaces', 'std_msgs': 'std_msgs',
    'sensor_msgs': 'sensor_msgs', 'geometry_msgs': 'geometry_msgs',
    'trajectory_msgs': 'trajectory_msgs', 'diagnostic_msgs': 'diagnostic_msgs',
    'rosgraph_msgs': 'rosgraph_msgs', 'builtin_interfaces': 'builtin_interfaces',
    'lifecycle_msgs': 'lifecycle_msgs', 'ament_index_python': 'ament_index_python',
    'rosidl_parser': 'rosidl_parser', 'launch': 'launch', 'launch_ros': 'launch_ros',
    'numpy': 'python3-numpy', 'yaml': 'python3-yaml', 'matplotlib': 'python3-matplotlib',
    'can': 'python3-can', 'argcomplete': 'python3-argcomplete',
    'casadi': 'casadi-pip', 'cantools': 'python3-cantools-pip',
    'mcap': None,                            # no key: pip install mcap
    'foxglove': None,                        # no key: pip install foxglove-sdk
    'websockets': 'python3-websockets',      # extra erva_ros[foxglove]: the bench's viewer
    'distributed': None,                     # extra erva_ros[dask]
    'psycopg': None,                         # extra erva_ros[fleet] (no rosdep key found)
}


def _imported_modules():
    """Return the top-level third-party modules imported anywhere in erva_ros and launch/."""
    import ast
    names = set()
    for folder in ('erva_ros', 'launch'):
        for base, _, files in os.walk(os.path.join(REPO, folder)):
            for f in files:
                if not f.endswith('.py'):
                    continue
                with open(os.path.join(base, f), encoding='utf-8') as fh:
                    tree = ast.parse(fh.read())
                for node in ast.walk(tree):
                    if isinstance(node, ast.Import):
                        names.update(a.name.split('.')[0] for a in node.names)
                    elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                        names.add(node.module.split('.')[0])
    return {n for n in names if n not in sys.stdlib_module_names and n != 'erva_ros'}


def test_every_imported_package_is_declared_with_its_rosdep_key():
    deps = {e.text for e in ET.parse(os.path.join(REPO, 'package.xml')).getroot()
            .findall('exec_depend')}
    imported = _imported_modules()
    assert imported <= set(ROSDEP_KEYS), f'no decision for {imported - set(ROSDEP_KEYS)}'
    missing = {ROSDEP_KEYS[m] for m in imported if ROSDEP_KEYS[m]} - deps
    assert not missing, f'package.xml lacks <exec_depend> {sorted(missing)}'
    # The pip-installed ones with a rosdistro key use it (not a comment saying there is none);
    # those without one are named for pip in a comment.
    assert {'casadi-pip', 'python3-cantools-pip', 'rosidl_parser'} <= deps
    with open(os.path.join(REPO, 'package.xml'), encoding='utf-8') as fh:
        assert 'pip install mcap foxglove-sdk' in fh.read()


def test_every_requirement_is_pinned_and_the_viewer_library_is_in_its_extra():
    """CI installs from scratch: each requirement of setup.py has an exact pin."""
    import importlib.metadata
    import re
    pins = {}
    with open(os.path.join(REPO, '.ci', 'constraints.txt'), encoding='utf-8') as fh:
        for line in fh:
            name, _, version = line.strip().partition('==')
            pins[re.sub(r'[-_.]+', '-', name).lower()] = version
    requires = importlib.metadata.requires('erva_ros')
    for req in requires:
        name = re.sub(r'[-_.]+', '-', re.split(r'[\[;<>=! ]', req)[0]).lower()
        if name != 'setuptools':
            assert pins.get(name), f'{req}: no pin in .ci/constraints.txt'
    assert 'argcomplete' in requires                       # `erva` completion, always
    assert 'websockets; extra == "foxglove"' in requires   # the benchmark's viewer
