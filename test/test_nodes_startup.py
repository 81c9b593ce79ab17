"""Node start-up: a bad parameter stops a node with one clear line, as `ros2 run` users see it.

The -p values come after ``--params-file config/live.yaml``, so these also check that a
command-line value overrides the file (live.yaml keeps everything in ``/**`` for that).
"""

import os
import shutil
import subprocess
import sys

import pytest

from conftest import REPO, ros_env

PAPER = os.path.join(REPO, 'config', 'erva_paper.yaml')
LIVE = os.path.join(REPO, 'config', 'live.yaml')

CASES = [
    ('plant_sim_node', ['-p', 'M_us:=0.0'],
     "plant_sim_node: error: parameter 'M_us' = 0.0 is out of range; allowed [1, 1000] kg"),
    ('plant_sim_node', ['-p', 'mode:=fast'],
     "plant_sim_node: error: parameter 'mode' = 'fast' is not allowed; choose one of "
     'realtime, lockstep'),
    ('road_preview_node', ['-p', 'road:=moon'],
     "road_preview_node: error: parameter 'road' = 'moon' is not allowed"),
    ('road_preview_node', ['-p', 'preview_steps:=0'],
     "road_preview_node: error: parameter 'preview_steps' = 0 is out of range"),
    ('nmpc_node', ['-p', 'alpha1:=-1.0'],
     "nmpc_node: error: parameter 'alpha1' = -1.0 is out of range; allowed [0, 1e+06]"),
    ('nmpc_node', ['-p', 'controller:=lqr'],
     "nmpc_node: error: parameter 'controller' = 'lqr' is not allowed"),
]


def _exe(name):
    # The console script as `ros2 run erva_ros <name>` would start it, when installed.
    script = shutil.which(name, path=os.path.dirname(sys.executable))
    return [script] if script else [sys.executable, '-m', f'erva_ros.nodes.{name}']


@pytest.mark.ros
def test_bad_parameters_stop_each_node_with_one_line():
    procs = []
    for name, params, _ in CASES:
        argv = _exe(name) + ['--ros-args', '-r', '__ns:=/erva_t_start', '--params-file', PAPER,
                             '--params-file', LIVE, *params]
        procs.append(subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                      text=True, env=ros_env(), cwd=REPO))
    try:
        for (name, params, expected), proc in zip(CASES, procs):
            out, err = proc.communicate(timeout=120)
            assert proc.returncode == 2, (name, params, out, err)
            lines = [ln for ln in (out + err).splitlines() if ln.strip()]
            assert lines == [lines[0]] and lines[0].startswith(expected), (name, out + err)
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


@pytest.mark.parametrize('name', ['plant_sim_node', 'road_preview_node', 'nmpc_node'])
def test_nodes_import_without_side_effects(name):
    import importlib
    mod = importlib.import_module(f'erva_ros.nodes.{name}')
    assert callable(mod.main)
