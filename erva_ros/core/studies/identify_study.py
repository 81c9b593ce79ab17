"""Identification measured on simulated devices: perturbed plants, their sessions, the NMPC.

``erva identify-study`` (commands/identify_study.py) runs, per plant, :func:`study_plant`:

1. **The device.**  Every parameter of the equations of motion (all but c_e0, the
   passive command value) is the paper's times a factor drawn uniformly from
   [1 − spread, 1 + spread] (default ±20 %) by ``numpy.random.default_rng((seed, plant))``.
2. **Its sessions** (:func:`simulate_session`): the excite controller on the road,
   through an actuator that applies each command ``delay_s`` after its sample (the HIL
   loop's 6 ms); the ECU's three sensors with the shipped sensor noise
   (``config/hil.yaml`` ecu_sim section, :class:`~erva_ros.core.hil.ecu_sim.SensorNoise`)
   and the DBC's quantisation (each frame encoded and decoded by the codec, so a
   saturated reading is clipped as on the bus, then dropped as missing); c_e and its
   cycle mean as the ECU's status frame reports them.  One session to fit, another
   (other road seed) held out.
3. **The fit:** :func:`erva_ros.core.identify.fit.identify` from the paper's values.
4. **The NMPC on the device:** the same controller built on the identified, the true
   and the paper's nominal parameters, each run on the device (full state, as
   `erva sim`) on the evaluation road, at each weighting; J = α1·acc_rms² − α2·P_avg.
   And the floor: the true model with every parameter moved by ±0.1 % (``floor_runs``
   random sign patterns) -- how far J moves for a model error ten times below the
   fit's, i.e. how closely any identified model can be expected to match.
"""

from dataclasses import dataclass
import time
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from erva_ros.core.controllers import make_controller
from erva_ros.core.identify.fit import ECU_CHANNELS, PARAMETERS, Recording, identify
from erva_ros.core.identify.report import as_dict
from erva_ros.core.metrics import evaluation_objective
from erva_ros.core.model.params import ERVAParams, paper_params
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.road.profiles import make_road
from erva_ros.core.studies.closed_loop import simulate_closed_loop

#: Default actuation delay of simulated sessions: the HIL loop's (config/hil.yaml).
HIL_DELAY_S = 0.006


def perturbed_params(seed: int, index: int, spread: float = 0.2,
                     base: Optional[ERVAParams] = None) -> ERVAParams:
    """Return plant ``index`` of study ``seed``: each parameter of the dynamics × U(1 ± spread)."""
    base = base or paper_params()
    rng = np.random.default_rng((int(seed), int(index)))
    factors = rng.uniform(1 - spread, 1 + spread, len(PARAMETERS))
    return base.with_(**{k: getattr(base, k) * f for k, f in zip(PARAMETERS, factors)})


def _ecu_frames():
    """Return a function that passes readings through the DBC as the ECU's frames do."""
    from erva_ros.core.hil.codec import Chassis, EcuCodec, EcuMode, Generator, Kind, Status
    codec = EcuCodec()
    senders = {k: codec.sender(k) for k in (Kind.CHASSIS, Kind.GENERATOR, Kind.STATUS)}
    limits = {}
    for kind, sig in ((Kind.CHASSIS, 'SPRUNG_ACCEL'), (Kind.CHASSIS, 'SUSP_DEFLECTION'),
                      (Kind.GENERATOR, 'GEN_SPEED')):
        s = codec.messages[kind].get_signal_by_name(sig)
        limits[sig] = (s.minimum, s.maximum)

    def through(acc, defl, speed, c_e, c_e_mean):
        def rt(kind, payload):
            return codec.decode(kind, codec.encode(kind, payload, senders[kind]).data)
        ch = rt(Kind.CHASSIS, Chassis(acc, defl))
        gen = rt(Kind.GENERATOR, Generator(speed, 0.0, 0.0))
        st = rt(Kind.STATUS, Status(EcuMode.CONTROLLED, c_e, c_e_mean, 0, 0))
        y = [ch.sprung_accel, ch.deflection, gen.speed]
        for i, sig in enumerate(('SPRUNG_ACCEL', 'SUSP_DEFLECTION', 'GEN_SPEED')):
            lo, hi = limits[sig]
            if not lo < y[i] < hi:          # saturated on the bus: not a measurement
                y[i] = float('nan')
        return y, st.c_e_applied, st.c_e_mean
    return through


def simulate_session(params: ERVAParams, road, duration_s: float, settings, *,
                     delay_s: float = HIL_DELAY_S, noise=None, name: str = 'simulated'
                     ) -> Recording:
    """Return what the ECU would record of ``settings``' controller on ``params`` (module doc).

    ``noise`` is a :class:`~erva_ros.core.hil.ecu_sim.SensorNoise` (default: shipped).
    """
    from erva_ros.core.hil.ecu_sim import SensorNoise
    noise = noise or SensorNoise()
    model = make_model(params)
    ctrl = make_controller(settings.controller, model, settings)
    run = simulate_closed_loop(model, ctrl, road, duration_s, settings.ts,
                               actuation_delay_s=delay_s)
    ts = run.ts
    n = run.t.size
    # The damping acting at t_k (what z̈_s(t_k) saw) and its mean over the cycle before.
    acting = np.concatenate([[ctrl.c_e0], run.u[:-1]]) if delay_s > 0 else run.u.copy()
    before = np.concatenate([[ctrl.c_e0], acting[:-1]])
    mean = (delay_s * before + (ts - delay_s) * acting) / ts
    rng = np.random.default_rng(noise.seed)
    frames = _ecu_frames()
    y = np.empty((n, 3))
    u_now, u_mean = np.empty(n), np.empty(n)
    for k in range(n):
        x = run.x[k]
        _, defl, speed = np.asarray(model.measurements(x, acting[k], run.w[k])).ravel()
        e = rng.standard_normal(3)
        y[k], u_now[k], u_mean[k] = frames(
            run.sprung_accel[k] + noise.sprung_accel * e[0], defl + noise.deflection * e[1],
            speed + noise.speed * e[2], acting[k], mean[k])
    u_mean[0] = np.nan                      # the cycle before the first sample: unknown
    return Recording(name, ts, run.w, u_now, u_mean, y, ECU_CHANNELS)


@dataclass(frozen=True)
class StudyConfig:
    """What one plant of the study runs (SI units)."""

    seed: int = 2027
    spread: float = 0.2
    excite_s: float = 60.0
    heldout_s: float = 20.0
    road: str = 'iso8608'
    road_class: str = 'C'
    eval_road: str = 'paper'
    eval_s: float = 10.0
    weights: Tuple[Tuple[float, float], ...] = ((1.0, 0.0), (0.0, 1.0))
    controller: str = 'preview'
    delay_s: float = HIL_DELAY_S
    floor_runs: int = 2
    floor_rel: float = 1e-3


def _road(kind: str, duration_s: float, seed: int, road_class: str):
    opts = {'road_class': road_class} if kind == 'iso8608' else {}
    return make_road(kind, duration_s, seed=seed, **opts)


def study_plant(job) -> Dict:
    """Identify plant ``index`` and compare the NMPCs on it (module doc); a pure function.

    Returns plain data: the truth, the fit (:func:`identify_report.as_dict`) and, per
    weighting, J = α1·acc_rms² − α2·P_avg with the comfort sampled at t_k (the paper's
    measure) and continuous (∫z̈_s² dt, what the continuous-cost NMPC minimises), the
    two comfort measures and the power, of the NMPC on the identified, true and nominal
    model.
    """
    from erva_ros.core.hil.ecu_sim import SensorNoise

    cfg, settings, index = job
    truth = perturbed_params(cfg.seed, index, cfg.spread)
    base = 1000 * (cfg.seed + 1) + 10 * index     # road and noise seeds of this plant
    ex = settings.with_(controller='excite', excite_seed=base % 2047)
    noise = SensorNoise(seed=base)
    fit = simulate_session(truth, _road(cfg.road, cfg.excite_s, base, cfg.road_class),
                           cfg.excite_s, ex, delay_s=cfg.delay_s, noise=noise, name='excite')
    held = simulate_session(truth, _road(cfg.road, cfg.heldout_s, base + 1, cfg.road_class),
                            cfg.heldout_s, ex.with_(excite_seed=(base + 1) % 2047),
                            delay_s=cfg.delay_s, noise=SensorNoise(seed=base + 1),
                            name='heldout')
    sigma0 = {'sprung_accel': noise.sprung_accel, 'deflection': noise.deflection,
              'generator_speed': noise.speed}
    t0 = time.process_time()
    result = identify([fit], make_model(paper_params()), heldout=[held], sigma0=sigma0,
                      truth=truth)
    fit_cpu = time.process_time() - t0
    road = _road(cfg.eval_road, cfg.eval_s, base + 2, cfg.road_class)
    # The floor: the true model with every parameter moved by ±floor_rel (random signs),
    # far less than any fit's error -- how much J moves for a model change that small.
    rng = np.random.default_rng((cfg.seed, index, 7))
    jitter = []
    for _ in range(cfg.floor_runs):
        signs = rng.choice([-1.0, 1.0], len(PARAMETERS))
        jitter.append(truth.with_(**{k: getattr(truth, k) * (1 + cfg.floor_rel * z)
                                     for k, z in zip(PARAMETERS, signs)}))
    models = [('identified', result.params), ('true', truth), ('nominal', paper_params())]
    models += [(f'floor{i}', m) for i, m in enumerate(jitter)]
    runs: List[Dict] = []
    for alpha in cfg.weights:
        s = settings.with_(alpha1=alpha[0], alpha2=alpha[1])
        row: Dict = {'weights': list(alpha)}
        for label, believed in models:
            run = simulate_closed_loop(make_model(truth),
                                       make_controller(cfg.controller, make_model(believed), s),
                                       road, cfg.eval_s, s.ts)
            m = run.metrics
            cont = dict(m, acc_rms=m['acc_rms_continuous'])
            row[label] = {'J_sampled': evaluation_objective(m, alpha),
                          'J_continuous': evaluation_objective(cont, alpha),
                          'acc_rms': m['acc_rms'],
                          'acc_rms_continuous': m['acc_rms_continuous'],
                          'power_w': m['power_w']}
        runs.append(row)
    return {'plant': index, 'truth': truth.as_dict(), 'fit': as_dict(result),
            'fit_cpu_s': fit_cpu, 'closed_loop': runs}


def summarise(plants: Sequence[Dict], objective: str = 'J_continuous') -> Dict:
    """Return the study's tables: parameter errors and coverage, the NMPC's J gaps.

    ``objective``: J_continuous or J_sampled (module doc of :func:`study_plant`).
    """
    params = []
    for name in PARAMETERS:
        rows = [next(p for p in pl['fit']['parameters'] if p['name'] == name) for pl in plants]
        free = [r for r in rows if r['free']]
        err = [100 * (r['value'] / r['truth'] - 1) for r in free]
        prior_err = [100 * (r['prior'] / r['truth'] - 1) for r in rows]
        inside = sum(r['ci95'][0] <= r['truth'] <= r['ci95'][1] for r in free)
        params.append({
            'name': name, 'free_in': len(free), 'plants': len(rows),
            'prior_error_pct_mean_abs': float(np.mean(np.abs(prior_err))),
            'error_pct_mean_abs': float(np.mean(np.abs(err))) if err else None,
            'error_pct_max_abs': float(np.max(np.abs(err))) if err else None,
            'rel_std_pct_mean': float(np.mean([100 * r['rel_std'] for r in free]))
            if free else None,
            'inside_95': inside,
            'fixed_reasons': sorted({r['reason'].split(':')[0] for r in rows if not r['free']}),
        })
    gaps = []
    for k, row in enumerate(plants[0]['closed_loop'] if plants else []):
        alpha = row['weights']
        rel = {lab: [] for lab in ('identified', 'nominal', 'floor')}
        for pl in plants:
            r = pl['closed_loop'][k]
            ref = abs(r['true'][objective])
            for lab in ('identified', 'nominal'):
                rel[lab].append(100 * (r[lab][objective] - r['true'][objective]) / ref)
            floor = [100 * abs(v[objective] - r['true'][objective]) / ref
                     for lab, v in r.items() if lab.startswith('floor')]
            rel['floor'].append(max(floor) if floor else None)
        gaps.append({'weights': alpha, 'objective': objective,
                     'identified_gap_pct': rel['identified'], 'nominal_gap_pct': rel['nominal'],
                     'identified_gap_pct_max_abs': float(np.max(np.abs(rel['identified']))),
                     'nominal_gap_pct_max_abs': float(np.max(np.abs(rel['nominal']))),
                     'floor_pct': rel['floor'],
                     'identified_within_floor': int(sum(
                         f is not None and abs(g) <= f
                         for g, f in zip(rel['identified'], rel['floor']))),
                     'within_2pct': int(sum(abs(g) <= 2.0 for g in rel['identified']))})
    held = {}
    for c in ECU_CHANNELS:
        held[c] = {'identified_mean': float(np.mean([p['fit']['heldout_fit_pct'][c]
                                                     for p in plants])),
                   'prior_mean': float(np.mean([p['fit']['heldout_prior_fit_pct'][c]
                                                for p in plants]))}
    return {'parameters': params, 'closed_loop': gaps, 'heldout_fit_pct': held}


__all__ = ['HIL_DELAY_S', 'perturbed_params', 'simulate_session', 'StudyConfig',
           'study_plant', 'summarise']
