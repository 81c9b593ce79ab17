"""Real-time scheduling of a node process (``realtime_priority`` parameter).

On a vehicle or HIL bench the control loop runs at SCHED_FIFO priority so that
other work on the same cores (logging, recording, desktop) cannot delay a sample;
ros2_control does the same for its controller manager.  Linux scheduling policy is
per *thread*: every thread of the process (the executor's and the DDS middleware's
receive threads) is switched, and threads created later inherit the policy.

Needs CAP_SYS_NICE (root, or an ``rtprio`` limit in /etc/security/limits.conf, or
``ulimit -r``).  Without it the node logs one warning and runs at normal priority,
so the same parameter file works on a developer laptop.  The kernel's RT throttling
(sched_rt_runtime_us, 95 % by default) keeps a runaway loop from freezing a core.
"""

import os
from typing import Callable

#: Highest priority a node may ask for (99 is left to the kernel's own threads).
MAX_PRIORITY = 98
#: Default of the ``realtime_priority`` parameter (config/live.yaml): below the threaded
#: IRQ handlers of a PREEMPT_RT kernel (50), so network and timer interrupts still
#: preempt the loop.
DEFAULT_PRIORITY = 20


def set_fifo_priority(priority: int, warn: Callable[[str], None]) -> str:
    """Switch every thread of this process to SCHED_FIFO ``priority``; return the outcome.

    Returns 'off' (priority 0), 'SCHED_FIFO <p>' or 'unavailable: <why>' (after
    calling ``warn`` with one line).
    """
    priority = int(priority)
    if priority <= 0:
        return 'off'
    if not 1 <= priority <= MAX_PRIORITY:
        raise ValueError(f'realtime_priority must be in [0, {MAX_PRIORITY}], got {priority}')
    try:
        for tid in [int(t) for t in os.listdir('/proc/self/task')]:
            try:
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
            except ProcessLookupError:
                continue    # the thread ended since the listing
    except (OSError, AttributeError) as exc:   # PermissionError without CAP_SYS_NICE
        why = getattr(exc, 'strerror', None) or str(exc)
        warn(f'realtime_priority {priority}: cannot switch to SCHED_FIFO ({why}); '
             'running at normal priority (needs CAP_SYS_NICE: root or an rtprio limit)')
        return f'unavailable: {why}'
    return f'SCHED_FIFO {priority}'


__all__ = ['set_fifo_priority', 'MAX_PRIORITY', 'DEFAULT_PRIORITY']
