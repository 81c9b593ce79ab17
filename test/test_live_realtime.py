"""realtime_priority: every thread of a node process switches to SCHED_FIFO (or warns)."""

import json
import os
import subprocess
import sys

import pytest

from conftest import fifo_permitted
from erva_ros.live.realtime import set_fifo_priority

PROBE = r'''
import json, os, threading, time
from erva_ros.live.realtime import set_fifo_priority
warnings = []
early = threading.Thread(target=time.sleep, args=(60,), daemon=True)
early.start()                      # exists before the switch, like DDS's threads
outcome = set_fifo_priority(7, warnings.append)
late = []
t = threading.Thread(target=lambda: late.append(os.sched_getscheduler(0)))
t.start(); t.join()                # created after: must inherit the policy
policies = {}
for tid in os.listdir('/proc/self/task'):   # a joined thread may linger in the listing
    try:
        policies[int(tid)] = os.sched_getscheduler(int(tid))
    except ProcessLookupError:
        pass
print(json.dumps({'outcome': outcome, 'warnings': warnings, 'policies': policies,
                  'late': late, 'fifo': os.SCHED_FIFO,
                  'prio': os.sched_getparam(0).sched_priority}))
'''


def _probe():
    out = subprocess.run([sys.executable, '-c', PROBE], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_zero_priority_leaves_scheduling_alone():
    warnings = []
    assert set_fifo_priority(0, warnings.append) == 'off'
    assert warnings == [] and os.sched_getscheduler(0) == os.SCHED_OTHER


def test_out_of_range_priority_is_an_error():
    with pytest.raises(ValueError, match=r'realtime_priority must be in \[0, 98\]'):
        set_fifo_priority(99, print)


def test_every_thread_switches_or_one_warning_explains_why():
    r = _probe()
    if fifo_permitted(7):
        assert r['outcome'] == 'SCHED_FIFO 7' and r['warnings'] == []
        assert set(r['policies'].values()) == {r['fifo']}, r['policies']
        assert r['late'] == [r['fifo']] and r['prio'] == 7
    else:
        assert r['outcome'].startswith('unavailable') and len(r['warnings']) == 1
        assert 'CAP_SYS_NICE' in r['warnings'][0]
