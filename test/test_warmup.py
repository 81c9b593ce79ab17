"""The compiled-function cache: atomic, shared safely, resumed; warm-up before any node starts."""

import os
import shutil
import signal
import stat
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from conftest import REPO, ros_env

CC = shutil.which('cc') or shutil.which('gcc')
pytestmark = pytest.mark.skipif(CC is None, reason='no C compiler')

#: Functions to compile (the model's own equations, a few kB of C each; B the larger).
FUNCTIONS = textwrap.dedent('''
    import casadi as ca
    from erva_ros.core.model.quarter_car import make_model
    from erva_ros.core.model.params import paper_params
    m = make_model(paper_params(), 'erva')
    x, u = ca.SX.sym('x', 6), ca.SX.sym('u')
    A = ca.Function('warmup_probe_a', [x, u], [m.power(x, u)])
    B = ca.Function('warmup_probe_b', [x, u], [ca.jacobian(m.ode(x, u, 0.001), x)])
''')


def _wrapper(tmp_path, body: str) -> str:
    """Return a C compiler wrapper script: the probe goes to the real one, ``body`` else."""
    path = tmp_path / 'cc-wrapper'
    path.write_text(textwrap.dedent(f'''\
        #!/bin/sh
        case "$*" in *probe.c*) exec {CC} "$@";; esac
        ''') + textwrap.dedent(body))
    path.chmod(path.stat().st_mode | stat.S_IXUSR)
    return str(path)


def _compile_in_child(cache, cc=None, wait=True, functions='A, B'):
    """Compile FUNCTIONS in a child process with ``cc``; return it (or its result)."""
    code = FUNCTIONS + textwrap.dedent(f'''
        from erva_ros.core.model.codegen import compile_functions
        from erva_ros.core.model.params import ParamError
        try:
            fs = compile_functions([{functions}], 'the probes')
            print('value', [float(f([1e-3, 2e-2, 0, -1e-2, 3e-3, 5e-2], 15000.0)[0][0])
                            for f in fs])
        except ParamError as exc:
            print('error', exc)
    ''')
    env = ros_env({'ERVA_CACHE_DIR': str(cache), **({'CC': cc} if cc else {})})
    proc = subprocess.Popen([sys.executable, '-c', code], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, cwd=REPO,
                            start_new_session=True)
    if not wait:
        return proc
    out, err = proc.communicate(timeout=300)
    return proc.returncode, out, err


def _libs(cache):
    return sorted(p.name for p in cache.glob('*.so'))


def test_a_killed_compile_keeps_what_was_done_and_the_next_run_compiles_the_rest(tmp_path):
    cache, calls, started = tmp_path / 'cache', tmp_path / 'calls', tmp_path / 'started'
    # A compiler that, for function A, writes half a library and hangs until killed.
    hang_on_a = _wrapper(tmp_path, f'''\
        for a; do case "$a" in *.c) src="$a";; esac; done
        if grep -q warmup_probe_a "$src"; then
            while [ "$1" != "-o" ]; do shift; done
            echo half > "$2"; touch {started}; exec sleep 600
        fi
        exec {CC} "$@"
        ''')
    proc = _compile_in_child(cache, hang_on_a, wait=False)
    deadline = time.monotonic() + 120
    while not (started.exists() and any('probe_b' in n for n in _libs(cache))):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)        # the process and its compilers, at once
    proc.wait()
    assert [n.split('_')[2] for n in _libs(cache)] == ['b']   # B kept, no half of A
    counting = _wrapper(tmp_path, f'''\
        echo x >> {calls}
        exec {CC} "$@"
        ''')
    code, out, err = _compile_in_child(cache, counting)       # the next run
    assert code == 0 and out.startswith('value'), (out, err)
    assert calls.read_text().count('x') == 1                  # A only
    assert len(_libs(cache)) == 2 and not list(cache.glob('*.tmp*'))   # the half file gone
    assert 'compiling the probes (first run on this machine' in err


def test_concurrent_processes_compile_a_function_once(tmp_path):
    cache, calls = tmp_path / 'cache', tmp_path / 'calls'
    counting = _wrapper(tmp_path, f'''\
        echo x >> {calls}
        sleep 2
        exec {CC} "$@"
        ''')
    procs = [_compile_in_child(cache, counting, wait=False) for _ in range(3)]
    outs = [p.communicate(timeout=300) for p in procs]
    values = {out.strip() for out, _ in outs}
    assert all(p.returncode == 0 for p in procs) and len(values) == 1, outs
    assert values.pop().startswith('value')
    # One compile of each function: the others waited on its lock and loaded its
    # library (without the lock, each process would have compiled both: 6 lines).
    assert calls.read_text().count('x') == 2
    assert len(_libs(cache)) == 2


def test_a_compiler_killed_once_is_run_again(tmp_path):
    cache, calls = tmp_path / 'cache', tmp_path / 'calls'
    flaky = _wrapper(tmp_path, f'''\
        echo x >> {calls}
        [ "$(wc -l < {calls})" -ge 2 ] || kill -9 $$
        exec {CC} "$@"
        ''')
    code, out, err = _compile_in_child(cache, flaky, functions='A')
    assert code == 0 and out.startswith('value'), (out, err)
    assert calls.read_text().count('x') == 2 and len(_libs(cache)) == 1


@pytest.mark.parametrize('body, message', [
    ('echo "probe.c:1:1: error: injected failure" >&2; exit 1',
     'compiling warmup_probe_a failed: probe.c:1:1: error: injected failure'),
    ('kill -9 $$', 'compiling warmup_probe_a failed twice: cc-wrapper was killed by SIGKILL'),
    ('exit 3', 'compiling warmup_probe_a failed twice: cc-wrapper exited with status 3 and no '
               'message'),
])
def test_a_failed_compile_says_what_the_compiler_said(tmp_path, body, message):
    code, out, err = _compile_in_child(tmp_path / 'cache', _wrapper(tmp_path, body),
                                       functions='A')
    assert code == 0 and out.startswith('error'), (out, err)
    assert message in out
    assert _libs(tmp_path / 'cache') == []


def test_warm_compiles_once_then_only_loads(tmp_path, monkeypatch):
    from erva_ros.core.model import codegen
    from erva_ros.core.loop import warmup
    from erva_ros.core.model.params import paper_params
    monkeypatch.setenv('ERVA_CACHE_DIR', str(tmp_path))
    targets = [warmup.Target('plant', paper_params(), 'benchmark', 0.02),
               warmup.Target('ekf', paper_params(), 'benchmark', 0.02, u_max=22800.0)]
    lines = []
    first = warmup.warm(targets, lines.append)
    assert [t.status for t in first.targets] == ['compiled', 'compiled'], first.as_dict()
    assert [t.functions for t in first.targets] == [1, 3] and first.compiled == 4
    assert {ln.split(' (first run')[0] for ln in lines[:2]} == {
        'compiling the plant (benchmark model)', 'compiling the EKF (benchmark model)'}
    assert lines[2].startswith('compiled 4 function(s) in ')
    # Warm: the manifests answer, no process is started and nothing is said.
    monkeypatch.setattr(warmup, '_plan_and_compile', pytest.fail)
    again, lines[:] = warmup.warm(targets, lines.append), []
    assert [t.status for t in again.targets] == ['cached', 'cached'] and lines == []
    # The cores built as their processes build them load the libraries: nothing compiles.
    monkeypatch.setattr(codegen, 'run_jobs', pytest.fail)
    plant, ekf = (t.build() for t in targets)
    assert plant._step.fn.class_name() == 'External'
    assert ekf._cycle.fn.class_name() == 'External'
    x1 = plant.step(15000.0, 0.0, 0.01)
    assert np.all(np.isfinite(x1)) and np.any(x1 != 0)


def test_a_missing_library_is_seen_despite_its_manifest(tmp_path, monkeypatch):
    from erva_ros.core.loop import warmup
    from erva_ros.core.model.params import paper_params
    monkeypatch.setenv('ERVA_CACHE_DIR', str(tmp_path))
    target = [warmup.Target('plant', paper_params(), 'benchmark', 0.02)]
    assert warmup.warm(target).targets[0].status == 'compiled'
    for lib in tmp_path.glob('*.so'):
        lib.unlink()
    check = warmup.warm(target, check=True)
    assert check.targets[0].status == 'missing' and check.targets[0].missing == 1
    assert not check.ok and _libs(tmp_path) == []
    assert warmup.warm(target).targets[0].status == 'compiled' and len(_libs(tmp_path)) == 1


def test_one_solver_for_no_preview_and_for_values_that_are_parameters(tmp_path, monkeypatch):
    # Why one manifest key serves them (warmup.NOT_COMPILED_IN): they load the same
    # libraries.  A structural change (the command delay modelled) does not.
    from erva_ros.core.loop import warmup
    from erva_ros.core.controllers.settings import ControllerSettings
    from erva_ros.core.model.params import paper_params
    monkeypatch.setenv('ERVA_CACHE_DIR', str(tmp_path))
    s = ControllerSettings(controller='preview', horizon=4)
    variants = [s, s.with_(controller='no_preview'),
                s.with_(alpha1=0.0, alpha2=1.0, max_iter=3, sqp_tol=0.1, time_budget_s=0.5),
                s.with_(command_delay_s=0.004), s.with_(command_delay_s=0.015)]
    targets = [warmup.nmpc_target(paper_params(), v) for v in variants]
    plans, compiled, errors = warmup._plan_and_compile(targets, 2, None)
    libs = [sorted(p.libs) for p in plans]
    assert len(libs[0]) == 2 and libs[0] == libs[1] == libs[2] != libs[3] == libs[4]
    assert compiled == set() and errors == {} and _libs(tmp_path) == []
    keys = {warmup._target_key(t, 'salt') for t in targets}
    assert len(keys) == 2


def test_erva_compile_check_and_json(tmp_path, erva):
    env = {'ERVA_CACHE_DIR': str(tmp_path)}
    proc = erva('compile', '--check', '--json', env=env)
    assert proc.returncode == 1 and proc.stderr == '', proc.stderr
    import json
    from erva_ros.core.model.codegen import codegen_target
    res = json.loads(proc.stdout)['targets'][codegen_target()]
    labels = [t['target'] for t in res['targets']]
    assert labels[:3] == ['the NMPC (preview_long, erva model)', 'the NMPC (preview, erva model)',
                          'the NMPC (no_preview, erva model)']
    assert 'the NMPC (preview, erva model, with a command delay)' in labels
    assert 'the NMPC (preview_long, benchmark model, with a command delay)' in labels
    assert 'the NMPC (preview, benchmark model)' in labels
    assert {'the plant (erva model)', 'the plant (benchmark model)', 'the EKF (erva model)',
            "the simulated ECU's plant (erva model)"} <= set(labels)
    assert all(t['status'] == 'missing' and t['missing'] == t['functions'] > 0
               for t in res['targets'])
    assert _libs(tmp_path) == []                # a check compiles nothing
    bad = erva('compile', '--nmpc', str(tmp_path / 'nope.yaml'), env=env)
    assert bad.returncode == 2 and bad.stderr.count('\n') == 1, bad.stderr
    assert 'nope.yaml' in bad.stderr and 'does not exist' in bad.stderr
