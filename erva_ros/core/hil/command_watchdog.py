"""The bridge's command watchdog (no ROS): damping plans → command frames at the period Ts.

:meth:`CommandWatchdog.submit` takes the NMPC's plan (``damping_cmd`` points: c_e for
its sample t_c, then for t_c + j·Ts, Ns/m), rejects non-finite or empty plans, clamps
every value to the hardware range (:class:`~erva_ros.core.model.hardware.GeneratorHardware`)
and sends points[0] at once as duty D = c_e / c_e,full, CONTROLLED, with the cycle it is
for (CMD_CYCLE = c mod 256, :func:`~erva_ros.core.hil.codec.cycle_of` of the stamp).

With the loop's command delay d > 0 the ECU applies a frame at its cycle's instant
t_c + d (docs/hil.md, the real-ECU contract), so the plan goes out with the command:
points[j] for cycle c + j as PLANNED frames, for the cycles up to ``command_timeout_s``
after the sample.  The command of a later sample replaces them if it comes in time; if
it is late, the ECU applies the plan -- the late rule of plant_sim_node.  A command
whose stamp is not after the previous one's would overwrite newer plans: refused as
stale.  :meth:`CommandWatchdog.tick` (called every Ts/4) keeps the ECU safe:

* a command is *fresh* for ``command_timeout_s`` (default 3·Ts) after it arrived;
* with d = 0 (the ECU applies a frame when it arrives): if no frame went out for
  1.5·Ts while the command is fresh (the NMPC is late), the plan's point for the elapsed
  time is sent, PLANNED (the NMPC's own plan, not a guess);
* once the command is stale, the **safe passive command** (c_e0, CMD_MODE =
  SAFE_PASSIVE) is sent every Ts and :attr:`CommandWatchdog.state` is ``timeout`` until
  a fresh command arrives; :attr:`CommandWatchdog.timeouts_worst` keeps the most plan
  frames that went out before a timeout, and the largest command age at which one was
  declared;
* a command that is already older than ``command_timeout_s`` when it arrives is
  refused (``commands_stale``);
* before the first command it sends the safe command too (state ``waiting``).

Frames go out through ``send`` (:meth:`erva_ros.core.hil.bus_link.BusLink.send`).
Thread-safe for :meth:`submit` and :meth:`tick` called from two threads.
"""

import math
import threading
from typing import Callable, Dict, List, Optional, Sequence

import can

from erva_ros.core.hil.codec import Command, CommandMode, CYCLE_MODULO, cycle_of, EcuCodec, Kind
from erva_ros.core.model.hardware import GeneratorHardware

COUNTER_NAMES = ('commands_received', 'commands_rejected', 'commands_stale',
                 'commands_clamped', 'commands_wrong_delay', 'frames_sent', 'safe_frames_sent',
                 'plan_frames_sent', 'command_timeouts')


class CommandWatchdog:
    """Commands to the ECU: the plan, its freshness, the safe command (see module doc)."""

    def __init__(self, codec: EcuCodec, hardware: GeneratorHardware, period_s: float,
                 timeout_s: float, c_e_safe: float, send: Callable[[can.Message], bool],
                 delay_s: float = 0.0):
        self.codec = codec
        self.hw = hardware
        self.period_s = float(period_s)
        self.ts_ns = int(round(self.period_s * 1e9))
        self.timeout_s = float(timeout_s)
        self.c_e_safe = float(c_e_safe)
        self.delay_s = float(delay_s)
        #: d > 0: plan points sent ahead with each command (cycles c+1 .. c+ahead).
        self.ahead = int(math.floor(self.timeout_s / self.period_s + 1e-9)) if delay_s > 0 else 0
        self._send = send
        self._lock = threading.RLock()          # plan, send times, E2E sender
        self._tx = codec.sender(Kind.COMMAND)
        self._plan: Optional[List[float]] = None
        self._offsets: List[float] = []
        self._plan_time = -math.inf
        self._cycle = 0                         # the cycle number of the plan's points[0]
        self._stamp: Optional[int] = None       # the newest command's stamp (ns)
        self._last_send = -math.inf
        self.state = 'waiting'                  # waiting | fresh | timeout
        self.last_command: Optional[Command] = None
        self._plan_frames = 0                   # plan frames since the last command
        #: Over all timeouts: the most plan frames sent after the last command, and the
        #: largest command age (s) at which the timeout was declared.
        self.timeouts_worst: Dict[str, float] = {'plan_frames': 0, 'command_age_s': 0.0}
        self.counts: Dict[str, int] = dict.fromkeys(COUNTER_NAMES, 0)

    def submit(self, plan: Sequence[float], now: float,
               offsets: Optional[Sequence[float]] = None,
               age_s: Optional[float] = None, stamp_ns: Optional[int] = None) -> str:
        """Take a new damping plan (Ns/m; plan[j] for t_c + j·Ts) and send plan[0] at once.

        ``offsets`` are the plan points' times after the command's action instant (s;
        default j·Ts).  ``age_s`` is how old the command was when it arrived (its sample
        instant to its arrival, s; None: unknown).  ``stamp_ns`` is its sample instant t_c
        (needed with d > 0: the cycle its frames are for).  Returns 'sent', 'clamped'
        (sent after clamping), 'not_sent' (bus down), 'rejected' (empty or non-finite:
        ignored, the previous command ages on) or 'stale' (older than ``timeout_s``, or
        with d > 0 not after the previous command: ignored and counted as well).
        """
        values = [float(v) for v in plan]
        if not values or not all(math.isfinite(v) for v in values):
            self.counts['commands_rejected'] += 1
            return 'rejected'
        if age_s is not None and not age_s <= self.timeout_s:
            self.counts['commands_stale'] += 1
            return 'stale'
        if self.delay_s > 0 and (stamp_ns is None or (
                self._stamp is not None and stamp_ns <= self._stamp)):
            self.counts['commands_stale'] += 1
            return 'stale'
        if offsets is None or len(offsets) != len(values):
            offsets = [k * self.period_s for k in range(len(values))]
        first = offsets[0]
        clamped = [self.hw.clamp_c_e(v) for v in values]
        with self._lock:
            self._plan = [v for v, _ in clamped]
            self._offsets = [float(o) - first for o in offsets]
            self._plan_time = now
            self._stamp = stamp_ns
            self._cycle = 0 if stamp_ns is None else cycle_of(stamp_ns, self.ts_ns)
            self.counts['commands_received'] += 1
            self._plan_frames = 0
            if clamped[0][1]:
                self.counts['commands_clamped'] += 1
            self.state = 'fresh'
            sent = self._send_c_e(self._plan[0], CommandMode.CONTROLLED, now, self._cycle)
            for j in range(1, min(self.ahead, len(self._plan) - 1) + 1):
                if self._send_c_e(self._plan[j], CommandMode.PLANNED, now, self._cycle + j):
                    self.counts['plan_frames_sent'] += 1
        if not sent:
            return 'not_sent'
        return 'clamped' if clamped[0][1] else 'sent'

    def reject(self, wrong_delay: bool = False) -> None:
        """Count a command refused before it got here.

        It was malformed or, ``wrong_delay``, made for another command delay than this
        loop's d (contract.check_command_delay).
        """
        self.counts['commands_rejected'] += 1
        if wrong_delay:
            self.counts['commands_wrong_delay'] += 1

    def _send_c_e(self, c_e: float, mode: CommandMode, now: float, cycle: int = 0) -> bool:
        duty, _ = self.hw.clamp_duty(self.hw.duty_from_c_e(c_e))
        cmd = Command(duty=duty, c_e=c_e, mode=mode, cycle=cycle % CYCLE_MODULO)
        ok = self._send(self.codec.encode(Kind.COMMAND, cmd, self._tx))
        if ok:
            self.last_command = cmd
            self._last_send = now
            self.counts['frames_sent'] += 1
            if mode is CommandMode.SAFE_PASSIVE:
                self.counts['safe_frames_sent'] += 1
        return ok

    def command_age(self, now: float) -> float:
        """Return the time since the last accepted command (s; inf before the first)."""
        return now - self._plan_time

    def tick(self, now: float) -> None:
        """Follow the plan while a command is late, or send the safe command (every Ts/4)."""
        with self._lock:
            self._tick(now)

    def _tick(self, now: float) -> None:
        period = self.period_s
        since_send = now - self._last_send
        if self.command_age(now) > self.timeout_s:
            if self.state == 'fresh':
                self.state = 'timeout'
                self.counts['command_timeouts'] += 1
                # What the NMPC's last plan covered before going safe (docs/hil.md).
                worst = self.timeouts_worst
                worst['plan_frames'] = max(worst['plan_frames'], self._plan_frames)
                worst['command_age_s'] = max(worst['command_age_s'], self.command_age(now))
                since_send = math.inf           # go safe now, not at the next period
            if since_send >= period * 0.95:
                self._send_c_e(self.c_e_safe, CommandMode.SAFE_PASSIVE, now)
        elif since_send >= 1.5 * period and not self.delay_s > 0:
            age = self.command_age(now) + 1e-9
            k = 0                               # the plan point due now
            for i, offset in enumerate(self._offsets):
                if offset <= age:
                    k = i
            if self._send_c_e(self._plan[k], CommandMode.PLANNED, now, self._cycle + k):
                self.counts['plan_frames_sent'] += 1
                self._plan_frames += 1
