"""Simulated generator ECU (no ROS): CAN damping commands to the plant, sensor frames back.

It plays the vehicle side of the CAN link for the HIL loop: the quarter car is
:class:`erva_ros.plant.PlantSimulator` (the shared model, never a copy), advanced
in latch steps of ``latch_s`` (default 1 ms, the ECU's PWM update granularity).
Once per ECU cycle Ts, :meth:`EcuSimCore.run_cycle`

1. reads every command frame that arrived (each carries its receive time),
2. integrates the cycle in latch steps; at every latch instant τ a command that
   arrived before τ is applied (E2E-checked: length, CRC, alive counter; the duty
   is clamped to the hardware range and counted if it was outside), and the
   **same timeout rule as the bridge** applies: no valid command for
   ``command_timeout_s`` → safe passive duty (c_e0), mode SAFE_TIMEOUT,
3. samples the sensors at the end of the cycle (with noise, see :class:`SensorNoise`)
   and sends ERVA_ECU_STATUS, ERVA_SENS_CHASSIS, ERVA_SENS_GENERATOR.

``road(t)`` gives the road height at the tyre (m) at epoch time t (s), so a road
published on ROS (stamped with the same wall clock) can drive it directly.
Because frames carry kernel receive times (SocketCAN, :class:`LoopbackUdpBus`) the
physics is the same as an ECU that latches each command within 1 ms of its arrival,
although the simulator itself only wakes once per cycle.
"""

from dataclasses import dataclass
import math
import time
from typing import Callable, Dict, List, Optional

import can
import numpy as np

from erva_ros.hil.codec import (Chassis, CommandMode, E2EReceiver, EcuCodec, EcuMode,
                                Generator, Kind, Status)
from erva_ros.hil.hardware import GeneratorHardware
from erva_ros.params import ERVAParams
from erva_ros.plant import PlantSimulator


@dataclass(frozen=True)
class EcuSimConfig:
    """Timing and safety of the simulated ECU (SI units)."""

    period_s: float = 0.02            # ECU cycle Ts: sensor frames at 50 Hz
    command_timeout_s: float = 0.06   # same rule as the bridge: 3 periods
    latch_s: float = 0.001            # command latch / plant step granularity
    c_e_safe: float = 10000.0         # Ns/m applied on timeout and at start-up (c_e0)
    max_delta_counter: int = 1


@dataclass(frozen=True)
class SensorNoise:
    """Standard deviations of the simulated sensors' white noise (SI units).

    Defaults resemble automotive parts at a 50 Hz sample rate: a MEMS accelerometer
    (≈ 0.02 m/s²), a ride-height potentiometer (0.1 mm), the generator's encoder speed
    (0.01 rad/s), current shunt (10 mA) and back-emf sampling (50 mV).  The DBC's
    quantisation (1 mm/s², 10 µm, 1 mrad/s, 1 mA, 10 mV) comes on top.
    """

    sprung_accel: float = 0.02        # m/s²
    deflection: float = 1e-4          # m
    speed: float = 0.01               # rad/s
    current: float = 0.01             # A
    voltage: float = 0.05             # V
    seed: int = 0

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


COUNTER_NAMES = ('cycles', 'commands_applied', 'duty_out_of_range', 'command_timeouts',
                 'frames_sent', 'send_errors', 'bus_losses', 'reconnects', 'overruns')


class EcuSimCore:
    """The ECU side of the CAN link with the quarter car behind it."""

    def __init__(self, params: ERVAParams, hardware: GeneratorHardware, codec: EcuCodec,
                 bus_factory: Callable[[], can.BusABC], road: Callable[[float], float],
                 config: EcuSimConfig = EcuSimConfig(), noise: SensorNoise = SensorNoise(),
                 kind: str = 'erva'):
        n = config.period_s / config.latch_s
        if abs(n - round(n)) > 1e-6 or n < 1:
            raise ValueError(f'period_s {config.period_s} must be a whole number of latch_s '
                             f'{config.latch_s}')
        self.cfg = config
        self.hw = hardware
        self.codec = codec
        self.params = params
        self.road = road
        self.noise = noise
        self._n_latch = int(round(n))
        self.plant = PlantSimulator(params, kind, ts=config.latch_s)
        self._v_gen = self.plant.model.generator_velocity
        self._rng = np.random.default_rng(noise.seed)
        self._factory = bus_factory
        self.bus: Optional[can.BusABC] = None
        self.bus_error = ''
        self._rx = E2EReceiver(codec, (Kind.COMMAND,), config.command_timeout_s,
                               config.max_delta_counter)
        self._tx = {k: codec.sender(k) for k in (Kind.CHASSIS, Kind.GENERATOR, Kind.STATUS)}
        self.counts: Dict[str, int] = dict.fromkeys(COUNTER_NAMES, 0)
        self._safe_duty, _ = hardware.clamp_duty(hardware.duty_from_c_e(config.c_e_safe))
        self.duty = self._safe_duty
        self.mode = EcuMode.INIT
        self._last_cmd = -math.inf            # epoch s of the last valid command
        self._inbox: List[can.Message] = []
        self.t0: Optional[float] = None       # epoch s of cycle 0
        self.k = 0

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

    def _drain(self) -> None:
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
    def _latch(self, tau: float) -> None:
        """Apply the commands that arrived before epoch time ``tau``, then the timeout rule."""
        keep = []
        for msg in self._inbox:
            if msg.timestamp > tau:
                keep.append(msg)
                continue
            kind, _, cmd = self._rx.accept(msg, msg.timestamp)
            if kind is not Kind.COMMAND or cmd is None:
                continue
            duty, clamped = self.hw.clamp_duty(cmd.duty)
            if clamped or not math.isfinite(cmd.duty):
                self.counts['duty_out_of_range'] += 1
            self.duty = duty
            self.mode = (EcuMode.CONTROLLED if cmd.mode is CommandMode.CONTROLLED
                         else EcuMode.SAFE_REQUESTED)
            self._last_cmd = msg.timestamp
            self.counts['commands_applied'] += 1
        self._inbox = keep
        if tau - self._last_cmd > self.cfg.command_timeout_s and self.mode not in (
                EcuMode.INIT, EcuMode.SAFE_TIMEOUT):
            self.mode = EcuMode.SAFE_TIMEOUT
            self.counts['command_timeouts'] += 1
        if self.mode in (EcuMode.INIT, EcuMode.SAFE_TIMEOUT):
            self.duty = self._safe_duty

    def start(self, t0: float) -> EcuSample:
        """Begin at epoch time ``t0``: open the bus, send the first sensor frames."""
        self.t0 = t0
        self.k = 0
        self._ensure_bus()
        # Commands queued while the ECU waited to start (e.g. for the road) are history:
        # keep only those still fresh at t0.
        self._drain()
        self._inbox = [m for m in self._inbox if m.timestamp > t0 - self.cfg.command_timeout_s]
        return self._measure_and_send(t0, self.hw.c_e_from_duty(self.duty))

    def run_cycle(self, send: bool = True) -> EcuSample:
        """Integrate the cycle [t0 + k·Ts, t0 + (k+1)·Ts] (epoch s) and send its sensor frames.

        ``send=False`` integrates without sending (catching up after an overrun).
        """
        if self.t0 is None:
            raise RuntimeError('call start() first')
        ts, dt = self.cfg.period_s, self.cfg.latch_s
        t_start = self.t0 + self.k * ts
        self._drain()
        c_sum = 0.0
        for j in range(self._n_latch):
            tau = t_start + j * dt
            self._latch(tau)
            u = self.hw.c_e_from_duty(self.duty)
            c_sum += u
            self.plant.step(u, self.road(tau), self.road(tau + dt))
        self.k += 1
        self.counts['cycles'] += 1
        t_now = self.t0 + self.k * ts
        self._latch(t_now)
        return self._measure_and_send(t_now, c_sum / self._n_latch, send)

    def _measure_and_send(self, t_epoch: float, c_e_mean: float,
                          send: bool = True) -> EcuSample:
        u = self.hw.c_e_from_duty(self.duty)
        w = self.road(t_epoch)
        s = self.plant.sample(u, w)
        v_gen = float(self._v_gen(s.x))
        n, r = self.noise, self._rng
        chassis = Chassis(sprung_accel=s.sprung_accel + n.sprung_accel * r.standard_normal(),
                          deflection=float(s.x[0] - s.x[2]) + n.deflection * r.standard_normal())
        gen = Generator(speed=v_gen / self.params.l + n.speed * r.standard_normal(),
                        current=self.hw.current(u, v_gen) + n.current * r.standard_normal(),
                        voltage=self.hw.back_emf(v_gen) + n.voltage * r.standard_normal())
        rx = self._rx.counts()
        rejected = sum(rx[k] for k in ('wrong_length', 'bad_crc', 'repeated', 'skipped',
                                       'bad_counter'))
        status = Status(mode=self.mode, c_e_applied=u, c_e_mean=c_e_mean,
                        cmd_rejected=rejected % 256,
                        cmd_timeouts=self.counts['command_timeouts'] % 256)
        if send:
            self._send(Kind.STATUS, status)
            self._send(Kind.CHASSIS, chassis)
            self._send(Kind.GENERATOR, gen)
        return EcuSample(t=t_epoch - self.t0, x=s.x, road_height=w, c_e=u, c_e_mean=c_e_mean,
                         sprung_accel=s.sprung_accel, v_gen=v_gen, power_w=s.power_w,
                         harvested_j=s.harvested_j, mode=self.mode)

    def rx_counts(self) -> Dict[str, int]:
        """Return the E2E counters of the received command frames."""
        return self._rx.counts()

    def summary(self) -> Dict[str, int]:
        """Return all counters (ECU and E2E) as one dict."""
        out = dict(self.counts)
        out.update({f'rx_{k}': v for k, v in self.rx_counts().items()})
        return out


def run_realtime(core: EcuSimCore, duration_s: float = 0.0,
                 on_cycle: Optional[Callable[[EcuSample], None]] = None,
                 should_stop: Callable[[], bool] = lambda: False,
                 wait: Optional[Callable[[float], None]] = None,
                 t0: Optional[float] = None) -> int:
    """Run ``core`` against the wall clock until ``duration_s`` (0: forever) or ``should_stop``.

    ``wait(seconds)`` sleeps until the next cycle (default time.sleep; a ROS caller passes
    a function that spins its executor meanwhile).  ``t0`` (epoch s, default now) is the
    time of cycle 0, e.g. an instant of the road's sample grid.  A cycle that starts more
    than one period late is counted as an overrun; the missed cycles are integrated
    without sending, so the plant stays on the wall clock.  Returns the number of cycles
    run.
    """
    wait = wait or time.sleep
    ts = core.cfg.period_s
    sample = core.start(time.time() if t0 is None else t0)
    if on_cycle:
        on_cycle(sample)
    while not should_stop():
        if duration_s > 0 and core.k * ts >= duration_s - 1e-9:
            break
        due = core.t0 + (core.k + 1) * ts
        delay = due - time.time()
        if delay > 0:
            wait(delay)
            if time.time() < due:
                continue                         # woke early (e.g. a ROS callback ran)
        elif -delay > ts:
            core.counts['overruns'] += 1
            for _ in range(int(-delay // ts)):
                core.run_cycle(send=False)
        sample = core.run_cycle()
        if on_cycle:
            on_cycle(sample)
    return core.k
