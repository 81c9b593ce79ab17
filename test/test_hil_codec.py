"""HIL frames: CRC-8 against the catalogue, E2E profile 1 checks, the DBC, c_e ↔ duty."""

import math

import pytest

from erva_ros.core.hil.codec import (Chassis, Command, CommandMode, E2EReceiver, EcuCodec, EcuMode,
                                     Generator, Kind, Status)
from erva_ros.core.hil.e2e import (COUNTER_MODULO, crc8_sae_j1850, E2EChecker, E2ESender,
                                   E2EStatus, e2e_crc)
from erva_ros.core.model.hardware import GeneratorHardware, validate_hardware
from erva_ros.core.model.params import ParamError


@pytest.fixture(scope='module')
def codec():
    return EcuCodec()


def test_crc8_matches_the_catalogue_and_an_independent_implementation():
    # reveng catalogue: CRC-8/SAE-J1850 check 0x4B; the zero-init variant (profile 1's
    # effective parameters) 0x37.
    assert crc8_sae_j1850(b'123456789', 0xFF, 0xFF) == 0x4B
    assert crc8_sae_j1850(b'123456789') == 0x37
    # crccheck (a cantools dependency), configured as E2E profile 1 computes it.
    crc = pytest.importorskip('crccheck.crc')

    class Profile1(crc.Crc8Base):
        _poly, _initvalue, _xor_output = 0x1D, 0x00, 0x00

    assert crc.Crc8SaeJ1850.calc(b'123456789') == 0x4B
    frame = bytes([0, 0x37, 0x10, 0x27, 0x88, 0x13, 0, 0])
    assert e2e_crc(0x1100, frame) == Profile1.calc(bytes([0x00, 0x11]) + frame[1:])


def test_dbc_messages_ids_and_data_ids(codec):
    assert {k: codec.frame_id(k) for k in Kind} == {
        Kind.COMMAND: 0x100, Kind.STATUS: 0x200, Kind.CHASSIS: 0x201, Kind.GENERATOR: 0x202}
    assert len(set(codec.data_ids.values())) == 4
    assert all(codec.cycle_time_s(k) == 0.02 for k in Kind)


def test_round_trip_of_every_message(codec):
    cases = [(Kind.COMMAND, Command(0.4167, 10000.0, CommandMode.CONTROLLED)),
             (Kind.STATUS, Status(EcuMode.SAFE_TIMEOUT, 10000.0, 7000.0, 3, 1)),
             (Kind.CHASSIS, Chassis(-1.234, 0.01234)),
             (Kind.GENERATOR, Generator(0.5, -1.25, 7.5))]
    for kind, payload in cases:
        rx = E2EReceiver(codec, [kind], timeout_s=0.06)
        msg = codec.encode(kind, payload, codec.sender(kind))
        got_kind, status, got = rx.accept(msg, 0.0)
        assert got_kind is kind and status is E2EStatus.INITIAL
        for name, value in vars(payload).items():
            assert getattr(got, name) == pytest.approx(value, abs=2.0), (kind, name)
    # Resolution of the DBC signals.
    msg = codec.encode(Kind.CHASSIS, Chassis(-1.2344, 0.012344), codec.sender(Kind.CHASSIS))
    got = codec.decode(Kind.CHASSIS, msg.data)
    assert got.sprung_accel == pytest.approx(-1.234, abs=1e-9)
    assert got.deflection == pytest.approx(0.01234, abs=1e-9)


def test_sensor_values_saturate_at_the_signal_range(codec):
    msg = codec.encode(Kind.CHASSIS, Chassis(99.0, -9.0), codec.sender(Kind.CHASSIS))
    got = codec.decode(Kind.CHASSIS, msg.data)
    assert got.sprung_accel == pytest.approx(32.767)
    assert got.deflection == pytest.approx(-0.32768)


def test_e2e_rejects_and_counts_every_fault(codec):
    data_id = codec.data_ids[Kind.CHASSIS]
    tx = E2ESender(data_id)
    chk = E2EChecker(data_id, timeout_s=0.06)

    def frame():
        return codec.encode(Kind.CHASSIS, Chassis(0.1, 0.001), tx).data

    f0 = frame()
    assert chk.check(f0, 0.00) is E2EStatus.INITIAL
    assert chk.check(f0, 0.01) is E2EStatus.REPEATED          # same counter again
    f1 = frame()
    bad = bytearray(f1)
    bad[3] ^= 0x10
    assert chk.check(bytes(bad), 0.02) is E2EStatus.BAD_CRC   # a flipped payload bit
    assert chk.check(f1[:6], 0.02) is E2EStatus.WRONG_LENGTH
    assert chk.check(f1, 0.02) is E2EStatus.OK
    frame()                                                     # lost on the bus
    f3 = frame()
    assert chk.check(f3, 0.04) is E2EStatus.SKIPPED            # dropped ...
    assert chk.check(frame(), 0.06) is E2EStatus.OK            # ... and re-synchronised
    forged = bytearray(frame())
    forged[1] = (forged[1] & 0xF0) | 0x0F
    forged[0] = e2e_crc(data_id, forged)
    assert chk.check(bytes(forged), 0.07) is E2EStatus.BAD_COUNTER
    assert chk.counts == {'accepted': 3, 'resyncs': 1, 'wrong_length': 1, 'bad_crc': 1,
                          'repeated': 1, 'skipped': 1, 'bad_counter': 1}


def test_e2e_data_id_catches_a_frame_under_the_wrong_id(codec):
    # A generator frame relabelled as chassis: its CRC was made with another Data ID.
    msg = codec.encode(Kind.GENERATOR, Generator(0.1, 0.2, 0.3), codec.sender(Kind.GENERATOR))
    chk = E2EChecker(codec.data_ids[Kind.CHASSIS], timeout_s=0.06)
    assert chk.check(msg.data, 0.0) is E2EStatus.BAD_CRC


def test_a_stuck_sender_stays_rejected_and_a_silent_one_restarts(codec):
    data_id = codec.data_ids[Kind.STATUS]
    tx = E2ESender(data_id)
    chk = E2EChecker(data_id, timeout_s=0.06)
    f = codec.encode(Kind.STATUS, Status(EcuMode.CONTROLLED, 1.0, 1.0, 0, 0), tx).data
    assert chk.check(f, 0.0).accepted
    # Repeating the same frame for a long time never becomes "a new stream".
    assert all(chk.check(f, 0.02 * k) is E2EStatus.REPEATED for k in range(1, 20))
    # After a real silence longer than the timeout any counter starts a new stream.
    tx.counter = 9
    g = codec.encode(Kind.STATUS, Status(EcuMode.CONTROLLED, 1.0, 1.0, 0, 0), tx).data
    assert chk.check(g, 0.38 + 0.07) is E2EStatus.INITIAL
    assert tx.counter == 10 and COUNTER_MODULO == 15


def test_c_e_duty_resistance_mapping():
    hw = GeneratorHardware()          # kappa 120 N/A, R_int 0.4, R_sw 0.2, duty <= 0.95
    assert hw.c_e_full == pytest.approx(120 ** 2 / 0.6)
    assert hw.c_e_range == pytest.approx((0.0, 0.95 * 24000.0))
    c_e0 = 10000.0
    duty = hw.duty_from_c_e(c_e0)
    assert duty == pytest.approx(10000.0 / 24000.0)
    assert hw.c_e_from_duty(duty) == pytest.approx(c_e0)
    # Paper: c_e = kappa^2 / R; R = (R_int + R_sw) / D.
    r = hw.resistance_from_c_e(c_e0)
    assert hw.kappa_n_per_a ** 2 / r == pytest.approx(c_e0)
    assert r == pytest.approx((0.4 + 0.2) / duty)
    assert hw.load_resistance_from_c_e(c_e0) == pytest.approx(r - 0.4)
    assert math.isinf(hw.resistance_from_c_e(0.0))
    # Electrical power back-emf x current equals the paper's P = c_e v^2 (eq. (12)).
    v = 0.03
    assert hw.back_emf(v) * hw.current(c_e0, v) == pytest.approx(c_e0 * v * v)
    assert hw.force_from_current(hw.current(c_e0, v)) == pytest.approx(c_e0 * v)
    assert hw.clamp_c_e(1e5) == (pytest.approx(22800.0), True)
    assert hw.clamp_c_e(-5.0) == (0.0, True)
    assert hw.clamp_c_e(5000.0) == (5000.0, False)


def test_hardware_validation_is_one_line():
    with pytest.raises(ParamError, match="'kappa_n_per_a' = -1"):
        validate_hardware({'kappa_n_per_a': -1})
    with pytest.raises(ParamError, match='duty_min = 0.9 is above duty_max = 0.5'):
        validate_hardware({'duty_min': 0.9, 'duty_max': 0.5})
    with pytest.raises(ParamError, match='needs a resistance'):
        validate_hardware({'r_internal_ohm': 0.0, 'r_switch_ohm': 0.0})


def test_bad_dbc_path_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match='cannot load DBC'):
        EcuCodec(str(tmp_path / 'missing.dbc'))
    other = tmp_path / 'other.dbc'
    other.write_text('VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: A\n\n'
                     'BO_ 1 OTHER: 8 A\n SG_ X : 0|8@1+ (1,0) [0|255] "" A\n')
    with pytest.raises(ValueError, match='has no message ERVA_CMD'):
        EcuCodec(str(other))
