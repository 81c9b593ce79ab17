"""`prediction` over real DDS: one per command, recorded, and reported by `erva report`.

A lock-step `erva run --record` with a command delay d > 0: nmpc_node publishes after
each damping_cmd its plan's prediction, stamped as the command.  The bag is read back
with the mcap package and its ROS 2 decoder (not erva_ros).  Over [t_k, t_{k+1}) the
plant applies exactly what the prediction assumed (the acting command, then u_k from
t_k + d, every command in time in lock-step), so one step ahead the predicted states
and z̈_s(t_{k+1}) (the damping acting then is u_k) equal the recorded ones to rounding;
further ahead the plans change and the errors are those of re-planning.
"""

import json
import os

import pytest

from conftest import REPO
from run_helpers import start_run

DELAY = 0.005
SAMPLE = os.path.join(REPO, 'bags', 'sample')      # an offline bag: no prediction


def _decoded(bag_dir, topics):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    mcap, = [f for f in os.listdir(bag_dir) if f.endswith('.mcap')]
    out = {t: [] for t in topics}
    with open(os.path.join(bag_dir, mcap), 'rb') as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _, channel, _, msg in reader.iter_decoded_messages(topics=topics):
            out[channel.topic].append(msg)
    return out


@pytest.fixture(scope='module')
def session(tmp_path_factory):
    """Return the summary of a 1 s lock-step session with d = 5 ms, recorded."""
    proc = start_run('--mode', 'lockstep', '--duration', 1, '--command-delay', DELAY,
                     '--record', tmp_path_factory.mktemp('prediction'), '--json')
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err[-3000:]
    return json.loads(out)


@pytest.mark.ros
def test_one_prediction_per_command_stamped_as_the_command(session):
    msgs = _decoded(session['bag'], ['/erva/damping_cmd', '/erva/prediction'])
    cmds, preds = msgs['/erva/damping_cmd'], msgs['/erva/prediction']
    assert len(cmds) == 51 and len(preds) == len(cmds)
    stamp = [(m.header.stamp.sec, m.header.stamp.nanosec) for m in cmds]
    assert [(m.header.stamp.sec, m.header.stamp.nanosec) for m in preds] == stamp
    names = ['z_s', 'zdot_s', 'z_us', 'zdot_us', 'z_d', 'zdot_d', 'sprung_accel', 'power']
    for m in preds:
        assert list(m.joint_names) == names and len(m.points) == 11
        assert all(len(p.positions) == len(names) for p in m.points)
        assert [p.time_from_start.nanosec for p in m.points] == [
            j * 20_000_000 for j in range(11)]


@pytest.mark.ros
def test_the_report_prints_the_errors_one_step_ahead_exact(session, erva, tmp_path):
    bag = session['bag']
    report = json.loads(erva('report', bag, '--json', '--out', tmp_path, check=True).stdout)
    pred = report['prediction']
    assert pred['messages'] == report['samples']['damping_cmd'] == 51
    assert pred['horizon'] == 10 and sorted(pred['steps'], key=int) == ['1', '5', '10']
    one = pred['steps']['1']
    # States x(t_0..t_50) and z̈_s(t_0..t_49) recorded; plans at t_0..t_50.
    for name in ('z_s', 'zdot_s', 'z_us', 'zdot_us', 'z_d', 'zdot_d', 'sprung_accel', 'power'):
        assert one[name]['samples'] == (49 if name in ('sprung_accel', 'power') else 50), name
        assert one[name]['max'] <= 1e-9, (name, one[name])
    far = pred['steps']['10']
    assert far['sprung_accel']['samples'] == 40 and far['sprung_accel']['max'] > 1e-6
    assert os.path.getsize(tmp_path / 'prediction.png') > 5000
    text = erva('report', bag, check=True).stdout
    assert 'prediction: 51 plans, horizon N = 10' in text
    assert [line.split(':')[0].strip() for line in text.splitlines()
            if line.startswith('  h = ')] == ['h =  1', 'h =  5', 'h = 10']


@pytest.mark.ros
def test_without_prediction_the_session_records_the_rest(tmp_path):
    live = tmp_path / 'live.yaml'
    live.write_text('/**:\n  ros__parameters:\n    publish_prediction: false\n')
    proc = start_run('--mode', 'lockstep', '--duration', 0.4, '--live', live,
                     '--record', tmp_path / 'bags', '--json')
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err[-3000:]
    msgs = _decoded(json.loads(out)['bag'], ['/erva/damping_cmd', '/erva/prediction'])
    assert len(msgs['/erva/damping_cmd']) == 21 and msgs['/erva/prediction'] == []


def test_a_bag_without_prediction_says_so_in_one_line(erva):
    text = erva('report', SAMPLE, check=True).stdout
    lines = [line for line in text.splitlines() if 'prediction' in line]
    assert lines == ['prediction: none in this bag (nmpc_node publishes it with '
                     'publish_prediction true)']
    report = json.loads(erva('report', SAMPLE, '--json', check=True).stdout)
    assert report['prediction'] is None and report['samples']['prediction'] == 0


def _base_requirements():
    """Return erva_ros's own run dependencies (its metadata's, without any extra)."""
    from importlib.metadata import requires
    return [r for r in requires('erva_ros') if 'extra ==' not in r]


@pytest.fixture(scope='module')
def no_ros_python(tmp_path_factory):
    """Return the python of a fresh venv holding only erva_ros's base dependencies.

    ``python -m venv`` (no system site-packages) and ``pip install`` of setup.py's
    install_requires, pinned by .ci/constraints.txt: no rclpy, no rosidl, no message
    package.  erva_ros itself comes from the source tree (PYTHONPATH), as a checkout
    would.  With pip's cache warm (CI's setup has just downloaded the same wheels)
    this took 19 s here.
    """
    import subprocess
    import sys
    venv = tmp_path_factory.mktemp('no_ros') / 'venv'
    subprocess.run([sys.executable, '-m', 'venv', str(venv)], check=True)
    python = str(venv / 'bin' / 'python')
    pip = subprocess.run([python, '-m', 'pip', 'install', '--quiet',
                          '--disable-pip-version-check', '-c',
                          os.path.join(REPO, '.ci', 'constraints.txt'),
                          *_base_requirements()], capture_output=True, text=True)
    assert pip.returncode == 0, pip.stderr[-3000:]
    return python


def _no_ros(python, *args):
    import subprocess
    env = {k: v for k, v in os.environ.items()
           if k not in ('PYTHONPATH', 'AMENT_PREFIX_PATH', 'VIRTUAL_ENV')}
    env.update(PYTHONPATH=REPO, MPLBACKEND='Agg', PYTHONNOUSERSITE='1')
    return subprocess.run([python, *args], capture_output=True, text=True, env=env,
                          cwd=REPO, timeout=300)


@pytest.mark.ros
def test_report_and_bag_info_work_without_the_ros_wheels(session, erva, no_ros_python):
    """`erva report` and `erva bag info` print the same without rclpy and messages."""
    probe = _no_ros(no_ros_python, '-c', 'import importlib.util as u; print([m for m in '
                    '("rclpy", "rosidl_parser", "rosidl_runtime_py", "std_msgs", '
                    '"trajectory_msgs", "builtin_interfaces", "rosbags", "mcap_ros2") '
                    'if u.find_spec(m)])')
    assert probe.stdout.strip() == '[]', probe.stderr
    for bag in (session['bag'], SAMPLE):
        for args in (('report', bag), ('report', bag, '--json'), ('bag', 'info', bag)):
            alone = _no_ros(no_ros_python, '-m', 'erva_ros.cli', *args)
            assert alone.returncode == 0, alone.stderr[-3000:]
            assert alone.stdout == erva(*args, check=True).stdout, args
    helped = _no_ros(no_ros_python, '-m', 'erva_ros.cli', '--help')
    assert helped.returncode == 0 and 'report' in helped.stdout, helped.stderr


@pytest.mark.parametrize('args', [('--help',), ('report', SAMPLE), ('bag', 'info', SAMPLE)])
def test_the_report_path_imports_no_ros_even_where_it_is_installed(args):
    """Lazy imports: with the ROS wheels installed, these commands still load none of them."""
    import subprocess
    import sys
    code = ('import contextlib, io, sys\n'
            'from erva_ros import cli\n'
            f'sys.argv = ["erva", *{list(args)!r}]\n'
            'with contextlib.redirect_stdout(io.StringIO()):\n'
            '    try:\n'
            '        cli.main()\n'
            '    except SystemExit:\n'
            '        pass\n'
            'print(sorted({m.split(".")[0] for m in sys.modules} & {"rclpy", "rosidl_parser",'
            ' "std_msgs", "trajectory_msgs", "sensor_msgs", "builtin_interfaces"}))\n')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         cwd=REPO, env={**os.environ, 'MPLBACKEND': 'Agg'}, timeout=120)
    assert out.returncode == 0 and out.stdout.strip().splitlines()[-1] == '[]', out
