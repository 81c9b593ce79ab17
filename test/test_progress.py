"""Progress of long commands (core/progress.py), and the figures `erva table/bench --out` write.

The progress lines are checked for their text, counts and order under a clock the test
drives, never against real time.  The commands are checked as a user runs them: progress
on stderr without --json, none with it, and the PNG files.
"""

import io
import json
import os
import subprocess
import sys

import pytest

from erva_ros.core.progress import PLAIN_MIN_S, Progress, stage

PNG_MAGIC = b'\x89PNG\r\n\x1a\n'


class Stream(io.StringIO):
    """A stderr stand-in that says whether it is a terminal."""

    def __init__(self, tty):
        super().__init__()
        self.tty = tty

    def isatty(self):
        return self.tty


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_terminal_line_is_rewritten_in_place_with_an_eta():
    out, clock = Stream(tty=True), Clock()
    p = Progress('erva table: seeds', 10, stream=out, clock=clock)
    for done in range(1, 11):
        clock.t += 9.0
        p(done, 10)
    p.close()
    text = out.getvalue()
    assert text.count('\n') == 1 and text.endswith('\n')          # one line for the stage
    updates = text.rstrip('\n').split('\r')[1:]
    assert len(updates) == 10
    assert updates[2] == 'erva table: seeds 3/10 (30 %), 27 s elapsed, ETA 1 min 03 s\x1b[K'
    assert updates[-1] == 'erva table: seeds 10/10 (100 %), done in 1 min 30 s\x1b[K'


def test_plain_lines_without_a_terminal_one_per_tenth_not_too_often():
    out, clock = Stream(tty=False), Clock()
    p = Progress('erva bench: samples', 100, stream=out, clock=clock)
    for done in range(1, 101):
        clock.t += 1.0         # 100 s in all: a tenth every 10 s, more than PLAIN_MIN_S
        p(done)
    p.close()
    lines = out.getvalue().splitlines()
    assert [line.split(' (')[0] for line in lines] == [
        f'erva bench: samples {n}/100' for n in range(10, 101, 10)]
    assert lines[-1] == 'erva bench: samples 100/100 (100 %), done in 1 min 40 s'
    assert all('\r' not in line for line in lines)
    # A stage of seconds prints only its last line.
    out, clock = Stream(tty=False), Clock()
    p = Progress('short', 50, stream=out, clock=clock)
    for done in range(1, 51):
        clock.t += (PLAIN_MIN_S - 1.0) / 50
        p(done)
    p.close()
    assert out.getvalue().splitlines() == ['short 50/50 (100 %), done in 4 s']


def test_a_started_stage_says_so_an_early_stop_is_named_an_error_left_alone():
    out, clock = Stream(tty=False), Clock()
    with Progress('erva table: seeds', 4, stream=out, clock=clock) as p:
        p(0)              # started: shown even though nothing is done yet
        clock.t += 80
        p(1)
    assert out.getvalue().splitlines() == [
        'erva table: seeds 0/4 (0 %), 0 s elapsed',
        'erva table: seeds 1/4 (25 %), 1 min 20 s elapsed, ETA 4 min 00 s',
        'erva table: seeds 1/4 (25 %), stopped after 1 min 20 s']
    out = Stream(tty=False)
    with stage('compiling the NMPC', stream=out):
        pass
    assert out.getvalue().splitlines() == ['compiling the NMPC, 0 s elapsed',
                                           'compiling the NMPC, done in 0 s']
    # An error inside the stage: its own line follows; the progress adds none (a terminal
    # line in progress is only ended).
    for tty, expected in ((False, ''), (True, '\rx 1/3 (33 %), 0 s elapsed, ETA 0 s\x1b[K\n')):
        out = Stream(tty)
        with pytest.raises(ValueError):
            with Progress('x', 3, stream=out, clock=Clock()) as p:
                p(1)
                raise ValueError('bad input')
        assert out.getvalue() == expected


def test_disabled_progress_prints_nothing():
    for tty in (True, False):
        out = Stream(tty)
        with Progress('x', 3, enabled=False, stream=out) as p:
            for i in range(1, 4):
                p.advance(note=f'run {i}')
        assert out.getvalue() == ''


def _progress_lines(stderr, prefix):
    return [line for line in stderr.splitlines() if line.startswith(prefix)]


def test_table_progress_on_stderr_unless_json_and_its_figure(erva, tmp_path):
    args = ('table', '--seeds', 2, '--duration', 0.3, '--no-bound', '--weights', '1,0;0,1',
            '--controllers', 'passive,skyhook', '--jobs', 1)
    proc = erva(*args, '--out', tmp_path, check=True)
    lines = _progress_lines(proc.stderr, 'erva table: seeds')
    assert lines[0] == 'erva table: seeds 0/2 (0 %), 0 s elapsed'
    assert lines[-1].startswith('erva table: seeds 2/2 (100 %), done in ')
    png = tmp_path / 'table.png'
    assert f'wrote {png}' in proc.stdout.splitlines()
    assert png.read_bytes()[:8] == PNG_MAGIC and png.stat().st_size > 10000
    quiet = erva(*args, '--json', check=True)
    assert 'erva table' not in quiet.stderr
    assert json.loads(quiet.stdout)['seeds'] == 2


def test_bench_progress_per_stage_and_the_solve_time_cdf(erva, tmp_path):
    proc = erva('bench', '--steps', 30, '--no-reference', '--out', tmp_path, check=True)
    lines = _progress_lines(proc.stderr, 'erva bench: ')
    assert lines and all(line.startswith('erva bench: seed 0, sqp, samples ') for line in lines)
    assert lines[-1].startswith('erva bench: seed 0, sqp, samples 30/30 (100 %), done in ')
    png = tmp_path / 'solve_time_cdf.png'
    assert f'wrote {png}' in proc.stdout.splitlines()
    assert png.read_bytes()[:8] == PNG_MAGIC and png.stat().st_size > 10000
    quiet = erva('bench', '--steps', 30, '--no-reference', '--json', check=True)
    assert 'erva bench' not in quiet.stderr
    bad = erva('bench', '--live', '--out', tmp_path)
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines() == [
        'erva bench: error: --out writes the offline solve-time CDF; it cannot go with --live']


@pytest.mark.parametrize('module', ['erva_ros.core.plots.figures',
                                    'erva_ros.core.plots.closed_loop',
                                    'erva_ros.core.plots.bag_report'])
def test_figures_leave_the_users_matplotlib_backend_alone(module, tmp_path):
    """A notebook's backend stays; figures are still written, without pyplot."""
    code = f"""
import sys, matplotlib
matplotlib.use('svg')
import {module}
from erva_ros.core.plots.figures import solve_time_cdf_figure
solve_time_cdf_figure({{'sqp': [1.0, 2.0, 30.0]}}, 10.0, {str(tmp_path / 'cdf.png')!r})
print(matplotlib.get_backend(), 'matplotlib.pyplot' in sys.modules)
"""
    env = {k: v for k, v in os.environ.items() if k != 'MPLBACKEND'}
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ['svg', 'False']
    assert (tmp_path / 'cdf.png').read_bytes()[:8] == PNG_MAGIC


@pytest.mark.parametrize('command,args,label', [
    ('fr', ['--f-min', 1, '--f-max', 3, '--f-step', 1, '--models', 'benchmark'],
     'erva fr: benchmark, tones'),
    ('pareto', ['--seeds', 1, '--duration', 0.2, '--ratios', 1, '--jobs', 1], 'erva pareto: runs'),
    ('delay-study', ['--seeds', 1, '--duration', 0.2, '--jobs', 1], 'erva delay-study: seeds'),
])
def test_study_commands_show_their_stage_unless_json(erva, command, args, label):
    lines = _progress_lines(erva(command, *args, check=True).stderr, label)
    assert lines[0].startswith(f'{label} 0/') and ', done in ' in lines[-1]
    assert label not in erva(command, *args, '--json', check=True).stderr
