"""Nodes die with `erva run`: at once when it is killed, and the recorder after closing its bag.

A small harness process adopts the orphans (PR_SET_CHILD_SUBREAPER), so their exit
statuses can be read after `erva run` is SIGKILLed: the loop's nodes must have been
killed by the kernel (SIGKILL, no clean-stop wait for peers that are gone: a SCHED_FIFO
plant_sim_node ran on for up to 10 s), the recorder must have ended by itself (exit 0)
with a finished bag that a reader we did not write opens.
"""

import json
import os
import signal
import subprocess
import sys

import pytest

from conftest import REPO, ros_env
from run_helpers import SampleWatch

pytestmark = pytest.mark.ros

HARNESS = r'''
import ctypes, json, os, re, signal, subprocess, sys
ctypes.CDLL('libc.so.6', use_errno=True).prctl(36, 1)      # PR_SET_CHILD_SUBREAPER
run = subprocess.Popen([sys.executable, '-m', 'erva_ros.cli', 'run', *sys.argv[1:]],
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
pids = {}
for line in run.stderr:
    pids.update({n: int(p) for n, p in re.findall(r'(\w+_node) \(pid (\d+)\)', line)})
    if 'connected in' in line:
        break
print(json.dumps(pids), flush=True)
sys.stdin.readline()                                      # the test: kill it now
os.kill(run.pid, signal.SIGKILL)
run.wait()
names = {p: n for n, p in pids.items()}
ended = {}
while True:
    try:
        pid, status = os.waitpid(-1, 0)
    except ChildProcessError:
        break
    if pid in names:
        ended[names[pid]] = (-os.WTERMSIG(status) if os.WIFSIGNALED(status)
                             else os.WEXITSTATUS(status))
print(json.dumps(ended), flush=True)
'''


def test_a_killed_erva_run_takes_its_nodes_at_once_and_the_recorder_finishes(tmp_path):
    bags = tmp_path / 'bags'
    watch = SampleWatch()
    harness = subprocess.Popen([sys.executable, '-c', HARNESS, '--duration', '60', '--record',
                                str(bags)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                               text=True, env=ros_env(), cwd=REPO, start_new_session=True)
    try:
        pids = json.loads(harness.stdout.readline() or '{}')
        assert set(pids) == {'recorder_node', 'nmpc_node', 'plant_sim_node',
                             'road_preview_node'}, pids
        watch.wait(25)                                    # the loop runs, the bag fills
        harness.stdin.write('kill\n')
        harness.stdin.flush()
        out, _ = harness.communicate(timeout=120)
    finally:
        watch.close()
        if harness.poll() is None:
            os.killpg(harness.pid, signal.SIGKILL)
    ended = json.loads(out)
    # The loop's nodes: ended by the kernel at the parent's death (a clean stop exits 0
    # after waiting for acknowledgements from peers that are gone).
    assert {n: ended[n] for n in ('nmpc_node', 'plant_sim_node', 'road_preview_node')} == {
        'nmpc_node': -signal.SIGKILL, 'plant_sim_node': -signal.SIGKILL,
        'road_preview_node': -signal.SIGKILL}, ended
    assert ended['recorder_node'] == 0, ended         # it stopped by itself ...
    from mcap.reader import make_reader
    (bag,) = list(bags.iterdir())
    (mcap_file,) = list(bag.glob('*.mcap'))
    with open(mcap_file, 'rb') as fh:                 # ... with its bag finished
        reader = make_reader(fh)
        summary = reader.get_summary()
        counts = {c.topic: n for c, n in ((summary.channels[i], k) for i, k in
                                          summary.statistics.channel_message_counts.items())}
    assert summary is not None and counts.get('/erva/sprung_accel', 0) >= 25, counts
