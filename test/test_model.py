"""The shared CasADi model: linearisation, energy, NaN-freedom, integrator convergence."""

import casadi as ca
import numpy as np
import pytest

from erva_ros.core.model.quarter_car import erva_terms, linearize, make_model, rk4_stable_substeps
from erva_ros.core.model.params import paper_params

P = paper_params()
M = make_model(P)


def terms_at(x):
    xs = ca.SX.sym('x', 6)
    t = erva_terms(P, xs)
    f = ca.Function('terms', [xs], [t.h, t.g, t.A, t.B, t.C, t.D, t.E])
    return [float(v) for v in f(x)]


def test_terms_vanish_at_rest():
    h, g, A, B, C, D, E = terms_at(np.zeros(6))
    assert h == B == C == D == E == 0.0
    assert A == pytest.approx(P.m_r + P.m_d) and g == pytest.approx(P.m_r + P.m_d)


def test_terms_do_not_vanish_away_from_rest():
    # A test of the test: with the rotor displaced the nonlinear terms are live.
    h, g, A, B, C, D, E = terms_at(np.array([0, 0, 0, 0, 0.05, 0]))
    assert h != 0 and B != 0 and D != 0 and E < 0 and A > g > P.m_r + P.m_d


def linear_erva_by_hand(p, u):
    """Build the linear ERVA independently: M ẍ + C ẋ + K x = 0 in (z_s, z_us, z_d)."""
    g = p.m_r + p.m_d
    mass = np.array([[p.M_s + p.m_b, -p.m_b, g],
                     [-p.m_b, p.M_us + p.m_b, -g],
                     [0.0, 0.0, g]])
    damp = np.array([[p.c, -p.c, 0], [-p.c, p.c, 0], [-u, u, u]])
    stiff = np.array([[p.k_s, -p.k_s, 0], [-p.k_s, p.k_s + p.k_t, 0],
                      [-p.k_d, p.k_d, p.k_d]])
    minv = np.linalg.inv(mass)
    a = np.zeros((6, 6))
    pos, vel = [0, 2, 4], [1, 3, 5]
    for i in range(3):
        a[pos[i], vel[i]] = 1.0
    a[np.ix_(vel, pos)] = -minv @ stiff
    a[np.ix_(vel, vel)] = -minv @ damp
    return a


@pytest.mark.parametrize('u', [0.0, 1e4, 5e4])
def test_linearisation_at_rest_is_the_linear_erva(u):
    a, bu, bw = linearize(M, u0=u)
    np.testing.assert_allclose(a, linear_erva_by_hand(P, u), rtol=1e-12, atol=1e-9)
    assert np.all(bu == 0)                      # u enters only through v_gen, zero at rest
    assert bw[3, 0] == pytest.approx(P.k_t * (P.M_s + 0) / (  # tyre force on z_us row
        (P.M_s + P.m_b) * (P.M_us + P.m_b) - P.m_b ** 2) + P.k_t * P.m_b / (
        (P.M_s + P.m_b) * (P.M_us + P.m_b) - P.m_b ** 2), rel=1e-9)


def test_fastest_eigenvalues_are_as_documented():
    # docs/model.md: fastest eigenvalue ≈ -250, -520, -1300 1/s at 10, 20, 50 kNs/m.
    m = M
    for u, lam in [(1e4, 250), (2e4, 520), (5e4, 1300)]:
        ev = np.linalg.eigvals(linearize(m, u0=u)[0])
        assert np.max(np.abs(ev.real)) == pytest.approx(lam, rel=0.03)
    assert rk4_stable_substeps(m, 0.02, 5e4) >= 10


def test_no_nan_over_physical_range():
    m = M
    rng = np.random.default_rng(1)
    n = 20000
    x = np.column_stack([rng.uniform(-0.2, 0.2, n), rng.uniform(-5, 5, n),
                         rng.uniform(-0.1, 0.1, n), rng.uniform(-5, 5, n),
                         rng.uniform(-0.3, 0.3, n), rng.uniform(-10, 10, n)])
    x[0] = 0.0  # exactly at rest, where E(x) = 0
    f = m.ode.map(n)
    xdot = np.asarray(f(x.T, rng.uniform(0, 1e5, (1, n)), rng.uniform(-0.05, 0.05, (1, n))))
    assert np.all(np.isfinite(xdot))


def stored_energy(model, xs, w=0.0):
    return np.asarray(model.energy.map(xs.shape[0])(xs.T, w)).ravel()


@pytest.mark.parametrize('kind', ['erva', 'benchmark'])
def test_energy_conserved_without_damping(kind):
    # c = 0, u = 0, no road: RK4 at 0.5 ms keeps energy to 1e-6 (relative) over 10 s.
    m = make_model(P.with_(c=0.0), kind)
    x0 = np.array([0.01, 0.0, 0.0, 0.1, 0.03, 0.3])[:m.nx]
    n = 20000
    xs = m.simulate(x0, np.zeros(n), np.zeros(n + 1), 5e-4)
    e = stored_energy(m, xs)
    assert np.max(np.abs(e - e[0])) / e[0] < 1e-6
    # the nonlinear inertia is really exercised (rotor swings several screw turns)
    if kind == 'erva':
        assert np.max(np.abs(xs[:, 4] - (xs[:, 0] - xs[:, 2]))) > 0.02


@pytest.mark.parametrize('kind', ['erva', 'benchmark'])
@pytest.mark.parametrize('switching,tol', [(False, 1e-4), (True, 3e-3)])
def test_energy_balance_with_damping_and_road(kind, switching, tol):
    """Road work = Δ stored energy + dissipated in c + harvested (docs/model.md)."""
    m = make_model(P, kind)
    dt, n = 5e-4, 8000
    t = dt * np.arange(n + 1)
    om = 2 * np.pi * 1.7
    w, wdot = 0.01 * np.sin(om * t), 0.01 * om * np.cos(om * t)
    u = (np.where(np.sin(2 * np.pi * 3.1 * t[:-1]) > 0, 3e4, 2e3) if switching
         else np.full(n, P.c_e0))
    xs = m.simulate(np.zeros(m.nx), u, w, dt)
    v24 = xs[:, 1] - xs[:, 3]
    vgen = np.asarray(m.generator_velocity.map(n + 1)(xs.T)).ravel()
    # u is held over each interval, so integrate interval by interval
    harvested = np.sum(dt * u * (vgen[:-1] ** 2 + vgen[1:] ** 2) / 2)
    parasitic = np.trapezoid(P.c * v24 ** 2, dx=dt)
    road_work = np.trapezoid(P.k_t * (w - xs[:, 2]) * wdot, dx=dt)
    e = np.asarray(m.energy.map(n + 1)(xs.T, w.reshape(1, -1))).ravel()
    assert harvested > 0 and road_work > 0
    assert harvested <= road_work                      # can never harvest more than put in
    balance = road_work - (e[-1] - e[0]) - parasitic - harvested
    assert abs(balance) < tol * road_work


def test_energy_decays_with_damping():
    m = M
    xs = m.simulate(np.array([0.01, 0, 0, 0.1, 0.03, 0.3]), np.full(4000, P.c_e0),
                    np.zeros(4001), 5e-4)
    e = stored_energy(m, xs)
    assert e[-1] < 0.2 * e[0]
    assert np.all(np.diff(e) <= 1e-9 * e[0])           # never gains energy


def test_plant_integrator_converges():
    """Halving the 0.5 ms plant sub-step changes a 1 s bang-bang run by < 1e-6 relative."""
    m = M
    dt = 0.02
    t = dt * np.arange(51)
    w = 0.01 * np.sin(2 * np.pi * 1.7 * t)
    u = np.where(np.arange(50) % 3 == 0, 5e4, 0.0)
    coarse = m.simulate(np.zeros(6), u, w, dt, substeps=40)
    fine = m.simulate(np.zeros(6), u, w, dt, substeps=80)
    err = np.max(np.abs(coarse - fine), axis=0) / np.max(np.abs(fine), axis=0)
    assert np.max(err) < 1e-6
    crude = m.simulate(np.zeros(6), u, w, dt, substeps=10)  # 2 ms: stable, inaccurate
    assert np.max(np.abs(crude - fine)) > 100 * np.max(np.abs(coarse - fine))


def test_benchmark_matches_its_equations():
    m = make_model(P, 'benchmark')
    x = np.array([0.01, 0.2, -0.003, -0.4])
    u, w = 5e3, 0.002
    mx = P.m_x
    mass = np.array([[P.M_s + mx, -mx], [-mx, P.M_us + mx]])
    rhs = np.array([(P.c + u) * (x[3] - x[1]) + P.k_s * (x[2] - x[0]),
                    (P.c + u) * (x[1] - x[3]) + P.k_s * (x[0] - x[2]) - P.k_t * x[2]
                    + P.k_t * w])
    acc = np.linalg.solve(mass, rhs)
    np.testing.assert_allclose(np.asarray(m.ode(x, u, w)).ravel(),
                               [x[1], acc[0], x[3], acc[1]], rtol=1e-12)
    assert float(m.power(x, u)) == pytest.approx(u * (x[1] - x[3]) ** 2)


def test_plant_simulator_matches_model_and_integrates_energy():
    from erva_ros.core.model.plant import PlantSimulator
    plant = PlantSimulator(M, ts=0.02)
    assert plant.substeps == 40
    dt = 0.02
    t = dt * np.arange(101)
    w = 0.01 * np.sin(2 * np.pi * 1.7 * t)
    u = np.full(100, 2e4)
    for k in range(100):
        plant.step(u[k], w[k], w[k + 1])
    ref = M.simulate(np.zeros(6), u, w, dt, substeps=40)
    np.testing.assert_allclose(plant.x, ref[-1], rtol=1e-12, atol=1e-15)
    # harvested energy vs a fine trapezoid of the sampled power
    # (same piecewise-linear road as the plant sees)
    w_fine = np.interp(2.5e-4 * np.arange(8001), t, w)
    fine = M.simulate(np.zeros(6), np.full(8000, 2e4), w_fine, 2.5e-4)
    vgen = np.asarray(M.generator_velocity.map(8001)(fine.T)).ravel()
    assert plant.harvested_j == pytest.approx(np.trapezoid(2e4 * vgen ** 2, dx=2.5e-4),
                                              rel=1e-4)
    assert plant.t == pytest.approx(2.0)


def test_compiled_plant_step_equals_the_casadi_vm_one():
    import shutil
    if not (shutil.which('cc') or shutil.which('gcc')):
        pytest.skip('no C compiler')
    from erva_ros.core.model.plant import PlantSimulator
    compiled, vm = PlantSimulator(M, codegen='on'), PlantSimulator(M, codegen='off')
    assert compiled._step.fn.name() == vm._step.fn.name()
    assert compiled._step.fn.class_name() == 'External' != vm._step.fn.class_name()
    for k in range(300):   # a command switching across the box, a 1 mm road
        u, w0, w1 = 10000 + 9000 * np.sign(np.sin(k / 5)), 1e-3 * np.sin(k / 3), \
            1e-3 * np.sin((k + 1) / 3)
        compiled.step(u, w0, w1)
        vm.step(u, w0, w1)
    np.testing.assert_allclose(compiled.x, vm.x, rtol=1e-12, atol=1e-15)
    assert compiled.harvested_j == pytest.approx(vm.harvested_j, rel=1e-12)
    assert np.max(np.abs(vm.x)) > 1e-4          # the trajectory really moved
