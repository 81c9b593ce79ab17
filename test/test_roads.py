"""Roads (paper, ISO 8608, bump, sine, recorded) and the preview error model."""

import math

import numpy as np
import pytest

from erva_ros.core.road.preview import PreviewErrorModel
from erva_ros.core.road.profiles import butter2_lowpass, lfilter2, make_road, ROAD_KINDS, RoadError


def test_road_kinds_exported():
    assert ROAD_KINDS == ('paper', 'iso8608', 'bump', 'sine', 'recorded')


def test_paper_road_is_seeded_and_reproducible():
    a = make_road('paper', 4.0, seed=3)
    b = make_road('paper', 4.0, seed=3)
    c = make_road('paper', 4.0, seed=4)
    t = np.linspace(0, 4, 777)
    np.testing.assert_array_equal(a.height(t), b.height(t))
    assert np.max(np.abs(a.height(t) - c.height(t))) > 1e-4
    assert a.height(0.0) == 0.0     # starts at rest, like the quarter car
    # A longer run with the same seed extends the same road.
    long = make_road('paper', 8.0, seed=3)
    np.testing.assert_allclose(long.height(t), a.height(t), atol=1e-15)


def test_paper_road_snr_is_7_db_and_noise_is_low_pass():
    road = make_road('paper', 200.0, seed=1, margin_s=0.0)
    t = road.times
    sine = 1e-3 * np.sin(2 * math.pi * 1.7 * t)
    noise = road.heights - sine
    snr = 10 * math.log10(np.mean(sine ** 2) / np.mean(noise[1000:] ** 2))
    assert snr == pytest.approx(7.0, abs=0.3)
    spec = np.abs(np.fft.rfft(noise)) ** 2
    f = np.fft.rfftfreq(noise.size, d=t[1] - t[0])
    below = spec[(f > 1) & (f < 5)].mean()
    above = spec[(f > 40) & (f < 100)].mean()
    assert above < 1e-3 * below   # 2nd-order roll-off beyond the 10 Hz cut-off


def test_butterworth_gain_at_dc_and_cutoff():
    b, a = butter2_lowpass(10.0, 1000.0)
    y = lfilter2(b, a, np.ones(5000))
    assert y[-1] == pytest.approx(1.0, rel=1e-9)
    t = np.arange(20000) / 1000.0
    y = lfilter2(b, a, np.sin(2 * math.pi * 10.0 * t))
    assert np.max(np.abs(y[10000:])) == pytest.approx(1 / math.sqrt(2), rel=0.01)


def test_height_is_vectorised_linear_interpolation_and_preview():
    road = make_road('paper', 2.0, seed=0)
    t = 0.0123
    i = int(t / 1e-3)
    expect = road.heights[i] + (road.heights[i + 1] - road.heights[i]) * (t / 1e-3 - i)
    assert road.height(t) == pytest.approx(expect, rel=1e-12)
    p = road.preview(0.5, 10, 0.02)
    assert p.shape == (11,)
    np.testing.assert_allclose(p, road.height(0.5 + 0.02 * np.arange(11)))
    assert road.distance(2.0) == pytest.approx(40.0)


def test_paper_preview_without_noise_sees_only_the_sine():
    road = make_road('paper', 2.0, seed=0, preview_sees_noise=False)
    p = road.preview(0.3, 5, 0.02)
    assert p[0] == pytest.approx(road.height(0.3))
    t = 0.3 + 0.02 * np.arange(1, 6)
    np.testing.assert_allclose(p[1:], 1e-3 * np.sin(2 * math.pi * 1.7 * t), atol=1e-9)


def test_iso8608_classes_scale_by_factor_two_per_class():
    rms = {}
    for cls in 'ACE':
        road = make_road('iso8608', 60.0, seed=2, road_class=cls, speed_mps=20.0)
        rms[cls] = np.std(road.heights)
    # G_d(n0) grows 4x per class, the RMS height 2x.
    assert rms['C'] / rms['A'] == pytest.approx(4.0, rel=1e-9)
    assert rms['E'] / rms['C'] == pytest.approx(4.0, rel=1e-9)
    assert 2e-3 < rms['C'] < 2e-2
    again = make_road('iso8608', 60.0, seed=2, road_class='C')
    np.testing.assert_array_equal(again.heights,
                                  make_road('iso8608', 60.0, seed=2, road_class='C').heights)


def test_bump_and_sine_and_recorded():
    bump = make_road('bump', 3.0, height_m=0.02, length_m=1.0, start_s=1.0, speed_mps=10.0)
    assert bump.height(0.5) == 0.0 and bump.height(1.2) == 0.0
    assert bump.height(1.05) == pytest.approx(0.02, rel=1e-6)
    sine = make_road('sine', 2.0, amplitude_m=2e-3, freq_hz=2.0)
    assert sine.height(0.125) == pytest.approx(2e-3, rel=1e-9)
    rec = make_road('recorded', 1.0, times=[10.0, 10.5, 11.0], heights=[0.0, 0.01, 0.0])
    assert rec.height(0.25) == pytest.approx(0.005)
    assert rec.height(0.75) == pytest.approx(0.005)


@pytest.mark.parametrize('kind,opts,match', [
    ('gravel', {}, 'unknown road'),
    ('paper', {'colour': 'red'}, 'does not take'),
    ('iso8608', {'road_class': 'F'}, 'road_class'),
    ('recorded', {'times': [0, 0], 'heights': [0, 1]}, 'strictly increasing'),
    ('recorded', {'times': [0, 1], 'heights': [0]}, 'equal length'),
    ('sine', {'freq_hz': -1}, 'freq_hz'),
])
def test_bad_road_options_give_one_line_errors(kind, opts, match):
    with pytest.raises(RoadError, match=match) as err:
        make_road(kind, 2.0, **opts)
    assert '\n' not in str(err.value)


def test_preview_error_model_is_deterministic_noise_and_delay():
    p = np.sin(np.linspace(0, 3, 11))
    model = PreviewErrorModel(snr_db=10.0, seed=5, ts=0.02)
    a, b = model.apply(p, 1.0), model.apply(p, 1.0)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(model.apply(p, 1.02), a)
    assert a[0] == p[0]                      # the height measured now is kept
    big = PreviewErrorModel(snr_db=0.0, seed=1, ts=0.02)
    errs = np.concatenate([big.apply(p, 0.02 * k)[1:] - p[1:] for k in range(400)])
    assert np.std(errs) == pytest.approx(np.sqrt(np.mean(p ** 2)), rel=0.1)
    late = PreviewErrorModel(delay_s=0.04, ts=0.02).apply(p, 0.0)
    np.testing.assert_allclose(late[2:], p[:-2])
    assert PreviewErrorModel().is_perfect
    with pytest.raises(ValueError):
        PreviewErrorModel(delay_s=-1.0)


# -- recorded roads from CSV files ---------------------------------------------------------
def test_road_csv_dialects_give_the_same_rows(tmp_path):
    from erva_ros.core.road.profiles import read_road_csv
    want = np.array([[0.0, 0.0], [0.5, 0.001], [1.0, -0.002]])
    dialects = {
        'plain': '0,0\n0.5,0.001\n1.0,-0.002\n',
        'header': '# my road\ntime_s, height_m\n\n0, 0\n0.5, 0.001   # the crest\n1.0, -0.002\n',
        'semicolons': 'time_s;height_m\n0;0\n0.5;0.001\n1.0;-0.002\n',
        'crlf': 'time_s, height_m\r\n0, 0\r\n0.5, 0.001\r\n1.0, -0.002\r\n',
        'columns': 't, h, note\n0, 0, a\n0.5, 0.001, b\n1.0, -0.002, c\n',
    }
    for name, text in dialects.items():
        path = tmp_path / f'{name}.csv'
        path.write_bytes(text.encode())
        np.testing.assert_array_equal(read_road_csv(str(path)), want, err_msg=name)


@pytest.mark.parametrize('text, match', [
    ('t, h\n0, 0\n1, x\n', r"bad.csv:3: expected \"time_s, height_m\", got '1, x'$"),
    ('t, h\n0, 0\n1, inf\n', r"bad.csv:3: '1, inf' is not a finite \"time_s, height_m\" row$"),
    ('t; h\n0; 0\n1\n', r'bad.csv:3: expected "time_s, height_m", got \'1\'$'),
    ('t, h\n0, 0\n', r'needs at least two "time_s, height_m" rows$'),
    ('only text\n', r'needs at least two "time_s, height_m" rows$'),
])
def test_a_bad_road_csv_names_its_line(tmp_path, text, match):
    from erva_ros.core.road.profiles import read_road_csv
    path = tmp_path / 'bad.csv'
    path.write_text(text)
    with pytest.raises(RoadError, match=match):
        read_road_csv(str(path))


@pytest.mark.slow
def test_ten_million_rows_are_read_whole_in_bounded_memory(tmp_path):
    # Read row by row, a file like this took 238 s and 2.9 GB (then `erva run`'s road node
    # timed out; the old reader's peak here: 2.8 GB).  Now numpy parses it in one pass; the
    # peak is the array (160 MB) and the interpreter, checked in a fresh process.
    import subprocess
    import sys
    n = 10_000_000
    path = tmp_path / 'long.csv'
    with open(path, 'w') as fh:
        fh.write('time_s, height_m\n')
        for start in range(0, n, 1_000_000):
            fh.write(''.join(f'{i / 1000},{(i % 7) * 1e-4}\n'
                             for i in range(start, start + 1_000_000)))
    code = ('import resource, sys\n'
            'from erva_ros.core.road.profiles import read_road_csv\n'
            'rows = read_road_csv(sys.argv[1])\n'
            'print(rows.shape[0], rows[-1, 0], rows[:, 1].sum(), '
            'resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)\n')
    out = subprocess.run([sys.executable, '-c', code, str(path)], capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    rows, last, total, peak_kb = out.stdout.split()
    assert int(rows) == n and float(last) == (n - 1) / 1000
    q, r = divmod(n, 7)
    assert float(total) == pytest.approx(1e-4 * (21 * q + r * (r - 1) // 2), rel=1e-9)
    assert int(peak_kb) < 1024 * 1024, peak_kb          # < 1 GiB (the text is 110 MB)
