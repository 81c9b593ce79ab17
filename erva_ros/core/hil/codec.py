"""Encode and decode the ERVA CAN frames with cantools and ``config/erva_ecu.dbc``.

Four messages, 8 bytes each, E2E-protected (:mod:`erva_ros.core.hil.e2e`):

=====  ===================  ======  ===========================================================
ID     name                 sender  content (SI units)
=====  ===================  ======  ===========================================================
0x100  ERVA_CMD             bridge  mode, PWM duty D, c_e the duty stands for (Ns/m), cycle
0x200  ERVA_ECU_STATUS      ECU     ECU mode, applied and cycle-mean c_e (Ns/m), ECU counters
0x201  ERVA_SENS_CHASSIS    ECU     sprung acceleration z̈_s (m/s²), deflection z_s − z_us (m)
0x202  ERVA_SENS_GENERATOR  ECU     rotor speed φ̇ (rad/s), current (A), back-emf (V)
=====  ===================  ======  ===========================================================

The ECU sends its three messages once per cycle, status first (it also has the lowest
ID, so it wins arbitration when the three are queued together): a receiver learns the
damping of the cycle before its measurements.  The E2E Data IDs are the DBC
attribute ``E2E_DataID``.

A command frame names the cycle it is for (CMD_CYCLE = k mod 256, :func:`cycle_of`):
with a command delay d > 0 the ECU applies it at t_k + d on its own clock, not when it
arrives (docs/hil.md, "the real-ECU contract").
"""

from dataclasses import dataclass
import enum
from typing import Any, Dict, Optional, Tuple

import can
import cantools

from erva_ros.core.hil.e2e import E2EChecker, E2ESender, E2EStatus, FRAME_LENGTH
from erva_ros.core.settings.files import shipped_config


class Kind(enum.Enum):
    """The four protected messages."""

    COMMAND = 'ERVA_CMD'
    CHASSIS = 'ERVA_SENS_CHASSIS'
    GENERATOR = 'ERVA_SENS_GENERATOR'
    STATUS = 'ERVA_ECU_STATUS'


class CommandMode(enum.IntEnum):
    """CMD_MODE: why the bridge sends this duty."""

    SAFE_PASSIVE = 0     # acts at once
    CONTROLLED = 1       # the NMPC's command for cycle CMD_CYCLE
    PLANNED = 2          # an earlier command's plan for cycle CMD_CYCLE


class EcuMode(enum.IntEnum):
    """ECU_MODE: what the ECU is applying."""

    INIT = 0
    CONTROLLED = 1
    SAFE_TIMEOUT = 2
    SAFE_REQUESTED = 3
    FAULT = 4


#: CMD_CYCLE counts the cycles modulo this.
CYCLE_MODULO = 256


def cycle_of(stamp_ns: int, ts_ns: int) -> int:
    """Return the cycle number k of a sample instant: t_k = k·Ts (epoch ns), nearest k."""
    return (int(stamp_ns) + int(ts_ns) // 2) // int(ts_ns)


def unwrap_cycle(cycle: int, near: int) -> int:
    """Return the cycle number ≡ ``cycle`` (mod CYCLE_MODULO) nearest to ``near``."""
    half = CYCLE_MODULO // 2
    return near + (int(cycle) - near + half) % CYCLE_MODULO - half


@dataclass
class Command:
    """Damping command frame (bridge → ECU)."""

    duty: float          # PWM duty of the load switch, 0..1
    c_e: float           # Ns/m the duty was computed for
    mode: CommandMode
    cycle: int = 0       # the cycle it is for, k mod CYCLE_MODULO (0: SAFE_PASSIVE)


@dataclass
class Chassis:
    """Chassis sensor frame (ECU → bridge)."""

    sprung_accel: float  # m/s², z̈_s
    deflection: float    # m, z_s − z_us


@dataclass
class Generator:
    """Generator sensor frame (ECU → bridge)."""

    speed: float         # rad/s, φ̇ = v_gen / l
    current: float       # A
    voltage: float       # V, back-emf κ·v_gen


@dataclass
class Status:
    """ECU status / heartbeat frame (ECU → bridge)."""

    mode: EcuMode
    c_e_applied: float   # Ns/m at the end of the cycle
    c_e_mean: float      # Ns/m, time mean over the cycle
    cmd_rejected: int    # modulo 256
    cmd_timeouts: int    # modulo 256


def default_dbc_path() -> str:
    """Return the path of the shipped ``config/erva_ecu.dbc`` (source tree or share dir)."""
    return shipped_config('erva_ecu.dbc', 'pass the DBC path explicitly')


# Signal names of each message's payload, E2E signals excluded (DBC order).
_FIELDS = {
    Kind.COMMAND: {'mode': 'CMD_MODE', 'duty': 'CMD_DUTY', 'c_e': 'CMD_CE',
                   'cycle': 'CMD_CYCLE'},
    Kind.CHASSIS: {'sprung_accel': 'SPRUNG_ACCEL', 'deflection': 'SUSP_DEFLECTION'},
    Kind.GENERATOR: {'speed': 'GEN_SPEED', 'current': 'GEN_CURRENT', 'voltage': 'GEN_VOLTAGE'},
    Kind.STATUS: {'mode': 'ECU_MODE', 'c_e_applied': 'CE_APPLIED', 'c_e_mean': 'CE_MEAN',
                  'cmd_rejected': 'CMD_REJECTED', 'cmd_timeouts': 'CMD_TIMEOUTS'},
}
_TYPES = {Kind.COMMAND: Command, Kind.CHASSIS: Chassis, Kind.GENERATOR: Generator,
          Kind.STATUS: Status}


class EcuCodec:
    """The DBC's messages: frame IDs, Data IDs, encoding with saturation, decoding."""

    def __init__(self, dbc_path: Optional[str] = None):
        self.dbc_path = dbc_path or default_dbc_path()
        try:
            self.db = cantools.database.load_file(self.dbc_path, strict=True)
        except (OSError, cantools.database.UnsupportedDatabaseFormatError) as exc:
            raise ValueError(f'cannot load DBC {self.dbc_path!r}: {exc}') from None
        self.messages = {}
        self.data_ids: Dict[Kind, int] = {}
        for kind in Kind:
            try:
                msg = self.db.get_message_by_name(kind.value)
            except KeyError:
                raise ValueError(f'DBC {self.dbc_path!r} has no message {kind.value}') from None
            if msg.length != FRAME_LENGTH:
                raise ValueError(f'DBC message {kind.value} must be {FRAME_LENGTH} bytes')
            self.messages[kind] = msg
            self.data_ids[kind] = int(msg.dbc.attributes['E2E_DataID'].value)
        self.kind_of_id = {m.frame_id: k for k, m in self.messages.items()}
        self._e2e_names = {k: (next(s.name for s in m.signals if s.name.endswith('_CRC')),
                               next(s.name for s in m.signals if s.name.endswith('_COUNTER')))
                           for k, m in self.messages.items()}
        self._reserved = {k: [s.name for s in m.signals if 'RESERVED' in s.name]
                          for k, m in self.messages.items()}

    def frame_id(self, kind: Kind) -> int:
        return self.messages[kind].frame_id

    def cycle_time_s(self, kind: Kind) -> float:
        """Return the DBC cycle time GenMsgCycleTime of a message in s."""
        return self.messages[kind].cycle_time / 1000.0

    def encode(self, kind: Kind, payload: Any, sender: E2ESender,
               saturate: bool = True) -> can.Message:
        """Encode a payload dataclass into a protected frame (next alive counter + CRC).

        With ``saturate`` each value is limited to its DBC signal range first (an ECU
        saturates a sensor reading rather than wrapping it); ``saturate=False`` encodes
        the raw value as far as the signal's bits allow (used to inject faults).
        """
        msg = self.messages[kind]
        crc_name, counter_name = self._e2e_names[kind]
        values = {crc_name: 0, counter_name: 0}
        values.update(dict.fromkeys(self._reserved[kind], 0))
        for attr, sig_name in _FIELDS[kind].items():
            v = getattr(payload, attr)
            v = int(v) if isinstance(v, enum.IntEnum) else v
            if saturate:
                sig = msg.get_signal_by_name(sig_name)
                v = min(max(v, sig.minimum), sig.maximum)
            values[sig_name] = v
        data = bytearray(msg.encode(values, scaling=True, padding=False, strict=saturate))
        sender.protect(data)
        return can.Message(arbitration_id=msg.frame_id, data=bytes(data),
                           is_extended_id=False, dlc=FRAME_LENGTH)

    def decode(self, kind: Kind, data: bytes) -> Any:
        """Decode the payload of an already checked frame into its dataclass."""
        raw = self.messages[kind].decode(bytes(data), decode_choices=False, scaling=True)
        values = {attr: raw[sig] for attr, sig in _FIELDS[kind].items()}
        if kind is Kind.COMMAND:
            m = int(values['mode'])
            values['mode'] = (CommandMode(m) if m in CommandMode._value2member_map_
                              else CommandMode.SAFE_PASSIVE)
            values['cycle'] = int(values['cycle'])
        elif kind is Kind.STATUS:
            m = int(values['mode'])
            values['mode'] = EcuMode(m) if m in EcuMode._value2member_map_ else EcuMode.FAULT
            values['cmd_rejected'] = int(values['cmd_rejected'])
            values['cmd_timeouts'] = int(values['cmd_timeouts'])
        return _TYPES[kind](**values)

    def sender(self, kind: Kind) -> E2ESender:
        """Return a new E2E alive-counter state for sending ``kind``."""
        return E2ESender(self.data_ids[kind])

    def checker(self, kind: Kind, timeout_s: float, max_delta_counter: int = 1) -> E2EChecker:
        """Return a fresh E2E receiver state for ``kind``."""
        return E2EChecker(self.data_ids[kind], timeout_s, max_delta_counter)


class E2EReceiver:
    """Check and decode received frames of some kinds; count everything else."""

    def __init__(self, codec: EcuCodec, kinds, timeout_s: float, max_delta_counter: int = 1):
        self.codec = codec
        self.checkers = {k: codec.checker(k, timeout_s, max_delta_counter) for k in kinds}
        self.ids = {codec.frame_id(k): k for k in kinds}
        self.unknown_id = 0
        self.remote_or_error = 0

    def reset(self) -> None:
        """Forget all streams (after the bus was re-opened)."""
        for c in self.checkers.values():
            c.reset()

    def accept(self, msg: can.Message, now: float) -> Tuple[Optional[Kind], E2EStatus, Any]:
        """Return (kind, E2E status, decoded payload or None) of one received frame.

        kind is None for frames this receiver does not handle (other IDs, remote and
        error frames), which are only counted.
        """
        if msg.is_error_frame or msg.is_remote_frame:
            self.remote_or_error += 1
            return None, E2EStatus.OK, None
        kind = self.ids.get(msg.arbitration_id)
        if kind is None or msg.is_extended_id:
            self.unknown_id += 1
            return None, E2EStatus.OK, None
        status = self.checkers[kind].check(bytes(msg.data), now)
        if not status.accepted:
            return kind, status, None
        return kind, status, self.codec.decode(kind, msg.data)

    def counts(self) -> Dict[str, int]:
        """Return the summed E2E counters of all kinds plus unknown / remote-error frames."""
        out: Dict[str, int] = {}
        for c in self.checkers.values():
            for key, n in c.counts.items():
                out[key] = out.get(key, 0) + n
        out['unknown_id'] = self.unknown_id
        out['remote_or_error'] = self.remote_or_error
        return out
