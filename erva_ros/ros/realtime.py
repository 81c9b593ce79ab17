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

A process that got SCHED_FIFO also asks the kernel, through ``/dev/cpu_dma_latency``
(PM QoS, as cyclictest does), for a CPU wake-up latency of 0 µs while it lives: idle
CPUs then poll instead of halting.  On this machine (a KVM guest, cpuidle haltpoll)
a halted vCPU took the bridge's p99 from ≈ 0.7 ms to 1.5–2.3 ms (`erva bench-hil`):
the wake-up of the loop's threads, not their work.  The request ends with the
process (the kernel drops it when the file is closed); polling costs power, which is
the price of the real-time mode.  Without permission (root only, by default) it is
skipped with one warning.
"""

import os
import struct
from typing import Callable, Optional

from erva_ros.core.settings.files import shipped_defaults
from erva_ros.core.settings.schemas import MAX_PRIORITY

#: Default of the ``realtime_priority`` parameter, as config/live.yaml ships it (20: below
#: the threaded IRQ handlers of a PREEMPT_RT kernel (50), so network and timer interrupts
#: still preempt the loop).
DEFAULT_PRIORITY = int(shipped_defaults('live.yaml')['realtime_priority'])
#: The PM QoS device of the CPU wake-up latency request.
CPU_DMA_LATENCY = '/dev/cpu_dma_latency'

_latency_fd: Optional[int] = None   # held open for the process's lifetime


def hold_cpu_wakeup_latency(microseconds: int = 0, device: str = CPU_DMA_LATENCY) -> str:
    """Ask for a CPU wake-up latency of at most ``microseconds`` while this process lives.

    Returns 'cpu_dma_latency <us> us' (held; idempotent) or 'unavailable: <why>'.
    """
    global _latency_fd
    if _latency_fd is None:
        try:
            fd = os.open(device, os.O_WRONLY)
        except OSError as exc:
            return f'unavailable: {exc.strerror or exc}'
        try:
            os.write(fd, struct.pack('i', int(microseconds)))
        except OSError as exc:
            os.close(fd)
            return f'unavailable: {exc.strerror or exc}'
        _latency_fd = fd
    return f'cpu_dma_latency {int(microseconds)} us'


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
    latency = hold_cpu_wakeup_latency(0)
    if latency.startswith('unavailable'):
        warn(f'realtime_priority {priority}: CPU wake-up latency not requested '
             f'({CPU_DMA_LATENCY}: {latency[13:]}); idle CPUs may wake up slowly')
    return f'SCHED_FIFO {priority}'


__all__ = ['set_fifo_priority', 'hold_cpu_wakeup_latency', 'MAX_PRIORITY',
           'DEFAULT_PRIORITY', 'CPU_DMA_LATENCY']
