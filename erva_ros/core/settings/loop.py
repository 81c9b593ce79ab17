"""The live loop's own specs: its sample time Ts, its command delay d, its time bases.

Leaves of every table (core/settings/controller.py, schemas.py): one spec each.
"""

from erva_ros.core.settings.specs import Number

#: Highest SCHED_FIFO priority a node may ask for (99 is the kernel's watchdogs').
MAX_PRIORITY = 98
#: Time bases of the live loop.
MODES = ('realtime', 'lockstep')

#: The sample time Ts of plant, road, controller and ECU: the one spec of ``ts``.
TS_SPEC = Number(1e-3, 1.0, 's', 'sample time Ts of the loop: plant, road, controller, ECU '
                 '(paper: 0.02)')
#: The loop's command delay d: the one spec of ``command_delay_s`` (logical execution time).
COMMAND_DELAY_SPEC = Number(0.0, 1.0, 's', 'command delay d: each command acts at its sample '
                            't_k + d (plant, ECU) and the OCP plans from x(t_k + d); < ts, '
                            '0 = the paper\'s ideal loop', lo_open=False)
#: Models understood everywhere a ``--model`` or ``model`` parameter is accepted.
MODEL_KINDS = ('erva', 'benchmark')


def command_delay_ns(command_delay_s: float) -> int:
    """Return the command delay d in integer ns (stamps are ns): its one conversion."""
    return int(round(command_delay_s * 1e9))
