"""A car's two-track road: coherence, spectra, the rear delay, seeds (core/road/two_track.py)."""

import math

import numpy as np
import pytest

from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.road.profiles import make_road, RoadError
from erva_ros.core.road.two_track import (bessel_k1, CORNERS, delayed_road, isotropic_coherency,
                                          make_two_track_road)

TRACK, WHEELBASE = 1.5, 2.7

# A long drive for the statistics: 1000 s at 40 m/s = 40 km of each track.  Welch: the
# profile taken every 0.08 m (it has no content above 2.83 cycle/m, below Nyquist 6.25),
# K = 488 disjoint Hann segments of 1024 samples (82 m, bins 0.0122 cycle/m apart).
SPEED, LONG_S, STEP, SEG = 40.0, 1000.0, 2, 1024


@pytest.fixture(scope='module')
def long_road():
    return make_two_track_road(LONG_S, track_m=TRACK, wheelbase_m=WHEELBASE, seed=11,
                               road_class='C', right_class='D', speed_mps=SPEED, margin_s=0.0)


def welch(left, right, dx):
    """Return n, the one-sided PSDs (m³) and the cross-spectrum of two profiles, and K."""
    k = left.size // SEG
    win = np.hanning(SEG)

    def spectra(x):
        rows = x[:k * SEG].reshape(k, SEG)
        return np.fft.rfft((rows - rows.mean(axis=1, keepdims=True)) * win, axis=1)
    xl, xr = spectra(left), spectra(right)
    scale = 2 * dx / np.sum(win ** 2)
    return (np.fft.rfftfreq(SEG, dx), scale * np.mean(np.abs(xl) ** 2, axis=0),
            scale * np.mean(np.abs(xr) ** 2, axis=0), scale * np.mean(xl * np.conj(xr), axis=0),
            k)


@pytest.fixture(scope='module')
def spectra(long_road):
    dx = SPEED * 1e-3 * STEP
    return welch(long_road.fl.heights[::STEP], long_road.fr.heights[::STEP], dx)


def octave_bands(n, lo=0.05, hi=2.5):
    """Yield index arrays of the Welch bins in octave bands from ``lo`` to ``hi`` cycle/m."""
    edge = lo
    while edge < hi:
        idx = np.flatnonzero((n >= edge) & (n < min(2 * edge, hi)))
        if idx.size:
            yield idx
        edge *= 2


def test_bessel_k1_matches_tabulated_values():
    # Abramowitz & Stegun, Table 9.8 (K1 at x = 0.1, 0.5, 1, 2, 5), to 10 significant digits
    x = np.array([0.1, 0.5, 1.0, 2.0, 5.0])
    want = np.array([9.853844781, 1.656441120, 0.6019072302, 0.1398658818, 0.004044613445])
    np.testing.assert_allclose(bessel_k1(x), want, rtol=1e-9)
    assert bessel_k1(1e-4) == pytest.approx(1e4 + 5e-5 * (math.log(5e-5) + 0.5772156649 - 0.5),
                                            rel=1e-12)      # the small-x series
    with pytest.raises(ValueError):
        bessel_k1([1.0, 0.0])


def test_isotropic_coherency_is_the_normalised_cross_spectrum_of_an_isotropic_surface():
    # For the ISO 8608 spectrum G(n) ∝ n^-2 an isotropic surface has the 2-D spectrum
    # ∝ (n² + m²)^(-3/2); two tracks B apart: G_LR(n)/G(n) = ∫cos(2πmB)(n²+m²)^(-3/2) dm
    # / ∫(n²+m²)^(-3/2) dm.  Numerically (m = n·sinh u, Simpson, truncated where the rest
    # is below 1e-9) against the closed form 2πnB·K1(2πnB).
    for n in (0.02, 0.1, 0.3):
        u = np.linspace(0.0, 12.0, 2_000_001)
        m = n * np.sinh(u)
        f = np.cos(2 * math.pi * m * TRACK) / np.cosh(u) ** 2   # (n²+m²)^(-3/2)·dm/du·n²
        h = u[1] - u[0]
        simpson = h / 3 * (f[0] + f[-1] + 4 * f[1:-1:2].sum() + 2 * f[2:-1:2].sum())
        assert isotropic_coherency(n, TRACK) == pytest.approx(simpson, abs=2e-7), n
    assert isotropic_coherency(0.0, TRACK) == 1.0
    rho = isotropic_coherency(np.linspace(0, 3, 301), TRACK)
    assert np.all(np.diff(rho) < 0) and rho[-1] < 1e-10      # 1 for long waves, then 0


def test_coherence_of_long_profiles_matches_the_model(spectra):
    # Welch's magnitude-squared coherence γ̂² of K disjoint segments of Gaussian-like
    # profiles has mean γ² + (1 − γ²)²/K and variance 2γ²(1 − γ²)²/K + (1 − γ²)²/K²
    # (Carter, Knapp & Nuttall 1973, to first order in 1/K; the second term is the
    # estimate's spread where γ = 0).  Averaged over an octave band of N bins (Hann's
    # neighbouring bins correlate: counted as N/2 independent ones) the estimate must lie
    # within 5 standard deviations of the model: a correct generator misses that with a
    # probability below 1e-5 over the six bands, and the test is seeded, so it never flakes.
    n, gl, gr, glr, k = spectra
    msc = np.abs(glr) ** 2 / (gl * gr)

    def misses(track_m):
        g2 = isotropic_coherency(n, track_m) ** 2
        out = []
        for idx in octave_bands(n):
            mean = np.mean(g2[idx] + (1 - g2[idx]) ** 2 / k)
            var = 2 * g2[idx] * (1 - g2[idx]) ** 2 / k + (1 - g2[idx]) ** 2 / k ** 2
            sd = math.sqrt(np.sum(var) * 2) / idx.size
            out.append((n[idx[0]], np.mean(msc[idx]), mean, abs(np.mean(msc[idx]) - mean) / sd))
        return out
    for band in misses(TRACK):
        assert band[3] < 5.0, band
    # the test can fail: the same estimate rejects a 30 % wider track and independent tracks
    assert max(b[3] for b in misses(1.3 * TRACK)) > 5.0
    assert max(b[3] for b in misses(1e3)) > 5.0             # ρ ≈ 0 from 0.05 cycle/m on
    # the cross-spectrum is real and positive (isotropy): the co-spectrum ratio tracks ρ
    low = (n >= 0.05) & (n <= 0.2)
    co = glr.real[low] / np.sqrt(gl[low] * gr[low])
    np.testing.assert_allclose(co, isotropic_coherency(n[low], TRACK), atol=0.06)


def test_each_track_has_the_psd_of_its_class(spectra):
    # G_d(n) = G_d(n0)·(n/n0)^-2, G_d(n0) = 256e-6 m³ (C, left) and 1024e-6 m³ (D, right).
    # A Welch PSD of K segments has a relative standard deviation 1/√K per bin; averaged
    # over an octave band of N bins (N/2 independent) the ratio to G_d must be within 5 of
    # them of 1.
    n, gl, gr, _, k = spectra
    for psd, gd_n0 in ((gl, 256e-6), (gr, 1024e-6)):
        for idx in octave_bands(n):
            ratio = np.mean(psd[idx] / (gd_n0 * (n[idx] / 0.1) ** -2))
            sd = 1 / math.sqrt(k * idx.size / 2)
            assert abs(ratio - 1) < 5 * sd, (n[idx[0]], ratio, sd)


def test_left_track_is_the_single_track_road_of_the_seed(long_road):
    single = make_road('iso8608', LONG_S, seed=11, road_class='C', speed_mps=SPEED,
                       margin_s=0.0)
    np.testing.assert_array_equal(long_road.fl.times, single.times)
    np.testing.assert_array_equal(long_road.fl.heights, single.heights)
    assert long_road.fr.heights[0] == 0.0 and long_road.rl.height(0.0) == 0.0


def test_rear_wheels_meet_the_front_road_a_wheelbase_later():
    car = make_two_track_road(6.0, track_m=TRACK, wheelbase_m=WHEELBASE, seed=3, speed_mps=17.0)
    tau = WHEELBASE / 17.0
    assert car.rear_delay_s == tau
    for front, rear in ((car.fl, car.rl), (car.fr, car.rr)):
        # the nodes: the front's heights, bit for bit, at the front's times + τ
        np.testing.assert_array_equal(rear.heights[1:], front.heights)
        np.testing.assert_array_equal(rear.times[1:], front.times + tau)
        # any instant: the front's height τ earlier, to rounding (linear interpolation both)
        t = np.linspace(tau, 6.0, 4001)
        np.testing.assert_allclose(rear.height(t), front.height(t - tau), rtol=0, atol=1e-15)
        assert np.max(np.abs(front.height(t))) > 1e-3           # not trivially flat
        # before the rear axle reaches the start: the flat approach
        assert np.all(rear.height(np.linspace(0.0, tau, 50)) == 0.0)
        p = rear.preview(1.3, 10, 0.02)
        np.testing.assert_allclose(p, front.height(1.3 - tau + 0.02 * np.arange(11)),
                                   rtol=0, atol=1e-15)
    assert list(car.corners()) == list(CORNERS)
    assert car.corner('RL') is car.rl


def test_same_seed_same_roads_and_other_seeds_differ():
    a = make_two_track_road(8.0, track_m=TRACK, wheelbase_m=WHEELBASE, seed=5)
    b = make_two_track_road(8.0, track_m=TRACK, wheelbase_m=WHEELBASE, seed=5)
    c = make_two_track_road(8.0, track_m=TRACK, wheelbase_m=WHEELBASE, seed=6)
    t = np.linspace(0, 8, 977)
    for corner in CORNERS:
        np.testing.assert_array_equal(a.corner(corner).height(t), b.corner(corner).height(t))
        assert np.max(np.abs(a.corner(corner).height(t) - c.corner(corner).height(t))) > 1e-3
    # the right track is its own profile, not the left one
    assert np.max(np.abs(a.fl.height(t) - a.fr.height(t))) > 1e-3


def test_a_corner_road_drives_the_closed_loop():
    from erva_ros.core.studies.closed_loop import simulate_closed_loop
    from erva_ros.core.controllers import ControllerSettings, make_controller
    from erva_ros.core.model.params import paper_params
    params = paper_params()
    car = make_two_track_road(2.0, track_m=TRACK, wheelbase_m=WHEELBASE, seed=2)
    model = make_model(params)
    run = simulate_closed_loop(model, make_controller('passive', model, ControllerSettings()),
                               car.rr, 1.0)
    np.testing.assert_array_equal(run.w, car.rr.height(run.t))
    late = run.t >= car.rear_delay_s
    np.testing.assert_allclose(run.w[late], car.fr.height(run.t[late] - car.rear_delay_s),
                               rtol=0, atol=1e-15)
    assert np.all(run.w[~late] == 0.0) and np.all(np.isfinite(run.sprung_accel))


@pytest.mark.parametrize('opts, match', [
    ({'track_m': 0.0}, 'track_m'),
    ({'wheelbase_m': float('nan')}, 'wheelbase_m'),
    ({'right_class': 'F'}, 'right_class'),
    ({'road_class': 'Z'}, 'road_class'),
    ({'seed': -1}, 'seed'),
    ({'speed_mps': -3}, 'speed_mps'),
])
def test_bad_two_track_options_give_one_line_errors(opts, match):
    kwargs = dict(track_m=TRACK, wheelbase_m=WHEELBASE)
    kwargs.update(opts)
    with pytest.raises(RoadError, match=match) as err:
        make_two_track_road(2.0, **kwargs)
    assert '\n' not in str(err.value)
    with pytest.raises(RoadError, match='delay'):
        delayed_road(make_road('sine', 1.0), 0.0)
