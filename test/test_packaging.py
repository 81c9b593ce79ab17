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
