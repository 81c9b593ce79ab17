"""Simulated generator ECU (no ROS): CAN damping commands to the plant, sensor frames back.

It plays the vehicle side of the CAN link for the HIL loop: the quarter car is
:class:`erva_ros.core.model.plant.PlantSimulator` (the shared model, never a copy), with the
damping latched in steps of ``latch_s`` (default 1 ms, the ECU's PWM update
granularity).  It keeps a real ECU's timing: at each sample instant t_k it samples the
sensors and sends ERVA_ECU_STATUS, ERVA_SENS_CHASSIS and ERVA_SENS_GENERATOR at once;
the physics of the cycle [t_k, t_k+1] is integrated *ahead*, not when t_k+1 comes:

1. every command frame is E2E-checked (length, CRC, alive counter) when it is read and
   kept with its kernel receive time; the duty is clamped to the hardware range;
2. the cycle's latch plan follows from those times alone.  With the loop's command delay
   d > 0 (``command_delay_s``, logical execution time) a CONTROLLED or PLANNED frame
   acts at its own cycle's instant t_c + d (CMD_CYCLE names c), never at its arrival: at
   t_k + d the newest frame received *for cycle k* by then acts; one received after its
   instant is **late**, counted, and never acts (the late rule of
   erva_ros/core/loop/command_hold.py: the bridge sends the plan's next values ahead as
   PLANNED frames, so a late command's cycle gets the previous command's plan, as in
   plant_sim_node); no frame for cycle k → passive c_e0 (SAFE_TIMEOUT).  With d = 0 a
   frame acts at the first latch instant at or after its arrival.  Safety first, for any
   d: a SAFE_PASSIVE frame acts at once and cancels the frames received before it, and
   the **same timeout rule as the bridge** applies (no valid frame for
   ``command_timeout_s`` → safe passive duty c_e0, mode SAFE_TIMEOUT);
3. :meth:`EcuSimCore.prepare` (called ``prepare_lead_s`` before t_k+1) integrates the
   cycle with that plan in one compiled call (:meth:`PlantSimulator.integrate_profile`;
   the road linear between w(t_k) and w(t_k+1), as the shared model has it);
   :meth:`EcuSimCore.run_cycle` at t_k+1 reads what arrived meanwhile, integrates again
   only if a frame landed inside the cycle after the preparation (~15 µs), takes
   the step, samples (with noise, see :class:`SensorNoise`) and sends.

So the physics is exactly that of an ECU whose PWM timer fires at t_k + d (d on the
latch grid; otherwise at the next latch instant) although the simulator wakes only
three times per cycle: :meth:`EcuSimCore.actuate`, at t_k + d, measures the software
ECU's own lateness (the *actuation jitter*, ``actuation``), and every CONTROLLED frame's
arrival t_k → received (``arrival``) gives the d that would have had it on time.
``road(t)`` gives the road height at the tyre (m) at epoch time t (s); it must be
known up to t_k+1 when :meth:`EcuSimCore.prepare` runs (a road known ahead: the
session's road, or a local one); with a road that arrives sample by sample, call only
:meth:`EcuSimCore.run_cycle`, once the sample of t_k+1 is there.
"""

from dataclasses import dataclass
import math
import time
from typing import Callable, Dict, List, NamedTuple, Optional, Tuple

import can
import numpy as np

from erva_ros.core.model.codegen import BufferedCall
from erva_ros.core.hil.codec import (Chassis, CommandMode, cycle_of, E2EReceiver, EcuCodec,
                                     EcuMode, Generator, Kind, Status, unwrap_cycle)
from erva_ros.core.model.hardware import GeneratorHardware
from erva_ros.core.hil.settings import ECU_SIM_DEFAULTS as _SIM
from erva_ros.core.timing import DurationStats, PeriodStats
from erva_ros.core.model.quarter_car import QuarterCarModel
from erva_ros.core.model.plant import PlantSimulator, ProfileStep


@dataclass(frozen=True)
class EcuSimConfig:
    """Timing and safety of the simulated ECU (SI units)."""

    period_s: float = 0.02            # ECU cycle Ts: sensor frames at 50 Hz
    command_timeout_s: float = 0.06   # same rule as the bridge: 3 periods
    latch_s: float = 0.001            # command latch / plant step granularity
    c_e_safe: float = 10000.0         # Ns/m applied on timeout and at start-up (c_e0)
    max_delta_counter: int = 1
    prepare_lead_s: float = 0.003     # integrate the cycle this long before it ends
    command_delay_s: float = 0.0      # d: a command for cycle k acts at t_k + d (0: at arrival)


@dataclass(frozen=True)
class SensorNoise:
    """Standard deviations of the simulated sensors' white noise (SI units).

    Defaults (the ecu_sim section of the shipped config/hil.yaml) resemble automotive
    parts at a 50 Hz sample rate: a MEMS accelerometer (≈ 0.02 m/s²), a ride-height
    potentiometer (0.1 mm), the generator's encoder speed (0.01 rad/s), current shunt
    (10 mA) and back-emf sampling (50 mV).  The DBC's
    quantisation (1 mm/s², 10 µm, 1 mrad/s, 1 mA, 10 mV) comes on top.
    """

    sprung_accel: float = _SIM['noise_sprung_accel']     # m/s²
    deflection: float = _SIM['noise_deflection']         # m
    speed: float = _SIM['noise_speed']                   # rad/s
    current: float = _SIM['noise_current']               # A
    voltage: float = _SIM['noise_voltage']               # V
    seed: int = _SIM['seed']

    @staticmethod
    def none() -> 'SensorNoise':
        return SensorNoise(0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass
class EcuSample:
    """Ground truth of one ECU cycle (what the sensors saw, before noise)."""

    t: float                 # s since the ECU started
    x: np.ndarray            # plant state at t
    road_height: float       # m
    c_e: float               # Ns/m applied at t
    c_e_mean: float          # Ns/m, mean over the cycle that ended at t
    sprung_accel: float      # m/s²
    v_gen: float             # m/s
    power_w: float           # W at t
    harvested_j: float       # J since the start
    mode: EcuMode
    gen_position: float = 0.0            # m, generator displacement (model.generator)
    sent_at: Optional[float] = None      # epoch s once the sensor frames were sent
    command_latched: Optional[float] = None   # epoch s the cycle's first CONTROLLED
    #                                           command was applied (None: none came)


class _Command(NamedTuple):
    """A valid command frame, E2E-checked when read."""

    t: float                 # kernel receive time (epoch s)
    duty: float              # clamped to the hardware range
    mode: CommandMode        # SAFE_PASSIVE, CONTROLLED or PLANNED
    out_of_range: bool       # the duty sent was outside the range (or not finite)
    cycle: int               # CMD_CYCLE: the cycle it is for, mod 256


class _CyclePlan(NamedTuple):
    """The latch decisions of one cycle, the ECU state they end in, and the physics."""

    key: Tuple[int, int]     # (cycle index, commands latched): recompute when it changes
    used: int                # pending commands latched in the cycle
    c_e: List[float]         # Ns/m per latch step
    duty: float              # at the cycle's end, after latching there
    mode: EcuMode
    last_cmd: float          # epoch s of the last valid command
    first_controlled: Optional[float]   # latch instant of the first CONTROLLED command
    changes: List[Tuple[str, float]]    # mode changes at the latch instants: (mode, c_e)
    step: ProfileStep
    road_end: float          # m, w at the cycle's end
    mailbox: Dict[int, _Command]        # d > 0: the newest frame for each coming cycle
    tally: Dict[str, int]               # counters of the cycle (COUNTER_NAMES)
    arrivals: List[Tuple[int, float, float]]   # CONTROLLED frames: (cycle, rx, rx − t_c)
    late: List[int]                     # cycle indices (k) of the late CONTROLLED frames


COUNTER_NAMES = ('cycles', 'commands_applied', 'duty_out_of_range', 'command_timeouts',
                 'frames_sent', 'send_errors', 'bus_losses', 'reconnects', 'overruns',
                 'cycles_skipped', 'recomputed', 'mode_changes_unlogged', 'late_commands',
                 'late_plan_frames', 'u_from_command', 'u_from_plan', 'u_from_passive')
#: Counted per latch plan (the rest by the loop).
_TALLY = ('commands_applied', 'duty_out_of_range', 'command_timeouts', 'late_commands',
          'late_plan_frames', 'u_from_command', 'u_from_plan', 'u_from_passive')
#: Mode changes kept for the status (cycle, mode, applied c_e): enough for a run's story;
#: later ones are only counted (``mode_changes_unlogged``).
MODE_LOG_SIZE = 64


class EcuSimCore:
    """The ECU side of the CAN link with the quarter car behind it."""

    def __init__(self, model: QuarterCarModel, hardware: GeneratorHardware, codec: EcuCodec,
                 bus_factory: Callable[[], can.BusABC], road: Callable[[float], float],
                 config: EcuSimConfig = EcuSimConfig(), noise: SensorNoise = SensorNoise()):
        n = config.period_s / config.latch_s
        if abs(n - round(n)) > 1e-6 or n < 1:
            raise ValueError(f'period_s {config.period_s} must be a whole number of latch_s '
                             f'{config.latch_s}')
        if not 0.0 <= config.command_delay_s < config.period_s:
            raise ValueError(f'command_delay_s {config.command_delay_s:g} s must be in '
                             f'[0, Ts = {config.period_s:g} s)')
        self.cfg = config
        self.hw = hardware
        self.codec = codec
        self.params = model.params
        self.road = road
        self.noise = noise
        self._n_latch = int(round(n))
        self.ts_ns = int(round(config.period_s * 1e9))
        #: d > 0: frames act at their cycle's instant (logical execution time), at latch
        #: step ``act_latch`` of the cycle: d on the latch grid, else the next latch instant.
        self.let = config.command_delay_s > 0
        self.act_latch = int(math.ceil(config.command_delay_s / config.latch_s - 1e-9))
        self.plant = PlantSimulator(model, ts=config.period_s)
        # Built (and compiled or loaded) now, not in the first cycle: that costs ms.
        self.plant.integrate_profile([config.c_e_safe] * self._n_latch,
                                     [0.0] * (self._n_latch + 1))
        self._generator = BufferedCall(self.plant.model.generator)
        self._measurements = BufferedCall(self.plant.model.measurements)
        self._rng = np.random.default_rng(noise.seed)
        self._factory = bus_factory
        self.bus: Optional[can.BusABC] = None
        self.bus_error = ''
        self._rx = E2EReceiver(codec, (Kind.COMMAND,), config.command_timeout_s,
                               config.max_delta_counter)
        self._tx = {k: codec.sender(k) for k in (Kind.CHASSIS, Kind.GENERATOR, Kind.STATUS)}
        self.counts: Dict[str, int] = dict.fromkeys(COUNTER_NAMES, 0)
        # Its own calibrated c_e0 in every safe mode (also on the bridge's safe command,
        # whose duty the frame carries rounded): the same damping however it went safe.
        self._safe_duty, _ = hardware.clamp_duty(hardware.duty_from_c_e(config.c_e_safe))
        self.duty = self._safe_duty
        self.mode = EcuMode.INIT
        self._last_cmd = -math.inf            # epoch s of the last valid command
        self._inbox: List[can.Message] = []   # read, not yet E2E-checked
        self._pending: List[_Command] = []    # valid, not yet latched (arrival order)
        self._mailbox: Dict[int, _Command] = {}   # d > 0: newest frame per coming cycle
        self._plan: Optional[_CyclePlan] = None
        self.mode_log: List[Tuple[int, str, float]] = []
        self._logged_mode = ''                # the newest change, logged or only counted
        self.t0: Optional[float] = None       # epoch s of cycle 0
        self.cycle0 = 0                       # its cycle number (codec.cycle_of)
        self.k = 0
        #: t_k -> CONTROLLED frame received (s), its period |Δt − Ts|, and the actuation
        #: instant's lateness (:meth:`actuate`) -- the timing model's figures.
        self.arrival = DurationStats()
        self.command_period = PeriodStats(config.period_s)
        self.actuation = DurationStats()
        self.first_late_cycle: Optional[int] = None   # cycle index k of the first late one
        self._acted = -1                      # the cycle whose actuation instant was taken

    # ------------------------------------------------------------------ bus
    def open(self) -> bool:
        """Open the bus now if it is not open; return True if it is up (else see bus_error)."""
        return self._ensure_bus()

    def _ensure_bus(self) -> bool:
        if self.bus is not None:
            return True
        try:
            self.bus = self._factory()
        except Exception as exc:  # reported and retried next cycle, never raised
            self.bus_error = f'cannot open bus: {exc}'
            return False
        if self.counts['cycles']:
            self.counts['reconnects'] += 1
        self._rx.reset()
        self.bus_error = ''
        return True

    def _lost(self, exc: BaseException) -> None:
        self.counts['bus_losses'] += 1
        self.bus_error = f'bus lost: {exc}'
        try:
            self.bus.shutdown()
        except Exception:  # a dead interface may fail to close; dropped anyway
            pass
        self.bus = None

    def _read(self) -> None:
        """Move every frame waiting on the bus to the inbox."""
        if not self._ensure_bus():
            return
        try:
            while True:
                msg = self.bus.recv(0.0)
                if msg is None:
                    return
                self._inbox.append(msg)
        except (can.CanError, OSError, ValueError) as exc:
            self._lost(exc)

    def _check_inbox(self) -> None:
        """E2E-check the frames read, in arrival order; keep the valid commands."""
        for msg in self._inbox:
            kind, _, cmd = self._rx.accept(msg, msg.timestamp)
            if kind is not Kind.COMMAND or cmd is None:
                continue
            duty, clamped = self.hw.clamp_duty(cmd.duty)
            self._pending.append(_Command(msg.timestamp, duty, cmd.mode,
                                          clamped or not math.isfinite(cmd.duty), cmd.cycle))
        self._inbox = []

    def _send(self, kind: Kind, payload) -> None:
        if self.bus is None:
            return
        try:
            self.bus.send(self.codec.encode(kind, payload, self._tx[kind]), timeout=0.005)
            self.counts['frames_sent'] += 1
        except (can.CanError, OSError, ValueError) as exc:
            self.counts['send_errors'] += 1
            self._lost(exc)

    def close(self) -> None:
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None

    # ------------------------------------------------------------------ ECU logic
    @property
    def due(self) -> float:
        """Return the epoch time of the next sample t_k+1 (s)."""
        return self.t0 + (self.k + 1) * self.cfg.period_s

    def _t(self, cycle: int) -> float:
        """Return the instant t_c (epoch s) of cycle number ``cycle``."""
        return self.t0 + (cycle - self.cycle0) * self.cfg.period_s

    @property
    def act_due(self) -> Optional[float]:
        """Return this cycle's actuation instant t_k + d (epoch s); None if taken or d = 0."""
        if not self.let or self._acted == self.k:
            return None
        return self.t0 + self.k * self.cfg.period_s + self.cfg.command_delay_s

    def _latch_plan(self) -> _CyclePlan:
        """Return the plan of the cycle [t_k, t_k+1] from the commands read so far.

        Pure: nothing is committed, so it is recomputed when a command arrives inside
        the cycle after an earlier (ahead-of-time) plan.  The rules: module doc, item 2.
        """
        ts, dt, n = self.cfg.period_s, self.cfg.latch_s, self._n_latch
        t_start = self.t0 + self.k * ts
        t_end = t_start + ts
        pending = self._pending
        due = 0
        while due < len(pending) and pending[due].t <= t_end:
            due += 1
        key = (self.k, due)
        if self._plan is not None and self._plan.key == key:
            return self._plan
        duty, mode, last = self.duty, self.mode, self._last_cmd
        now = self.cycle0 + self.k                      # this cycle's number
        mailbox = dict(self._mailbox)
        tally = dict.fromkeys(_TALLY, 0)
        arrivals: List[Tuple[int, float, float]] = []
        late: List[int] = []
        i = 0
        first = None
        c_e = []
        changes = []

        def apply(cmd: _Command) -> None:
            nonlocal duty, mode, first
            duty = cmd.duty
            mode = (EcuMode.SAFE_REQUESTED if cmd.mode is CommandMode.SAFE_PASSIVE
                    else EcuMode.CONTROLLED)
            tally['commands_applied'] += 1
            tally['duty_out_of_range'] += cmd.out_of_range
            if first is None and mode is EcuMode.CONTROLLED:
                first = tau

        for j in range(n + 1):
            tau = t_start + j * dt
            while i < due and pending[i].t <= tau:
                cmd = pending[i]
                i += 1
                last = cmd.t
                if cmd.mode is CommandMode.SAFE_PASSIVE:      # safety first: at once
                    mailbox.clear()
                    apply(cmd)
                    continue
                c = unwrap_cycle(cmd.cycle, now)
                if cmd.mode is CommandMode.CONTROLLED:
                    arrivals.append((c - self.cycle0, cmd.t, cmd.t - self._t(c)))
                if not self.let:                              # d = 0: at arrival
                    apply(cmd)
                    continue
                act = self._t(c) + self.cfg.command_delay_s
                if cmd.t > act or c < now or (c == now and j > self.act_latch):
                    if cmd.mode is CommandMode.CONTROLLED:
                        tally['late_commands'] += 1
                        late.append(c - self.cycle0)
                    else:
                        tally['late_plan_frames'] += 1
                    continue
                mailbox[c] = cmd                              # the newest for cycle c
            if tau - last > self.cfg.command_timeout_s and mode not in (
                    EcuMode.INIT, EcuMode.SAFE_TIMEOUT):
                mode = EcuMode.SAFE_TIMEOUT
                tally['command_timeouts'] += 1
                mailbox.clear()
            if self.let and j == self.act_latch:              # t_k + d: this cycle's frame
                cmd = mailbox.pop(now, None)
                for c in [c for c in mailbox if c < now]:
                    del mailbox[c]
                if cmd is not None:
                    apply(cmd)
                    tally['u_from_command' if cmd.mode is CommandMode.CONTROLLED
                          else 'u_from_plan'] += 1
                else:
                    tally['u_from_passive'] += 1
                    if mode is EcuMode.CONTROLLED:            # the plan ran out
                        mode = EcuMode.SAFE_TIMEOUT
                        tally['command_timeouts'] += 1
            if mode in (EcuMode.INIT, EcuMode.SAFE_TIMEOUT, EcuMode.SAFE_REQUESTED):
                duty = self._safe_duty
            # Every change, also one undone within the cycle (a timeout the next command
            # ends before the sample): the log must account for every timeout counted.
            if mode is not (changes[-1][0] if changes else self.mode):
                changes.append((mode, self.hw.c_e_from_duty(duty)))
            if j < n:
                c_e.append(self.hw.c_e_from_duty(duty))
        # The road linear between its samples, as the shared model has it (plant.py): the
        # same heights whatever the epoch time's rounding, so two runs agree bit for bit.
        w0, w1 = self.road(t_start), self.road(t_end)
        road = [w0 + (w1 - w0) * j / n for j in range(n)] + [w1]
        step = self.plant.integrate_profile(c_e, road)
        if self._plan is not None and self._plan.key[0] == self.k:
            self.counts['recomputed'] += 1
        self._plan = _CyclePlan(key, due, c_e, duty, mode, last, first,
                                [(m.name, u) for m, u in changes], step, road[-1], mailbox,
                                tally, arrivals, late)
        return self._plan

    def start(self, t0: float, cycle0: Optional[int] = None) -> EcuSample:
        """Begin at epoch time ``t0``: open the bus, send the first sensor frames.

        ``cycle0`` is the cycle number of t0 (default :func:`cycle_of` of t0 rounded to
        the ns; pass it when t0 is known in ns, so the frames' CMD_CYCLE match exactly).
        """
        self.t0 = t0
        self.cycle0 = (cycle_of(int(round(t0 * 1e9)), self.ts_ns) if cycle0 is None
                       else int(cycle0))
        self.k = 0
        self._plan = None
        self._acted = -1
        self._ensure_bus()
        # Commands queued while the ECU waited to start (e.g. for the road) are history:
        # keep only those still fresh at t0.
        self._read()
        self._inbox = [m for m in self._inbox if m.timestamp > t0 - self.cfg.command_timeout_s]
        self._check_inbox()
        return self._measure_and_send(t0, self.hw.c_e_from_duty(self.duty), self.road(t0))

    def prepare(self) -> None:
        """Integrate the current cycle ahead of its end, with the commands read so far."""
        if self.t0 is None:
            raise RuntimeError('call start() first')
        self._read()
        self._check_inbox()
        self._latch_plan()

    def collect(self) -> None:
        """Read and check the frames received so far (ahead of the actuation instant)."""
        self._read()
        self._check_inbox()

    def actuate(self, now: Callable[[], float] = time.time) -> float:
        """Take this cycle's actuation instant t_k + d; return (and record) its lateness.

        The software ECU's PWM update, called when its timer fires: ``now() − (t_k + d)``
        (s) goes to :attr:`actuation` -- the actuation jitter.  The physics applies
        exactly at t_k + d (on the latch grid) whatever this lateness, from the frames'
        receive times.
        """
        at = self.act_due
        if at is None:
            return math.nan
        self._acted = self.k
        lag = now() - at
        self.actuation.add(lag)
        return lag

    def run_cycle(self, send: bool = True) -> EcuSample:
        """End the cycle [t0 + k·Ts, t0 + (k+1)·Ts] (epoch s): take its step, sample, send.

        The step was integrated ahead by :meth:`prepare` unless a command arrived inside
        the cycle since.  ``send=False`` only integrates (catching up after an overrun).
        """
        if self.t0 is None:
            raise RuntimeError('call start() first')
        self._read()
        self._check_inbox()
        plan = self._latch_plan()
        self.plant.apply(plan.step)
        del self._pending[:plan.used]
        self.duty, self.mode, self._last_cmd = plan.duty, plan.mode, plan.last_cmd
        self._mailbox = plan.mailbox
        for key, n in plan.tally.items():
            self.counts[key] += n
        for _, rx, lag in plan.arrivals:
            self.arrival.add(lag)
            self.command_period.mark(rx)
        if plan.late and self.first_late_cycle is None:
            self.first_late_cycle = min(plan.late)
        self._plan = None
        self.k += 1
        self.counts['cycles'] += 1
        for mode, c_e in plan.changes:
            self._log_mode(mode, c_e)
        sample = self._measure_and_send(self.t0 + self.k * self.cfg.period_s,
                                        sum(plan.c_e) / self._n_latch, plan.road_end, send)
        sample.command_latched = plan.first_controlled
        return sample

    def _measure_and_send(self, t_epoch: float, c_e_mean: float, w: float,
                          send: bool = True) -> EcuSample:
        u = self.hw.c_e_from_duty(self.duty)
        s = self.plant.sample(u, w)
        position, v_gen, _ = self._generator(s.x, u)
        _, deflection, speed = map(float, self._measurements(s.x, u, w)[0])
        n, r = self.noise, self._rng
        chassis = Chassis(sprung_accel=s.sprung_accel + n.sprung_accel * r.standard_normal(),
                          deflection=deflection + n.deflection * r.standard_normal())
        gen = Generator(speed=speed + n.speed * r.standard_normal(),
                        current=self.hw.current(u, v_gen) + n.current * r.standard_normal(),
                        voltage=self.hw.back_emf(v_gen) + n.voltage * r.standard_normal())
        rx = self._rx.counts()
        rejected = sum(rx[k] for k in ('wrong_length', 'bad_crc', 'repeated', 'skipped',
                                       'bad_counter'))
        status = Status(mode=self.mode, c_e_applied=u, c_e_mean=c_e_mean,
                        cmd_rejected=rejected % 256,
                        cmd_timeouts=self.counts['command_timeouts'] % 256)
        sent_at = None
        if send:
            self._send(Kind.STATUS, status)
            self._send(Kind.CHASSIS, chassis)
            self._send(Kind.GENERATOR, gen)
            sent_at = time.time()
        self._log_mode(self.mode.name, u)
        return EcuSample(t=t_epoch - self.t0, x=s.x, road_height=w, c_e=u, c_e_mean=c_e_mean,
                         sprung_accel=s.sprung_accel, v_gen=v_gen, power_w=s.power_w,
                         harvested_j=s.harvested_j, mode=self.mode, gen_position=position,
                         sent_at=sent_at)

    def _log_mode(self, mode: str, c_e: float) -> None:
        """Log a change to ``mode`` (applying ``c_e``) in the cycle that ends at sample k."""
        if mode == self._logged_mode:
            return
        self._logged_mode = mode
        if len(self.mode_log) < MODE_LOG_SIZE:
            self.mode_log.append((self.k, mode, c_e))
        else:
            self.counts['mode_changes_unlogged'] += 1

    def rx_counts(self) -> Dict[str, int]:
        """Return the E2E counters of the received command frames."""
        return self._rx.counts()

    def summary(self) -> Dict[str, int]:
        """Return all counters (ECU and E2E) as one dict."""
        out = dict(self.counts)
        out.update({f'rx_{k}': v for k, v in self.rx_counts().items()})
        return out

    def mode_changes(self) -> str:
        """Return the mode changes as ``cycle:MODE:c_e`` items (c_e applied, Ns/m).

        ``cycle`` is the sample k that ends the cycle in which the mode changed (at a 1 ms
        latch instant); a change undone within one cycle is listed too (two items with
        the same k), so every ``command_timeouts`` count has its SAFE_TIMEOUT item.
        """
        return ','.join(f'{k}:{mode}:{c_e:.0f}' for k, mode, c_e in self.mode_log)


#: The wait for an actuation instant: ``wait`` (which may be busy with a callback) until
#: this long before it, then the frames are read, then a plain sleep: a software timer.
#: (A busy wait for the last 0.2 ms had a longer tail among the loop's other real-time
#: processes: p99 0.30-0.43 ms against 0.06-0.08 ms, two alternating 10 s runs each.)
ACT_GUARD_S = 0.0005


def run_realtime(core: EcuSimCore, duration_s: float = 0.0,
                 on_cycle: Optional[Callable[[EcuSample], None]] = None,
                 should_stop: Callable[[], bool] = lambda: False,
                 wait: Optional[Callable[[float], None]] = None,
                 t0: Optional[float] = None,
                 ahead: bool = True,
                 until_road: Optional[Callable[[float], None]] = None,
                 cycle0: Optional[int] = None) -> int:
    """Run ``core`` against the wall clock until ``duration_s`` (0: forever) or ``should_stop``.

    ``wait(seconds)`` sleeps (default time.sleep; a ROS caller passes a function that
    spins its executor meanwhile).  ``t0`` (epoch s, default now) is the time of cycle 0,
    e.g. an instant of the road's sample grid, and ``cycle0`` its cycle number
    (:meth:`EcuSimCore.start`).  With ``ahead`` (the road is known up to the next sample)
    each cycle is integrated ``prepare_lead_s`` before its end, so the sensor frames go
    out as soon as the sample instant has come; otherwise ``until_road(t)`` is called at
    each sample instant t to wait for its road sample, then the cycle is integrated and
    sent.  With d > 0 the loop also wakes at each actuation instant t_k + d
    (:meth:`EcuSimCore.actuate`).  A cycle that starts more than one period late is
    counted as an overrun; the missed cycles are integrated without sending, so the
    plant stays on the wall clock.  Returns the number of cycles run.
    """
    wait = wait or time.sleep
    ts, lead = core.cfg.period_s, core.cfg.prepare_lead_s
    sample = core.start(time.time() if t0 is None else t0, cycle0)
    if on_cycle:
        on_cycle(sample)
    prepared = -1
    while not should_stop():
        if duration_s > 0 and core.k * ts >= duration_s - 1e-9:
            break
        due = core.due
        act = core.act_due
        prep = due - lead if ahead and prepared != core.k else None
        if act is not None and (prep is None or act <= prep):
            delay = act - time.time()
            if delay > ACT_GUARD_S:
                wait(delay - ACT_GUARD_S)
                continue                         # woke (maybe early): look again
            core.collect()
            delay = act - time.time()
            if delay > 0:
                time.sleep(delay)
            core.actuate()
            continue
        if prep is not None:
            delay = prep - time.time()
            if delay > 0:
                wait(delay)
                continue
            core.prepare()
            prepared = core.k
            continue
        delay = due - time.time()
        if delay > 0:
            wait(delay)
            continue
        if -delay > ts:
            core.counts['overruns'] += 1
            core.counts['cycles_skipped'] += int(-delay // ts)   # integrated, never sent
            for _ in range(int(-delay // ts)):
                core.run_cycle(send=False)
            continue                             # the current cycle, prepared anew
        if not ahead and until_road is not None:
            until_road(due)
        sample = core.run_cycle()
        if on_cycle:
            on_cycle(sample)
    return core.k
