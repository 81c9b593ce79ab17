"""How long this process has run: the start of a bring-up stage table (no ROS).

A command's or a node's bring-up is measured from the moment its process started (the
kernel's start time, /proc/self/stat), so the interpreter's own start-up and the
imports count too -- what a user waits for after pressing Enter.
"""

import os
import time


def process_age_s() -> float:
    """Return the seconds since this process started (Linux; else since this module loaded).

    The kernel's start time is in clock ticks (10 ms) since boot, on the same clock as
    CLOCK_BOOTTIME.
    """
    try:
        with open('/proc/self/stat', encoding='ascii') as fh:
            fields = fh.read().rsplit(')', 1)[1].split()
        started = int(fields[19]) / os.sysconf('SC_CLK_TCK')    # field 22: starttime
        return max(0.0, time.clock_gettime(time.CLOCK_BOOTTIME) - started)
    except (OSError, ValueError, IndexError, AttributeError):
        return time.monotonic() - _LOADED


def process_start_monotonic() -> float:
    """Return when this process started, on time.monotonic()'s clock."""
    return time.monotonic() - process_age_s()


_LOADED = time.monotonic()

__all__ = ['process_age_s', 'process_start_monotonic']
