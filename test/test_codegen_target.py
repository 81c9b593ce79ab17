"""Compiled functions built for a CPU target: keyed by it, loaded only where it runs."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import casadi as ca
import numpy as np
import pytest

from conftest import REPO, ros_env, run_erva
from erva_ros.core.model import codegen
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import paper_params

MODEL = make_model(paper_params(), 'erva')
#: -march names of which at least one is beyond any CPU: knl has AVX512ER/PF (only
#: Knights Landing), the others AVX-512 (not on AMD before Zen 4) or SSE4A (AMD only).
BEYOND = ('x86-64-v4', 'sapphirerapids', 'znver1', 'knl')

pytestmark = pytest.mark.skipif(codegen.c_compiler() is None, reason='no C compiler')


def _hessian():
    """Return a function of the model with transcendental-free but deep arithmetic."""
    x, u, w = ca.SX.sym('x', 6), ca.SX.sym('u'), ca.SX.sym('w')
    lag = MODEL.sprung_accel(x, u, w) ** 2 + ca.dot(ca.DM.ones(6), MODEL.ode(x, u, w))
    return ca.Function('lagrangian_hessian', [x, u, w],
                       [ca.hessian(lag, ca.vertcat(x, u))[0]])


def _use(monkeypatch, cache, target):
    monkeypatch.setenv('ERVA_CACHE_DIR', str(cache))
    monkeypatch.setenv(codegen.TARGET_ENV, target)


def _beyond_this_cpu() -> str:
    for target in BEYOND:
        if codegen.toolchain(target).record.missing_here():
            return target
    raise AssertionError(f'this CPU runs all of {BEYOND}: extend the list')


def test_every_target_gives_the_native_results_bit_for_bit(tmp_path, monkeypatch):
    # No fused multiply-adds for any target: the same IEEE operations in the same order,
    # so a portable build computes exactly what the native one does.
    fn = _hessian()
    rng = np.random.default_rng(5)
    points = [(rng.normal(0, 0.02, 6), rng.uniform(0, 2e4), rng.normal(0, 0.01))
              for _ in range(20)]
    out = {}
    for target in ('native', 'x86-64', 'x86-64-v2'):
        _use(monkeypatch, tmp_path, target)
        compiled, = codegen.compile_functions([fn])
        out[target] = [np.asarray(compiled(*pt)) for pt in points]
    for target in ('x86-64', 'x86-64-v2'):
        for a, b in zip(out['native'], out[target]):
            np.testing.assert_array_equal(a, b)


def test_the_cache_is_keyed_by_the_target(tmp_path, monkeypatch):
    fn = _hessian()
    libs = {}
    for target in ('native', 'x86-64-v2', 'native'):
        _use(monkeypatch, tmp_path, target)
        [lib], jobs = codegen.plan_functions([fn])
        # A run asking for another target compiles anew, never loads the other's.
        assert bool(jobs) == (target not in libs), target
        assert libs.setdefault(target, lib) == lib
        codegen.compile_functions([fn])
    assert libs['native'] != libs['x86-64-v2']
    tags = {r.target: r for r in codegen.cached_records()}
    assert set(tags) == {'native', 'x86-64-v2'}
    assert '-march=x86-64-v2' in tags['x86-64-v2'].flags
    assert {'sse4_2', 'popcnt'} <= tags['x86-64-v2'].requires
    assert 'avx' not in tags['x86-64-v2'].requires


def test_a_native_library_of_another_cpu_is_never_found(tmp_path, monkeypatch):
    fn = _hessian()
    _use(monkeypatch, tmp_path, 'native')
    codegen.compile_functions([fn])
    [mine], _ = codegen.plan_functions([fn])
    # The same cache seen from another CPU (another model name and flags): its own key.
    other = 'model name\t: Another CPU\nflags\t\t: fpu sse sse2\n'
    monkeypatch.setattr(codegen, '_cpu_id', lambda: other)
    codegen._toolchain.cache_clear()
    try:
        [theirs], jobs = codegen.plan_functions([fn])
        assert theirs != mine and [j.lib for j in jobs] == [theirs]
    finally:
        monkeypatch.undo()
        codegen._toolchain.cache_clear()


def test_a_library_loads_only_on_a_cpu_that_runs_its_target(tmp_path, monkeypatch):
    target = _beyond_this_cpu()
    fn = _hessian()
    _use(monkeypatch, tmp_path, target)
    # Building for another machine works (`erva compile --target`) ...
    _, jobs = codegen.plan_functions([fn])
    codegen.run_jobs(jobs)
    assert os.path.isfile(jobs[0].lib)
    # ... loading it here does not: one line naming what this CPU lacks.
    missing = codegen.toolchain().record.missing_here()
    with pytest.raises(codegen.TargetError) as err:
        codegen.compile_functions([fn])
    assert f'{codegen.TARGET_ENV}={target}' in str(err.value)
    assert ', '.join(missing) in str(err.value) and '\n' not in str(err.value)
    # Nor does codegen 'auto' hide it by running uncompiled.
    with pytest.raises(codegen.TargetError):
        codegen.compile_for('auto', [fn], 'the test function')


def test_a_cache_built_elsewhere_loads_without_a_compiler(tmp_path, monkeypatch):
    # A vehicle PC without gcc, given the cache a workstation built for its target.
    fn = _hessian()
    _use(monkeypatch, tmp_path / 'built', 'x86-64-v2')
    built, = codegen.compile_functions([fn])
    shutil.copytree(tmp_path / 'built', tmp_path / 'vehicle')
    _use(monkeypatch, tmp_path / 'vehicle', 'x86-64-v2')
    monkeypatch.delenv('CC', raising=False)
    monkeypatch.setenv('PATH', '')
    assert codegen.c_compiler() is None and codegen.use_codegen('auto')
    loaded, = codegen.compile_functions([fn])         # would raise if it had to compile
    x = (np.full(6, 0.01), 15000.0, 0.002)
    np.testing.assert_array_equal(np.asarray(loaded(*x)), np.asarray(built(*x)))
    # A target the cache does not hold: codegen 'auto' runs uncompiled, 'on' says why.
    monkeypatch.setenv(codegen.TARGET_ENV, 'x86-64-v3')
    assert not codegen.use_codegen('auto')
    with pytest.raises(codegen.TargetError, match='no C compiler .* and no libraries '
                                                  'built for x86-64-v3'):
        codegen.toolchain()


def test_a_bad_or_foreign_target_is_one_line_and_nothing_runs(tmp_path):
    env = {'ERVA_CACHE_DIR': str(tmp_path)}
    cases = {'no such cpu': 'not a -march name',
             'pentium9': 'cannot build for it',
             _beyond_this_cpu(): 'this CPU cannot run code built for it'}
    for target, why in cases.items():
        proc = run_erva('sim', '--controller', 'preview', '--duration', '0.1',
                        env=dict(env, **{codegen.TARGET_ENV: target}))
        assert proc.returncode == 2, (target, proc.stdout, proc.stderr)
        assert len(proc.stderr.strip().splitlines()) == 1 and why in proc.stderr, target
    assert not any(p.endswith('.so') for p in os.listdir(tmp_path))


def test_compile_check_lists_the_targets_the_cache_holds(tmp_path, monkeypatch):
    # The suite's warm cache (conftest.compiled_functions): every part of the native target.
    # (ERVA_CODEGEN_TARGET may name another target than native: the suite runs either.)
    selected = codegen.codegen_target()
    proc = run_erva('compile', '--check', '--json')
    assert proc.returncode == 0, proc.stdout + proc.stderr
    out = json.loads(proc.stdout)
    mine = [c for c in out['cache'] if c['selected']]
    assert len(mine) == 1 and mine[0]['target'] == selected and mine[0]['runs_here']
    assert mine[0]['cached'] == mine[0]['parts'] > 10
    assert all(t['status'] == 'cached' for t in out['targets'][selected]['targets'])
    # Asking for a target not built yet: missing, and exit 1.
    other = 'x86-64' if selected != 'x86-64' else 'x86-64-v2'
    proc = run_erva('compile', '--check', '--target', other)
    assert proc.returncode == 1 and f'target {other}: missing' in proc.stdout


#: A compiler for the Ctrl-C test: probes (small sources) and the first library compile
#: run gcc; every later library "compiles" for ten minutes in a child, as cc1 does under
#: gcc's driver.  So the libraries finished before the signal are known, and none can
#: finish after it (the real compilers made that a race: the directory was listed, then
#: a compile ended, then the signal came).
SLOW_CC = r"""#!/bin/bash
for a in "$@"; do
  if [[ "$a" == *.c && $(wc -c < "$a") -gt 1000 ]] && ! mkdir "$MARKS/first" 2>/dev/null; then
    sleep 600 & echo > "$MARKS/sleep.$!"; wait; exit 1
  fi
done
exec gcc "$@"
"""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f'/proc/{pid}/stat', encoding='ascii') as fh:      # a zombie is gone
        return fh.read().rsplit(')', 1)[1].split()[0] != 'Z'


@pytest.mark.skipif(shutil.which('gcc') is None, reason='no gcc')
@pytest.mark.parametrize('to', ['group', 'erva'])
def test_ctrl_c_stops_a_compile_in_one_line_and_keeps_what_finished(tmp_path, to):
    # As a terminal does: SIGINT to the whole process group; and to erva alone, as to a
    # compiler started just after the terminal's SIGINT.  The compilers run in groups of
    # their own: erva must end them itself (else each runs to its end, a minute under load).
    cache, marks = tmp_path / 'cache', tmp_path / 'marks'
    marks.mkdir()
    cc = tmp_path / 'cc'
    cc.write_text(SLOW_CC)
    cc.chmod(0o755)
    env = ros_env({'ERVA_CACHE_DIR': str(cache), 'CC': str(cc), 'MARKS': str(marks)})
    # Ctrl-C as in a terminal: a shell that started the suite in the background (`&`) had
    # SIGINT ignored, and Python keeps an inherited SIG_IGN (erva then compiled on).
    proc = subprocess.Popen([sys.executable, '-m', 'erva_ros.cli', 'compile'], cwd=REPO,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))

    def libraries():
        return {f for f in os.listdir(cache) if f.endswith('.so')} if cache.is_dir() else set()

    def sleepers():
        return [int(f.split('.')[1]) for f in os.listdir(marks) if f.startswith('sleep.')]
    try:
        deadline = time.monotonic() + 600
        while not (len(libraries()) == 1 and sleepers()) and proc.poll() is None:
            assert time.monotonic() < deadline, 'no compile finished, or none started after it'
            time.sleep(0.1)
        before = libraries()
        if to == 'group':
            os.killpg(proc.pid, signal.SIGINT)
        else:
            proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=120)
        # Ended with their group (SIGTERM): gone within seconds, not in ten minutes.
        deadline = time.monotonic() + 10
        while (running := [p for p in sleepers() if _alive(p)]) and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        for pid in sleepers():
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert 'Traceback' not in err and 'KeyboardInterrupt' not in err, err
    assert err.strip().splitlines()[-1].startswith('erva compile: interrupted'), err
    # What finished is kept; the compilers that ran are ended, children too, and nothing
    # half-written stays: every file in the cache is a whole library or a record.
    assert libraries() == before and len(before) == 1
    assert sleepers() and not running
    assert not [f for f in os.listdir(cache) if f.endswith(('.tmp', '.c'))]


def test_a_solver_built_once_is_loaded_without_building_it(tmp_path, monkeypatch):
    # A node's start-up: the libraries found by what the solver is built from, not by
    # building it symbolically and hashing its C.  Bit for bit the same solver.
    from erva_ros.core.controllers import ControllerSettings, make_controller, sqp
    monkeypatch.setenv('ERVA_CACHE_DIR', str(tmp_path))
    s = ControllerSettings(time_budget_s=10.0, horizon=4)
    first = make_controller('preview', make_model(paper_params()), s)
    sqp.build_rti.cache_clear()                    # as another process finds it
    monkeypatch.setattr(sqp, '_sqp_parts', lambda *a: pytest.fail('built again'))
    again = make_controller('preview', make_model(paper_params()), s)
    x = np.array([0.01, -0.1, 0.002, 0.2, 0.003, -0.3])
    preview = 0.002 * np.sin(np.arange(5))
    for c in (first, again):
        c.reset()
    for k in range(5):
        a, b = first.compute(x, preview, k * s.ts), again.compute(x, preview, k * s.ts)
        np.testing.assert_array_equal(a.plan, b.plan)
    # Another configuration (here the Hessian) is built, and so is one whose library went.
    sqp.build_rti.cache_clear()
    with pytest.raises(pytest.fail.Exception, match='built again'):
        make_controller('preview', make_model(paper_params()), s.with_(hessian='gauss_newton'))
    for lib in tmp_path.glob('sqp_step_*.so'):
        lib.unlink()
    sqp.build_rti.cache_clear()
    with pytest.raises(pytest.fail.Exception, match='built again'):
        make_controller('preview', make_model(paper_params()), s)
