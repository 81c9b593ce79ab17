"""ISO 2631-1 frequency weighting and the weighted RMS acceleration a_w (core/comfort.py)."""

import math

import numpy as np
import pytest

from erva_ros.core.comfort import (bilinear_error_db, ComfortError, point_vertical_acceleration,
                                   point_weighted_rms, THIRD_OCTAVE_NOMINAL_HZ, weight,
                                   weighted_rms, WEIGHTINGS, weighting_of)

# ISO 2631-1:1997, Table 3 (principal frequency weightings in one-third octaves), factors
# × 1000 at the nominal band centres 0.1-400 Hz: W_k and W_d.  Transcribed from public
# copies of the table (docs/model.md says which); not read off the standard itself.
TABLE_WK = (31.2, 48.6, 79.0, 121, 182, 263, 352, 418, 459, 477, 482, 484, 494, 531, 631, 804,
            967, 1039, 1054, 1036, 988, 902, 768, 636, 513, 405, 314, 246, 186, 132, 88.7, 54.0,
            28.5, 15.2, 7.90, 3.98, 1.95)
TABLE_WD = (62.4, 97.3, 158, 243, 365, 530, 713, 853, 944, 992, 1011, 1008, 968, 890, 776, 642,
            512, 409, 323, 253, 212, 161, 125, 100, 80.0, 63.2, 49.4, 38.8, 29.5, 21.1, 14.1,
            8.63, 4.55, 2.43, 1.26, 0.64, 0.31)


def last_digit(value):
    """Return one unit of the last digit the table prints ``value`` with (3 significant)."""
    digits = 2 if value < 1 else 3          # 0.64, 0.31: two significant digits
    return 10.0 ** (math.floor(math.log10(value)) - digits + 1)


@pytest.mark.parametrize('name, table', [('k', TABLE_WK), ('d', TABLE_WD)])
def test_weightings_reproduce_the_standards_table(name, table):
    # The analog definition at the nominal band centres reproduces the table to its
    # printed precision: within one unit of its last digit (W_k: 0.7 unit, 0.28 %, 0.024 dB
    # at most; W_d: 0.61 %, 0.053 dB where it prints two digits) -- except W_d at 10 Hz,
    # where the table's 212 is 0.43 dB above the definition's 201.7 and its neighbours
    # (253 at 8 Hz, 161 at 12.5 Hz) agree with the definition.  That entry is reported as
    # a table anomaly (docs/model.md), not absorbed: it is asserted as it is.
    got = 1000 * np.abs(WEIGHTINGS[name].response(THIRD_OCTAVE_NOMINAL_HZ))
    assert len(table) == len(THIRD_OCTAVE_NOMINAL_HZ)
    for f, g, want in zip(THIRD_OCTAVE_NOMINAL_HZ, got, table):
        if name == 'd' and f == 10.0:
            assert g == pytest.approx(201.706, abs=1e-3)
            assert 20 * math.log10(want / g) == pytest.approx(0.43, abs=0.01)
            continue
        assert abs(g - want) <= last_digit(want) + 1e-9, (f, g, want)
        assert abs(20 * math.log10(g / want)) < 0.06, (f, g, want)


def test_the_table_is_at_the_nominal_not_the_exact_band_centres():
    # At the exact centres 10^(b/10) W_k is up to 2.5 % (0.22 dB) off the table, nine times
    # its worst deviation at the nominal centres (0.28 %): the standard evaluated its
    # weighting at the nominal frequencies.
    exact = 10.0 ** (np.arange(-10, 27) / 10)
    got = 1000 * np.abs(WEIGHTINGS['k'].response(exact))
    assert np.max(np.abs(got / np.array(TABLE_WK) - 1)) > 0.02


def test_weighting_shapes():
    k, d = WEIGHTINGS['k'], WEIGHTINGS['d']
    assert k.response(0.0) == 0                     # the band-limiting high-pass
    assert abs(k.response(1e4)) < 1e-3              # the low-pass at 100 Hz
    f = np.logspace(-1, 2, 400)
    assert f[np.argmax(np.abs(k.response(f)))] == pytest.approx(6.3, rel=0.15)
    assert f[np.argmax(np.abs(d.response(f)))] == pytest.approx(1.0, rel=0.15)
    assert weighting_of('W_k') is k and weighting_of('Wd') is d
    with pytest.raises(ComfortError, match='weighting'):
        weighting_of('b')


@pytest.mark.parametrize('fs', [50.0, 1000.0])
def test_a_sine_on_a_dft_bin_is_weighted_exactly(fs):
    # Frequency-domain weighting: at every DFT frequency the weighted signal is the analog
    # filter's steady state, |H|·A·sin(2πft + φ + arg H), to rounding -- also at 50 Hz
    # sampling, where a bilinear filter is 0.47 dB off at 10 Hz (bilinear_error_db).
    t = np.arange(int(10 * fs)) / fs                # 10 s: bins 0.1 Hz apart
    for name in 'kd':
        w = WEIGHTINGS[name]
        for f in (0.5, 1.0, 1.7, 4.0, 5.8, 10.0, 16.0, 24.0):
            if f >= fs / 2:
                continue
            h = w.response(f)
            a = 0.8 * np.sin(2 * math.pi * f * t + 0.3)
            want = 0.8 * abs(h) * np.sin(2 * math.pi * f * t + 0.3 + np.angle(h))
            np.testing.assert_allclose(weight(a, fs, name), want, rtol=0, atol=1e-12)
            assert weighted_rms(a, fs, name) == pytest.approx(0.8 * abs(h) / math.sqrt(2),
                                                              rel=1e-12)
    assert abs(bilinear_error_db(10.0, 50.0, 'k')) > 0.4


def test_off_bin_leakage_of_a_long_record_is_small():
    # A sine that does not fit the record leaks into neighbouring bins, weighted a little
    # differently.  Worst case over frequency and phase, 1-20 Hz, against the analog steady
    # state on the same samples: 0.36 % for 60 s at 50 Hz (docs/model.md: 2.2 % for 10 s).
    fs, seconds = 50.0, 60.0
    t = np.arange(int(seconds * fs)) / fs
    w = WEIGHTINGS['k']
    worst = 0.0
    for f in np.arange(1.0, 20.0, 0.5 / seconds * 37) + 0.25 / seconds:
        h = w.response(f)
        for phase in (0.0, 0.7, 1.4, 2.1):
            a = np.sin(2 * math.pi * f * t + phase)
            ideal = abs(h) * np.sin(2 * math.pi * f * t + phase + np.angle(h))
            worst = max(worst, abs(weighted_rms(a, fs) / np.sqrt(np.mean(ideal ** 2)) - 1))
    assert 1e-4 < worst < 0.005


def test_seat_acceleration_from_heave_pitch_and_roll():
    fs = 100.0
    t = np.arange(2000) / fs
    rng = np.random.default_rng(4)
    heave, pitch, roll = rng.standard_normal((3, t.size))
    x, y = 0.4, 0.37                               # driver's seat: ahead of and left of the CG
    z = point_vertical_acceleration(heave, pitch, roll, x, y)
    np.testing.assert_array_equal(z, heave - x * pitch + y * roll)   # ISO 8855: nose down
    # a_w is linear in the motion: pure pitch at x is |x| × the pitch's weighted RMS
    zero = np.zeros_like(t)
    assert point_weighted_rms(zero, pitch, zero, fs, x, y) == pytest.approx(
        x * weighted_rms(pitch, fs), rel=1e-12)
    assert point_weighted_rms(heave, zero, zero, fs, x, y) == pytest.approx(
        weighted_rms(heave, fs), rel=1e-12)
    # heave and nose-up pitch in phase at 2 Hz (on a bin): amplitudes add at the seat
    # ahead of the CG, cancel behind it at -x
    s = np.sin(2 * math.pi * 2.0 * t)
    gain = abs(WEIGHTINGS['k'].response(2.0)) / math.sqrt(2)
    assert point_weighted_rms(s, -s, zero, fs, x, 0.0) == pytest.approx((1 + x) * gain, rel=1e-12)
    assert point_weighted_rms(s, -s / x, zero, fs, -x, 0.0) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize('args, match', [
    (([0.0, float('nan'), 1.0], 50.0), 'non-finite'),
    (([1.0], 50.0), 'at least 2'),
    ((np.zeros((3, 3)), 50.0), '1-D'),
    (([0.0, 1.0, 2.0], 0.0), 'fs'),
    (([0.0, 1.0, 2.0], 'fast'), 'fs'),
])
def test_bad_inputs_give_one_line_errors(args, match):
    with pytest.raises(ComfortError, match=match) as err:
        weighted_rms(*args)
    assert '\n' not in str(err.value)
    with pytest.raises(ComfortError, match='one length'):
        point_vertical_acceleration([0.0, 1.0], [0.0], [0.0, 1.0], 0.4, 0.3)
    with pytest.raises(ComfortError, match='x_m'):
        point_vertical_acceleration([0.0, 1.0], [0.0, 1.0], [0.0, 1.0], float('inf'), 0.3)
