"""Frequency response (paper Fig. 4): simulated peaks agree with the linearised model."""

import json
import os

import numpy as np
import pytest

from erva_ros.core.studies import fr
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import paper_params

P = paper_params()
M = make_model(P)


@pytest.mark.parametrize('kind,band', [('erva', (1.4, 2.0)), ('erva', (5.4, 6.3)),
                                       ('benchmark', (3.8, 4.8))])
def test_nonlinear_peaks_agree_with_linearisation_at_1mm(kind, band):
    m = make_model(P, kind)
    freqs = np.round(np.arange(band[0], band[1] + 1e-9, 0.05), 3)
    curve = fr.sweep(m, freqs, 1e-3, P.c_e0)
    lin = fr.linear_response(m, freqs, 1e-3, P.c_e0)
    for sim, ana in [(curve.accel, lin['accel_amp']), (curve.power, lin['power_mean_w'])]:
        peaks_sim, peaks_lin = fr.find_peaks(freqs, sim), fr.find_peaks(freqs, ana)
        assert len(peaks_sim) == len(peaks_lin) == 1
        assert peaks_sim[0] == pytest.approx(peaks_lin[0], abs=0.02)
        np.testing.assert_allclose(sim, ana, rtol=0.01)


def test_nonlinearity_shows_at_large_amplitude():
    # A test of the comparison above: the inertia nonlinearity (ε·r_1 = ε·φ²) is weak
    # at road amplitudes of millimetres but detunes the first resonance at 10 cm.
    m = M
    freqs = np.array([1.7])
    big = fr.sweep(m, freqs, 0.1, P.c_e0)
    lin = fr.linear_response(m, freqs, 0.1, P.c_e0)
    assert abs(big.accel[0] - lin['accel_amp'][0]) / lin['accel_amp'][0] > 0.05


def test_find_peaks_refines_and_ignores_ripple():
    f = np.arange(1, 3.01, 0.1)
    y = np.exp(-((f - 2.03) / 0.3) ** 2)
    y[2] += 1e-4 * (-1) ** 2  # tiny ripple far below min_rel
    assert fr.find_peaks(f, y) == [pytest.approx(2.03, abs=0.01)]
    assert fr.find_peaks(f, np.linspace(0, 1, f.size)) == []


def test_erva_fr_cli_json_csv_png(tmp_path, erva):
    out = tmp_path / 'fr'
    proc = erva('fr', '--f-min', 1.5, '--f-max', 2.0, '--f-step', 0.1, '--json',
                '--out', out, check=True)
    res = json.loads(proc.stdout)
    assert set(res) >= {'erva', 'benchmark', 'amplitude_m'}
    assert res['amplitude_m'] == 1e-3
    assert res['erva']['accel_peaks_hz'] == [pytest.approx(1.70, abs=0.03)]
    for key in ('accel_peaks_hz', 'power_peaks_hz'):
        assert isinstance(res['benchmark'][key], list)
    rows = (out / 'fr.csv').read_text().splitlines()
    assert rows[0].startswith('model,freq_hz,accel_amp_m_s2')
    assert len(rows) == 1 + 2 * 6
    for png in ('fr.png', 'fr_bode.png'):         # linear as paper Fig. 4, and Bode
        assert (out / png).read_bytes()[:4] == b'\x89PNG'
        assert os.path.getsize(out / png) > 10_000
        assert str(out / png) in res['files']


def test_bode_magnitudes_are_per_unit_road_amplitude_in_db():
    """|z̈_s|/|w| in dB (20·log10) and P/|w|² in dB (10·log10).

    A 2 mm tone giving 2 m/s² and 4e-6 W is a gain of 1000 s⁻² (60 dB) and 1 W/m² (0 dB).
    """
    tones = [fr.ToneResult(1.0, 2.0, 1.4, 4e-6, 2.0), fr.ToneResult(2.0, 0.2, 0.14, 4e-8, 2.0)]
    curve = fr.FRCurve('erva', 1e4, 2e-3, tones)
    assert curve.gain_db == pytest.approx([60.0, 40.0])
    assert curve.power_db == pytest.approx([0.0, -20.0])


@pytest.mark.parametrize('args,needle', [
    (['--f-min', '5', '--f-max', '2'], '--f-max 2.0 is below --f-min 5.0'),
    (['--models', 'erva,quarter'], "unknown model 'quarter'"),
    (['--amplitude', '-1'], "'-1' must be a positive, finite number"),
])
def test_erva_fr_cli_errors(erva, args, needle):
    proc = erva('fr', *args)
    assert proc.returncode == 2
    assert needle in proc.stderr
    assert 'Traceback' not in proc.stderr
