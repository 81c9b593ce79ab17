"""The whole car (core/model/full_car.py, core/model/car_params.py): values that physics fixes.

Four quarter cars where symmetry says so, energy, the heave/pitch/roll modes, the body's
geometry, the published parameters and their one-line errors.
"""

from dataclasses import replace
import os

import numpy as np
import pytest
import yaml

from erva_ros.core.studies import fr
from erva_ros.core.model.car_params import BODY_SPECS, CarParams, CORNERS, load_car_params
from erva_ros.core.model.quarter_car import linearize, QuarterCarModel, rk4_stable_substeps
from erva_ros.core.model.params import paper_params, PAPER_VALUES, ParamError
from erva_ros.core.road.profiles import make_road
from erva_ros.core.model.full_car import (body_modes as vehicle_body_modes, body_response,
                                          corner_slice, FullCarModel, get_car_model, NX,
                                          ROAD_PATTERNS, STATE_NAMES)

from conftest import REPO

P = paper_params()
DT, SUB = 0.02, 40                  # the plant's 0.5 ms RK4 sub-steps
#: The published set (CommonRoad vehicle 2, BMW 320i, commonroad-vehicle-models 3.0.2's
#: parameters_vehicle2.yaml; docs/model.md), and the same values as printed in "CommonRoad:
#: Vehicle Models (Version 2019b)", Table 4, with the unit of their last digit.
PUBLISHED = {'M': 965.7108098804363, 'I_theta': 1565.8178787125541,
             'I_phi': 207.26524557936952, 'l_f': 1.1561957064, 'l_r': 1.4227170936,
             't_f': 1.38684, 't_r': 1.36398, 'M_u_f': 63.7921826056784,
             'M_u_r': 63.7921826056784}
PRINTED = {'M': (965.0, 1.0), 'I_theta': (1565.0, 1.0), 'I_phi': (207.2, 0.1),
           'l_f': (1.156, 1e-3), 'l_r': (1.422, 1e-3), 't_f': (1.386, 1e-3),
           't_r': (1.364, 1e-3), 'M_u_f': (63.79, 0.01), 'M_u_r': (63.79, 0.01)}


def symmetric_car(p=P, I_theta=1234.0, I_phi=456.0, arm=1.3, t=1.5) -> CarParams:
    """Return a rigid symmetric body: centre of gravity in the middle, mass 4·M_s."""
    return CarParams(4 * p.M_s, I_theta, I_phi, arm, arm, t, t, (p,) * 4)


def arms(p: CarParams) -> np.ndarray:
    """J_i = (1, −x_i, y_i) of each corner, written from ISO 8855 here (rows FL..RR)."""
    return np.array([[1.0, -p.l_f, p.t_f / 2], [1.0, -p.l_f, -p.t_f / 2],
                     [1.0, p.l_r, p.t_r / 2], [1.0, p.l_r, -p.t_r / 2]])


def body_modes(p: CarParams):
    """Body modes of a car with four equal corners: K_J v = λ·diag(M, I_θ, I_φ)·v.

    Each is a quarter car whose sprung mass is 1/λ (docs/model.md, "The whole car").
    """
    j = arms(p)
    lam, vec = np.linalg.eig(np.linalg.solve(np.diag([p.M, p.I_theta, p.I_phi]), j.T @ j))
    return lam.real, vec.real


def clamped_corner(p, u: float) -> np.ndarray:
    """Return A of a corner under a body that does not move, at rest, built by hand."""
    g = p.m_r + p.m_d
    mass = np.array([[p.M_us + p.m_b, -g], [0.0, g]])
    damp = np.array([[p.c, 0.0], [u, u]])
    stiff = np.array([[p.k_s + p.k_t, 0.0], [p.k_d, p.k_d]])
    a = np.zeros((4, 4))
    a[0, 1] = a[2, 3] = 1.0
    a[np.ix_([1, 3], [0, 2])] = -np.linalg.solve(mass, stiff)
    a[np.ix_([1, 3], [1, 3])] = -np.linalg.solve(mass, damp)
    return a


def road(seed: int, n: int) -> np.ndarray:
    return make_road('iso8608', n * DT, seed=seed, road_class='C').height(DT * np.arange(n + 1))


# -- four quarter cars -------------------------------------------------------------------------

@pytest.mark.parametrize('mode', ['heave', 'pitch', 'roll'])
def test_a_symmetric_car_is_four_quarter_cars(mode):
    """Give every corner one road and one bang-bang command: four quarter cars, to 1e-9.

    The road in phase, or against itself front/rear or left/right: each corner is the quarter
    car whose sprung mass is its share of the body's mass (heave, M/4 = Table I's M_s) or
    inertia (I_θ/(4 l²), I_φ/t²), states and accelerations.
    """
    cp = symmetric_car()
    car = FullCarModel(cp)
    l, t = cp.l_f, cp.t_f
    share = {'heave': cp.M / 4, 'pitch': cp.I_theta / (4 * l * l), 'roll': cp.I_phi / t ** 2}
    qc = QuarterCarModel(P.with_(M_s=share[mode]))
    assert share['heave'] == P.M_s
    n = 250
    w = road(7, n)
    u = np.where((np.arange(n) // 3) % 2 == 0, 2e4, 0.0)
    sign = np.array(ROAD_PATTERNS[mode])
    xs = car.simulate(np.zeros(NX), np.outer(u, np.ones(4)), np.outer(w, sign), DT, SUB)
    xq = qc.simulate(np.zeros(6), u, w, DT, SUB)
    zs, vs = (np.asarray(f).T for f in car.body_points.map(n + 1)(xs.T))
    body_acc, acc, power = car.outputs_along(xs, np.outer(np.r_[u, u[-1]], np.ones(4)),
                                             np.outer(w, sign))
    acc_q, power_q = qc.outputs_along(xq, np.r_[u, u[-1]], w)
    for i in range(4):
        s = sign[i]
        np.testing.assert_allclose(s * zs[:, i], xq[:, 0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(s * vs[:, i], xq[:, 1], rtol=0, atol=1e-9)
        np.testing.assert_allclose(s * xs[:, corner_slice(i)], xq[:, 2:], rtol=0, atol=1e-9)
        np.testing.assert_allclose(s * acc[:, i], acc_q, rtol=0, atol=1e-9)
        np.testing.assert_allclose(power[:, i], power_q, rtol=0, atol=1e-9)
    others = [k for k, m in zip((0, 2, 4), ROAD_PATTERNS) if m != mode]
    assert np.all(xs[:, others] == 0.0) and np.all(xs[:, [k + 1 for k in others]] == 0.0)
    assert np.max(np.abs(xq[:, 4] - (xq[:, 0] - xq[:, 2]))) > 1e-3      # the rotor swings
    assert np.max(np.abs(acc_q)) > 0.5 and np.max(power_q) > 100        # not a quiet run


# -- modes and frequency response --------------------------------------------------------------

def quarter_car_spectrum(p, u):
    return np.linalg.eigvals(linearize(QuarterCarModel(p), u0=u)[0])


@pytest.mark.parametrize('which', ['published', 'symmetric'])
@pytest.mark.parametrize('u', [0.0, P.c_e0, 2e4])
def test_the_body_modes_are_quarter_cars(which, u):
    """Find the quarter cars' eigenvalues in the car's, linearised at rest.

    With four equal corners they are those of three quarter cars, one per body mode k with
    sprung mass 1/λ_k, and of one corner under a body that does not move (the warp mode):
    3·6 + 4 = 22.
    """
    cp = load_car_params() if which == 'published' else symmetric_car()
    corner = cp.corners[0]
    assert all(c.with_(M_s=corner.M_s) == corner for c in cp.corners[1:])   # M_s: not used
    car = get_car_model(cp)
    lam, _ = body_modes(cp)
    expected = np.concatenate([quarter_car_spectrum(corner.with_(M_s=1 / lk), u)
                               for lk in lam] + [np.linalg.eigvals(clamped_corner(corner, u))])
    got = list(np.linalg.eigvals(linearize(car, u0=u)[0]))
    assert len(got) == len(expected) == NX
    for ev in expected:                     # each expected eigenvalue, matched once
        k = int(np.argmin(np.abs(np.array(got) - ev)))
        assert abs(got[k] - ev) <= 1e-9 * abs(ev), (ev, got[k])
        got.pop(k)
    if which == 'symmetric':                # heave M/4, pitch I_θ/(4l²), roll I_φ/t²
        np.testing.assert_allclose(sorted(1 / lam), sorted(
            [cp.M / 4, cp.I_theta / (4 * cp.l_f ** 2), cp.I_phi / cp.t_f ** 2]), rtol=1e-12)


def test_the_published_cars_modes():
    """Find roll a mode of its own, heave and pitch coupled into axle bounces.

    Left/right symmetry leaves roll alone; heave and pitch make a front- and a rear-axle
    bounce (docs/model.md), each within 1 % of its axle's static share of the body.
    """
    cp = load_car_params()
    lam, vec = body_modes(cp)
    masses = 1 / lam
    roll = int(np.argmax(np.abs(vec[2])))
    assert masses[roll] == pytest.approx(cp.I_phi / ((cp.t_f ** 2 + cp.t_r ** 2) / 2),
                                         rel=1e-12)
    others = [k for k in range(3) if k != roll]
    assert np.max(np.abs(vec[:2, roll])) < 1e-12 and np.max(np.abs(vec[2, others])) < 1e-12
    front, rear = cp.static_share(0), cp.static_share(2)
    bounce = sorted(masses[k] for k in range(3) if k != roll)
    assert bounce[0] == pytest.approx(rear, rel=0.01)
    assert bounce[1] == pytest.approx(front, rel=0.01)
    shipped, shapes = vehicle_body_modes(cp)           # what the module gives users
    np.testing.assert_allclose(shipped, sorted(masses, reverse=True), rtol=1e-12)
    for k, m in enumerate(shipped):
        v = vec[:, int(np.argmin(np.abs(masses - m)))]
        assert abs(shapes[:, k] @ v) == pytest.approx(np.linalg.norm(v), rel=1e-12)


def complex_response(model, pattern, freqs, u):
    """Return the body accelerations (z̈_c, θ̈, φ̈) per metre of road in ``pattern``."""
    a, _, bw = linearize(model, u0=u)
    b = bw @ np.asarray(pattern, dtype=float)
    out = []
    for f in freqs:
        x = np.linalg.solve(2j * np.pi * f * np.eye(a.shape[0]) - a, b)
        out.append(a[[1, 3, 5]] @ x + b[[1, 3, 5]])
    return np.array(out)


def complex_response_qc(qc, freqs, u):
    """Return the quarter car's z̈_s per metre of road, complex."""
    a, _, bw = linearize(qc, u0=u)
    out = []
    for f in freqs:
        x = np.linalg.solve(2j * np.pi * f * np.eye(6) - a, bw[:, 0])
        out.append(a[1] @ x + bw[1, 0])
    return np.array(out)


@pytest.mark.parametrize('mode', ['heave', 'pitch', 'roll'])
def test_road_patterns_excite_the_modes_as_quarter_cars(mode):
    """Sum the body modes' quarter-car responses: the published car's, to 1e-9.

    q̈ = Σ_k v_k·(v_kᵀ Jᵀ w)/(v_kᵀ K_J v_k) · z̈_s,k/w of the quarter car QC(1/λ_k).
    """
    cp = load_car_params()
    car = get_car_model(cp)
    lam, vec = body_modes(cp)
    freqs = np.arange(0.5, 8.0, 0.05)
    pattern = np.array(ROAD_PATTERNS[mode])
    got = complex_response(car, pattern, freqs, P.c_e0)
    want = np.zeros_like(got)
    for k, lk in enumerate(lam):
        v = vec[:, k]
        gen = v @ arms(cp).T @ pattern / (v @ arms(cp).T @ arms(cp) @ v)
        qc = QuarterCarModel(cp.corners[0].with_(M_s=1 / lk))
        want += np.outer(complex_response_qc(qc, freqs, P.c_e0) * gen, v)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.max(np.abs(got)))
    np.testing.assert_allclose(body_response(car, freqs, pattern, P.c_e0, 1e-3),
                               np.abs(got) * 1e-3, rtol=1e-12)
    if mode == 'roll':                      # one mode: φ̈ peaks where its quarter car does
        roll = int(np.argmax(np.abs(vec[2])))
        qc = QuarterCarModel(cp.corners[0].with_(M_s=1 / lam[roll]))
        assert np.max(np.abs(got[:, :2])) < 1e-9 * np.max(np.abs(got[:, 2]))
        peaks = fr.find_peaks(freqs, np.abs(got[:, 2]))
        assert peaks == pytest.approx(fr.find_peaks(
            freqs, fr.linear_response(qc, freqs, 1e-3, P.c_e0)['accel_amp']), abs=1e-9)
        assert len(peaks) == 2 and 2.0 < peaks[0] < 2.4     # the roll mode, then the wheel's


@pytest.mark.parametrize('mode,dof', [('heave', 0), ('pitch', 1), ('roll', 2)])
def test_a_sweep_peaks_at_each_mode_of_a_symmetric_car(mode, dof):
    """Sweep each road pattern: one body motion moves, peaking where its quarter car does.

    In phase (heave), front/rear (pitch), left/right (roll); the peak is paper Fig. 4's first.
    """
    cp = symmetric_car()
    car = get_car_model(cp)
    share = {'heave': cp.M / 4, 'pitch': cp.I_theta / (4 * cp.l_f ** 2),
             'roll': cp.I_phi / cp.t_f ** 2}[mode]
    arm = {'heave': 1.0, 'pitch': cp.l_f, 'roll': cp.t_f / 2}[mode]
    freqs = np.arange(0.5, 8.0, 0.02)
    got = body_response(car, freqs, ROAD_PATTERNS[mode], P.c_e0, 1e-3)
    qc = fr.linear_response(QuarterCarModel(P.with_(M_s=share)), freqs, 1e-3, P.c_e0)
    assert np.all(np.delete(got, dof, axis=1) <= 1e-12 * np.max(got))
    np.testing.assert_allclose(got[:, dof] * arm, qc['accel_amp'], rtol=1e-9)
    first = fr.find_peaks(freqs, got[:, dof])[0]
    assert first == pytest.approx(fr.find_peaks(freqs, qc['accel_amp'])[0], abs=1e-9)
    assert 1.0 < first < 3.0


@pytest.mark.parametrize('mode', ['heave', 'pitch', 'roll'])
def test_the_nonlinear_car_follows_its_linearisation_at_1mm(mode):
    """Follow the linearisation's periodic motion within 1e-4 on a 1 mm road.

    At each pattern's strongest resonance; the gap grows as the road's amplitude squared
    (the inertia nonlinearity ε·r_1, r_1 = φ²), ~100× at 1 cm.
    """
    cp = load_car_params()
    car = get_car_model(cp)
    pattern = np.array(ROAD_PATTERNS[mode])
    freqs = np.arange(1.0, 3.0, 0.01)
    dof = {'heave': 0, 'pitch': 1, 'roll': 2}[mode]
    f = freqs[int(np.argmax(body_response(car, freqs, pattern, P.c_e0)[:, dof]))]
    a, _, bw = linearize(car, u0=P.c_e0)
    om = 2 * np.pi * f
    dt = 5e-4
    n = int(round(3 / f / dt))              # three periods
    t = dt * np.arange(n + 1)
    gap = {}
    for amp in (1e-3, 1e-2):
        xw = np.linalg.solve(1j * om * np.eye(NX) - a, bw @ pattern) * amp
        xs = car.simulate(np.imag(xw), np.full((n, 4), P.c_e0),
                          np.outer(amp * np.sin(om * t), pattern), dt)
        lin = np.imag(np.outer(np.exp(1j * om * t), xw))      # the linear periodic motion
        gap[amp] = np.max(np.abs(xs - lin)) / np.max(np.abs(lin))
    assert gap[1e-3] < 1e-4
    assert 50 < gap[1e-2] / gap[1e-3] < 150


# -- energy ------------------------------------------------------------------------------------

def uneven_car() -> CarParams:
    """Return the published body on four different corners."""
    cp = load_car_params()
    c = cp.corners
    return CarParams(cp.M, cp.I_theta, cp.I_phi, cp.l_f, cp.l_r, cp.t_f, cp.t_r,
                     (c[0], c[1].with_(k_s=45e3, c=120.0), c[2].with_(M_us=40.0, k_t=170e3),
                      c[3].with_(k_d=20e3, m_d=110.0, epsilon=0.2)))


@pytest.mark.parametrize('switching,tol', [(False, 1e-4), (True, 3e-3)])
def test_energy_balance_with_damping_and_four_roads(switching, tol):
    """Balance the road's work on four tyres: Δ stored + dissipated in c + harvested.

    As the quarter car's (test_model.py), with different roads, commands and corners.
    """
    cp = uneven_car()
    car = FullCarModel(cp)
    dt, n = 5e-4, 8000
    t = dt * np.arange(n + 1)
    freq = np.array([1.7, 1.9, 2.3, 5.5])
    phase = np.array([0.0, 1.0, 2.0, 3.0])
    om = 2 * np.pi * freq
    w = 0.01 * np.sin(np.outer(t, om) + phase)
    wdot = 0.01 * om * np.cos(np.outer(t, om) + phase)
    if switching:
        u = np.where(np.sin(2 * np.pi * np.outer(t[:-1], [3.1, 2.3, 4.7, 1.3])) > 0, 3e4, 2e3)
    else:
        u = np.tile([1e4, 5e3, 2e4, 0.0], (n, 1))
    xs = car.simulate(np.zeros(NX), u, w, dt)
    vgen = np.asarray(car.generator_velocity.map(n + 1)(xs.T)).T
    zs, vs = (np.asarray(f).T for f in car.body_points.map(n + 1)(xs.T))
    harvested = parasitic = road_work = 0.0
    for i, c in enumerate(cp.corners):
        zus, vus = xs[:, corner_slice(i)][:, 0], xs[:, corner_slice(i)][:, 1]
        harvested += np.sum(dt * u[:, i] * (vgen[:-1, i] ** 2 + vgen[1:, i] ** 2) / 2)
        parasitic += np.trapezoid(c.c * (vs[:, i] - vus) ** 2, dx=dt)
        road_work += np.trapezoid(c.k_t * (w[:, i] - zus) * wdot[:, i], dx=dt)
    e = np.asarray(car.energy.map(n + 1)(xs.T, w.T)).ravel()
    assert harvested > 0 and road_work > 0 and harvested <= road_work
    balance = road_work - (e[-1] - e[0]) - parasitic - harvested
    assert abs(balance) < tol * road_work
    assert np.max(np.abs(xs[:, [2, 4]])) > 1e-3                 # pitch and roll took part


def test_energy_is_conserved_without_damping_and_decays_with_it():
    cp = uneven_car()
    free = replace(cp, corners=tuple(c.with_(c=0.0) for c in cp.corners))
    x0 = np.zeros(NX)
    x0[[1, 3, 5]] = 0.1, 0.2, 0.3
    for i in range(4):
        x0[corner_slice(i)] = [0.01 * (i + 1), 0.1, 0.03, 0.3 * (-1) ** i]
    n = 10000
    for params, u in ((free, 0.0), (cp, [1e4, 0.0, 5e3, 2e4])):
        car = FullCarModel(params)
        xs = car.simulate(x0, np.broadcast_to(u, (n, 4)), np.zeros((n + 1, 4)), 5e-4)
        e = np.asarray(car.energy.map(n + 1)(xs.T, 0.0)).ravel()
        if params is free:                  # 5 s: kept to 1e-6, the inertia nonlinearity live
            assert np.max(np.abs(e - e[0])) / e[0] < 1e-6
            rotor = np.max(np.abs(np.asarray(car.generator.map(n + 1)(xs.T, 0.0)[0])))
            assert rotor > 0.02
        else:                               # never gains energy without a road
            assert np.all(np.diff(e) <= 1e-9 * e[0]) and e[-1] < 0.2 * e[0]


def test_plant_step_integrates_power_and_accelerations():
    """Check plant_step: x⁺ is rk4_step's (and rk4_flow's), integrals a 10 µs trapezoid's."""
    car = get_car_model(load_car_params())
    n0 = 50                                 # a state the road made, then one control period
    w = np.stack([road(seed, n0 + 1) for seed in range(4)], axis=1)
    u = np.array([2e4, 0.0, 1e4, 5e3])
    x0 = car.simulate(np.zeros(NX), np.tile(u, (n0, 1)), w[:n0 + 1], DT, SUB)[-1]
    w0, w1 = w[n0], w[n0 + 1]
    xn, eh, acc2, body2 = (np.asarray(v).ravel() for v in car.plant_step(DT, SUB)(x0, u, w0, w1))
    np.testing.assert_array_equal(xn, np.asarray(car.rk4_step(DT, SUB)(x0, u, w0, w1)).ravel())
    flow = np.asarray(car.rk4_flow(SUB)(x0, u, w0, w1, DT)).ravel()
    np.testing.assert_allclose(flow, xn, rtol=0, atol=1e-14 * np.max(np.abs(xn)))
    n = 2000
    fine = np.linspace(w0, w1, n + 1)
    xs = car.simulate(x0, np.tile(u, (n, 1)), fine, DT / n)
    body, acc, power = car.outputs_along(xs, u, fine)
    np.testing.assert_allclose(eh, np.trapezoid(power, dx=DT / n, axis=0), rtol=1e-6)
    np.testing.assert_allclose(acc2, np.trapezoid(acc ** 2, dx=DT / n, axis=0), rtol=1e-6)
    np.testing.assert_allclose(body2, np.trapezoid(body ** 2, dx=DT / n, axis=0), rtol=1e-6)
    assert np.all(eh[[0, 2, 3]] > 1e-3) and eh[1] == 0.0 and np.all(acc2 > 1e-3)


def test_the_plant_integrator_converges():
    """Halve the 0.5 ms sub-step: a 1 s bang-bang run on four roads moves < 1e-6."""
    car = get_car_model(load_car_params())
    n = 50
    t = DT * np.arange(n + 1)
    w = 0.01 * np.sin(2 * np.pi * np.outer(t, [1.7, 2.2, 1.7, 2.9]))
    u = np.where((np.arange(n)[:, None] + np.arange(4)) % 3 == 0, 5e4, 0.0)
    coarse = car.simulate(np.zeros(NX), u, w, DT, SUB)
    fine = car.simulate(np.zeros(NX), u, w, DT, 2 * SUB)
    crude = car.simulate(np.zeros(NX), u, w, DT, SUB // 4)         # 2 ms: stable, inaccurate
    scale = np.max(np.abs(fine), axis=0)
    assert np.max(np.abs(coarse - fine) / scale) < 1e-6
    assert np.max(np.abs(crude - fine)) > 100 * np.max(np.abs(coarse - fine))
    assert rk4_stable_substeps(car, DT, 5e4) <= SUB


# -- geometry ----------------------------------------------------------------------------------

def test_the_body_points_lie_on_the_rigid_body_plane():
    """Find z_s,i on the body's plane at (x_i, y_i).

    ISO 8855: pitch positive nose down, roll positive left side up, the plane's height at
    the centre of gravity z_c.
    """
    cp = load_car_params()
    car = get_car_model(cp)
    x = np.random.default_rng(5).normal(scale=0.02, size=NX)
    z, v = (np.asarray(a).ravel() for a in car.body_points(x))
    pos = np.array(cp.positions())
    for pts, (h, th, ph) in ((z, x[[0, 2, 4]]), (v, x[[1, 3, 5]])):
        plane = np.linalg.lstsq(np.c_[np.ones(4), pos], pts, rcond=None)
        np.testing.assert_allclose(plane[0], [h, -th, ph], rtol=1e-12)  # height, slopes x, y
        assert np.allclose(np.c_[np.ones(4), pos] @ plane[0], pts, rtol=0, atol=1e-15)
    assert (z[0] + z[1]) / 2 - (z[2] + z[3]) / 2 == pytest.approx(-(cp.l_f + cp.l_r) * x[2])
    assert z[0] - z[1] == pytest.approx(cp.t_f * x[4]) and z[2] - z[3] == pytest.approx(
        cp.t_r * x[4])
    np.testing.assert_array_equal(np.asarray(car.deflection(x)).ravel(),
                                  z - x[[corner_slice(i).start for i in range(4)]])


def test_a_standing_car_on_an_uneven_road_takes_the_plane_its_springs_choose():
    """Stand on four road heights: the body takes the plane its corners' forces balance.

    Static forces k_i·(w_i − z_s,i), k_i = k_s·k_t/(k_s + k_t): pitch and roll follow the
    road's slopes, what the body cannot follow (warp) stays in the springs.
    """
    cp = uneven_car()
    car = FullCarModel(cp)
    w = np.array([0.02, -0.01, 0.005, 0.03])
    a, _, bw = linearize(car, u0=P.c_e0)
    x = -np.linalg.solve(a, bw @ w)                 # ẋ = 0 of the linearisation ...
    xdot = np.asarray(car.ode(x, P.c_e0, w)).ravel()
    assert np.max(np.abs(xdot)) < 1e-12             # ... is the nonlinear car's rest too
    k = np.array([c.k_s * c.k_t / (c.k_s + c.k_t) for c in cp.corners])
    j = arms(cp)
    pose = np.linalg.solve(j.T @ (k[:, None] * j), j.T @ (k * w))
    np.testing.assert_allclose(x[[0, 2, 4]], pose, rtol=1e-9)
    assert abs(pose[1]) > 1e-3 and abs(pose[2]) > 1e-3
    zs = j @ pose
    force = k * (w - zs)
    for i, c in enumerate(cp.corners):
        zus, zd = x[corner_slice(i)][0], x[corner_slice(i)][2]
        assert zs[i] - zus == pytest.approx(-force[i] / c.k_s, rel=1e-9)     # spring
        assert zus - w[i] == pytest.approx(-force[i] / c.k_t, rel=1e-9)      # tyre
        assert zd == pytest.approx(zs[i] - zus, rel=1e-9)                    # k_d relaxed
    assert np.max(np.abs(force)) > 10 * np.max(np.abs(j.T @ force))          # warp held


def test_pitch_and_roll_answer_a_bump_under_one_wheel():
    """Lift the nose (θ < 0) and the left side (φ > 0) with a bump under the front left.

    A 2 cm bump; under the front right the motion is its mirror image.
    """
    cp = load_car_params()
    car = get_car_model(cp)
    n = 100
    t = DT * np.arange(n + 1)
    bump = np.where(t < 0.2, 0.01 * (1 - np.cos(2 * np.pi * t / 0.2)), 0.0)
    runs = {}
    for corner in ('FL', 'FR', 'RL'):
        w = np.zeros((n + 1, 4))
        w[:, CORNERS.index(corner)] = bump
        runs[corner] = car.simulate(np.zeros(NX), np.full((n, 4), P.c_e0), w, DT, SUB)
    fl, fr_, rl = runs['FL'], runs['FR'], runs['RL']
    first = np.argmax(np.abs(fl[:, 2]) > 1e-4)
    assert fl[first, 2] < 0 and fl[np.argmax(np.abs(fl[:, 4]) > 1e-4), 4] > 0
    assert rl[np.argmax(np.abs(rl[:, 2]) > 1e-4), 2] > 0             # rear up: nose down
    mirror = fl.copy()
    mirror[:, [4, 5]] *= -1
    swap = np.r_[corner_slice(1), corner_slice(0), corner_slice(3), corner_slice(2)]
    mirror[:, 6:] = fl[:, swap]
    np.testing.assert_allclose(fr_, mirror, rtol=0, atol=1e-12 * np.max(np.abs(fl)))
    assert np.max(np.abs(fl[:, 4])) > 1e-3 and np.max(np.abs(fl[:, 2])) > 1e-3


# -- outputs -----------------------------------------------------------------------------------

def test_each_corner_measures_what_its_quarter_car_would():
    cp = uneven_car()
    car = FullCarModel(cp)
    assert car.nx == NX == 22 and len(STATE_NAMES) == 22 and car.kind == 'car'
    assert STATE_NAMES[:6] == ('z_c', 'zdot_c', 'theta', 'thetadot', 'phi', 'phidot')
    assert STATE_NAMES[corner_slice(3)] == ('z_us_RR', 'zdot_us_RR', 'z_d_RR', 'zdot_d_RR')
    rng = np.random.default_rng(11)
    x = rng.normal(scale=0.01, size=NX)
    u, w = np.array([1e4, 0.0, 2e4, 5e3]), rng.normal(scale=0.003, size=4)
    y = np.asarray(car.measurements(x, u, w)).reshape(4, 3)
    acc = np.asarray(car.sprung_accel(x, u, w)).ravel()
    zs, vs = (np.asarray(a).ravel() for a in car.body_points(x))
    position, vgen, power = (np.asarray(a).ravel() for a in car.generator(x, u))
    for i, c in enumerate(cp.corners):
        local = np.r_[zs[i], vs[i], x[corner_slice(i)]]
        qc = QuarterCarModel(c)
        assert y[i, 0] == acc[i]
        assert y[i, 1] == pytest.approx(float(qc.deflection(local)), rel=1e-15)
        assert y[i, 2] == pytest.approx(float(qc.generator_velocity(local)) / c.l, rel=1e-12)
        assert vgen[i] == pytest.approx(float(qc.generator_velocity(local)), rel=1e-12)
        assert position[i] == pytest.approx(float(qc.generator(local, u[i])[0]), rel=1e-12)
        assert power[i] == pytest.approx(float(qc.power(local, u[i])), rel=1e-12)
    assert float(car.total_power(x, u)) == pytest.approx(np.sum(power), rel=1e-15)
    body = np.asarray(car.body_accel(x, u, w)).ravel()
    np.testing.assert_allclose(acc, arms(cp) @ body, rtol=1e-12)
    xdot = np.asarray(car.ode(x, u, w)).ravel()
    np.testing.assert_array_equal(xdot[[1, 3, 5]], body)
    assert np.all(np.isfinite(np.asarray(car.ode(np.zeros(NX), 5e4, 0.0))))      # E(x) = 0


# -- parameters --------------------------------------------------------------------------------

def write(tmp_path, values, name='car.yaml'):
    path = tmp_path / name
    path.write_text(yaml.safe_dump({'/**': {'ros__parameters': values}}))
    return str(path)


def test_the_shipped_car_is_the_published_set_on_table_i_corners():
    with open(os.path.join(REPO, 'config', 'car.yaml'), encoding='utf-8') as fh:
        shipped = yaml.safe_load(fh)['/**']['ros__parameters']
    assert shipped == PUBLISHED and set(shipped) == set(BODY_SPECS)
    for key, (printed, digit) in PRINTED.items():   # within one unit of the last digit
        assert abs(shipped[key] - printed) < digit, key
    cp = load_car_params()
    assert (cp.M, cp.I_theta, cp.I_phi, cp.l_f, cp.l_r, cp.t_f, cp.t_r) == tuple(
        PUBLISHED[k] for k in ('M', 'I_theta', 'I_phi', 'l_f', 'l_r', 't_f', 't_r'))
    for i, c in enumerate(cp.corners):
        own = c.as_dict()
        assert own.pop('M_us') == PUBLISHED['M_u_f'] / 2
        assert own.pop('M_s') == pytest.approx(cp.M * (cp.l_r if i < 2 else cp.l_f)
                                               / (2 * (cp.l_f + cp.l_r)))
        assert own == {k: v for k, v in PAPER_VALUES.items() if k not in ('M_s', 'M_us')}
    assert sum(c.M_s for c in cp.corners) == pytest.approx(cp.M)


def test_a_corner_may_have_its_own_device(tmp_path):
    path = write(tmp_path, dict(PUBLISHED, rr={'k_s': 50000.0, 'M_us': 40.0},
                                **{'fl.epsilon': 0.2}))
    cp = load_car_params(path)
    assert cp.corners[3].k_s == 50000.0 and cp.corners[3].M_us == 40.0
    assert cp.corners[0].epsilon == 0.2
    assert cp.corners[1] == load_car_params().corners[1]


@pytest.mark.parametrize('change,needle', [
    ({'I_phi': -1.0}, "parameter 'I_phi' = -1.0 is out of range; allowed (0, 100000] kg m^2"),
    ({'l_f': float('nan')}, "parameter 'l_f' = nan is out of range; allowed (0, 10] m"),
    ({'M': 'heavy'}, "parameter 'M' must be a number in [1, 10000] kg, got str 'heavy'"),
    ({'t_r': None}, "parameter 't_r' must be a number in (0, 5] m"),
    ({'rr': {'k_s': -5.0}}, "parameter 'rr.k_s' = -5.0 is out of range; allowed [100, 1e+07]"),
    ({'fl.M_us': 0.0}, "parameter 'fl.M_us' = 0.0 is out of range; allowed [1, 1000] kg"),
    ({'rl': 3.0}, "parameter 'rl' must be a mapping of corner parameters"),
    ({'fr': {'k_z': 1.0}}, "unknown parameter(s) of corner fr: k_z; did you mean 'k_t'?"),
    ({'fr': {'M_s': 300.0}}, "unknown parameter(s) of corner fr: M_s; did you mean 'M_us'?"),
    ({'I_thet': 1.0}, "unknown parameter(s) I_thet; did you mean 'I_theta'?"),
    ({'FL': {'k_s': 1.0}}, "unknown parameter(s) FL; did you mean 'fl'?"),
])
def test_a_bad_car_file_fails_in_one_line_naming_the_key(tmp_path, change, needle):
    with pytest.raises(ParamError) as info:
        load_car_params(write(tmp_path, dict(PUBLISHED, **change)))
    text = str(info.value)
    assert needle in text and '\n' not in text and text.startswith(str(tmp_path)), text


def test_a_missing_body_value_and_a_bad_device_file_are_named(tmp_path):
    values = dict(PUBLISHED)
    del values['I_theta']
    with pytest.raises(ParamError, match=r"missing parameter 'I_theta' \(expected \(0, 100000\]"):
        load_car_params(write(tmp_path, values))
    device = write(tmp_path, dict(PAPER_VALUES, k_d=-1.0), 'erva.yaml')
    with pytest.raises(ParamError, match=r"erva.yaml: parameter 'k_d' = -1.0 is out of range"):
        load_car_params(write(tmp_path, PUBLISHED), device)
