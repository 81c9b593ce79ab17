"""``erva map-study``: the NMPC with the preview from a map of past drives, against the oracle.

One job per road seed (a pure function of its arguments: local processes or Dask give the
same numbers).  Per seed, on the paper road as a route (its 20 m/s profile, by distance):

1. **Map drives.**  ``max(drives)`` drives at ``map_speed`` with passive damping, each
   recorded as the ECU measures it (:class:`~erva_ros.core.roadmap.vehicle.EcuSensors`),
   smoothed by the road estimator (RTS) and fused into a map; for each odometry error
   level e every drive's distance has that error
   (:meth:`~erva_ros.core.roadmap.vehicle.OdometryError.level`) and is registered on the
   map.  The map after the first 1, 3, 10 drives is kept.
2. **Test drives** from ``start_m``, ``warmup_s`` + ``duration_s``, metrics after the
   warm-up, the NMPC ``controller`` at each weighting:

   ============  ==============================================================
   oracle        true state, the true road ahead (today's ``preview``)
   no_preview    true state, the measured height held (today's ``no_preview``)
   estimated     the road estimator's state and road; the true road's increments
                 ahead, anchored on ŵ_k (what the estimation alone costs)
   map           estimator + map preview (:class:`~erva_ros.core.roadmap.preview.MapPreview`)
                 for every (drives, odometry error); ``variance``: the same, weighted
   speed         map preview at ``other_speed`` (the map drives were at map_speed),
                 with its own oracle and no_preview at that speed
   delay         the HIL command delay (``delay_s`` acting after the sample, modelled
                 in the OCP): oracle, no_preview and map
   ============  ==============================================================

Shares of the gain (:func:`aggregate`): comfort at (1, 0) as
(RMS_no_preview − RMS)/(RMS_no_preview − RMS_oracle) of the continuous RMS z̈_s, power at
(0, 1) as (P − P_no_preview)/(P_oracle − P_no_preview), both from the means over seeds.
"""

from dataclasses import asdict, dataclass, replace
from typing import Dict, List, Sequence, Tuple

import numpy as np

from erva_ros.core.controllers import ControllerSettings, make_controller
from erva_ros.core.model.quarter_car import make_model, QuarterCarModel
from erva_ros.core.model.road_estimator import RoadEKF
from erva_ros.core.road.profiles import make_road
from erva_ros.core.roadmap import MapError
from erva_ros.core.roadmap.drive import estimate_drive, grid_profile
from erva_ros.core.roadmap.preview import map_preview_source, MapPreview, MapPreviewSettings
from erva_ros.core.roadmap.profile import highpass
from erva_ros.core.roadmap.store import compare, RoadMap

#: Road seeds of the study: nothing was tuned on them (development used 0-2).
FIRST_SEED = 100


@dataclass(frozen=True)
class StudyConfig:
    """What ``erva map-study`` runs (SI units)."""

    drives: Tuple[int, ...] = (1, 3, 10)
    odometry_m: Tuple[float, ...] = (0.0, 0.2, 0.5, 1.0)
    weights: Tuple[Tuple[float, float], ...] = ((1.0, 0.0), (0.0, 1.0))
    controller: str = 'preview'
    map_speed: float = 20.0
    other_speed: float = 15.0
    start_m: float = 30.0
    warmup_s: float = 1.0
    duration_s: float = 4.0
    delay_s: float = 0.006
    goal_drives: int = 3
    goal_odometry_m: float = 0.5
    grid_m: float = 0.1
    highpass_m: float = 6.0
    search_m: float = 3.0

    @property
    def route_m(self) -> float:
        """Return how far the map drives go: the test drive, its horizon and a margin."""
        return self.start_m + (self.warmup_s + self.duration_s) * self.map_speed + 20.0


@dataclass(frozen=True)
class Variant:
    """One test drive's setting."""

    name: str                # oracle | no_preview | estimated | map | variance | ...
    alpha: Tuple[float, float]
    speed: float
    drives: int = 0
    odometry_m: float = 0.0
    delay: bool = False

    def key(self) -> str:
        return (f'{self.name}|a={self.alpha[0]:g},{self.alpha[1]:g}|v={self.speed:g}|'
                f'n={self.drives}|e={self.odometry_m:g}|d={int(self.delay)}')


def variants(cfg: StudyConfig) -> List[Variant]:
    """Return every test drive of one seed (module doc)."""
    out = []
    g_n, g_e = cfg.goal_drives, cfg.goal_odometry_m
    for alpha in cfg.weights:
        v = cfg.map_speed
        out += [Variant('oracle', alpha, v), Variant('no_preview', alpha, v),
                Variant('no_preview_estimated', alpha, v), Variant('estimated', alpha, v)]
        out += [Variant('map', alpha, v, n, e) for n in cfg.drives for e in cfg.odometry_m]
        out += [Variant('variance', alpha, v, g_n, g_e)]
        o = cfg.other_speed
        out += [Variant('oracle', alpha, o), Variant('no_preview', alpha, o),
                Variant('map', alpha, o, g_n, g_e)]
        out += [Variant('oracle', alpha, v, delay=True),
                Variant('no_preview', alpha, v, delay=True),
                Variant('map', alpha, v, g_n, g_e, delay=True)]
    return out


def _maps(model: QuarterCarModel, cfg: StudyConfig, seed: int, route, ts: float,
          codegen: str = 'auto'):
    """Return {(drives, e): MapProfile} and the map drives' own estimation errors."""
    from erva_ros.core.roadmap.vehicle import Odometry, OdometryError, simulate_vehicle

    passive = make_controller('passive', model, ControllerSettings())
    ekf = RoadEKF(model, ts=ts, keep_history=True, codegen=codegen)
    n_max = max(cfg.drives)
    duration = cfg.route_m / cfg.map_speed
    estimates, errors = [], []
    for d in range(n_max):
        run = simulate_vehicle(model, passive, route.drive(cfg.map_speed), duration,
                               sensor_seed=seed * 1000 + d)
        est = estimate_drive(run.record(f'drive {d}', route.name, cfg.map_speed), model,
                             ts, ekf)
        estimates.append((run, est))
        g = grid_profile(est, cfg.grid_m, cfg.highpass_m, ts=ts)
        truth = highpass(route.height(g.s), cfg.grid_m, cfg.highpass_m)
        ok = np.isfinite(g.h)
        errors.append(float(np.sqrt(np.mean((g.h[ok] - truth[ok]) ** 2))))
    maps, refused = {}, {}
    for e in cfg.odometry_m:
        road_map = RoadMap.create(':memory:', route.name, cfg.grid_m, cfg.highpass_m)
        for d, (run, est) in enumerate(estimates):
            odo = Odometry(OdometryError.level(e, seed * 1000 + 500 + d), 0.0, ts)
            est = replace(est, distance=np.array([odo.step(cfg.map_speed)[0]
                                                  for _ in range(run.t.size)]))
            g = grid_profile(est, cfg.grid_m, cfg.highpass_m, ts=ts)
            try:
                road_map.add(g, f'{seed}-{d}-{e}', f'drive {d}', search_m=cfg.search_m)
            except MapError:                 # not placed on the map: counted, left out
                refused[e] = refused.get(e, 0) + 1
            if d + 1 in cfg.drives:
                maps[(d + 1, e)] = road_map.profile()
        road_map.close()
    return maps, errors, refused


def run_seed(job) -> Tuple[int, Dict]:
    """Run one seed's map drives and test drives; return (seed, results)."""
    from erva_ros.core.roadmap.vehicle import (OdometryError, oracle_preview, Route,
                                               simulate_vehicle)

    params, settings, seed, cfg = job
    ts = settings.ts
    route = Route.of(make_road('paper', cfg.route_m / cfg.map_speed, seed=seed,
                               speed_mps=cfg.map_speed))
    model = make_model(params)
    maps, drive_errors, refused = _maps(model, cfg, seed, route, ts, settings.codegen)
    ekf = RoadEKF(model, ts=ts, codegen=settings.codegen)
    controllers = {}
    rows = []
    for var in variants(cfg):
        name = 'no_preview' if var.name.startswith('no_preview') else cfg.controller
        key = (name, var.alpha, var.delay)
        if key not in controllers:
            s = settings.with_(alpha1=var.alpha[0], alpha2=var.alpha[1],
                               command_delay_s=cfg.delay_s if var.delay else 0.0)
            controllers[key] = make_controller(name, model, s)
        road = route.drive(var.speed, cfg.start_m)
        est = None if var.name in ('oracle', 'no_preview') else ekf
        preview, mp = None, None
        if var.name == 'estimated':
            preview = oracle_preview(road, ts, anchored=True)
        elif var.name in ('map', 'variance'):
            weighting = 'variance' if var.name == 'variance' else 'none'
            mp = MapPreview(maps[(var.drives, var.odometry_m)], ts,
                            MapPreviewSettings(weighting=weighting))
            preview = map_preview_source(mp)
        run = simulate_vehicle(
            model, controllers[key], road, cfg.duration_s, start_m=cfg.start_m,
            estimator=est, preview=preview, warmup_s=cfg.warmup_s,
            odometry=OdometryError.level(var.odometry_m, seed * 1000 + 900),
            sensor_seed=seed * 1000 + 77, delay_s=cfg.delay_s if var.delay else 0.0)
        row = {'variant': asdict(var), 'key': var.key(), 'metrics': run.metrics}
        if est is not None:
            n0 = int(round(cfg.warmup_s / ts))
            e = run.w_hat[n0:] - run.w[n0:]
            row['road_error_m'] = float(np.sqrt(np.mean((e - e.mean()) ** 2)))
        if mp is not None:
            row['preview'] = asdict(mp.counts)
            row['preview']['offset_m'] = mp.offset
        rows.append(row)
    map_errors = {}
    for (n, e), mp in maps.items():
        c = compare(mp, route.height, cfg.search_m)
        map_errors[f'{n}|{e:g}'] = {'rms_m': c.error_rms_m, 'predicted_std_m': c.predicted_std_m,
                                    'variance_scale': mp.variance_scale}
    truth = highpass(route.height(np.arange(0, cfg.route_m, cfg.grid_m)), cfg.grid_m,
                     cfg.highpass_m)
    return seed, {'rows': rows, 'drive_errors_m': drive_errors, 'map_errors': map_errors,
                  'drives_refused': {f'{e:g}': n for e, n in refused.items()},
                  'road_detail_rms_m': float(np.sqrt(np.mean(truth ** 2)))}


def _mean(values: Sequence[float]) -> Dict[str, float]:
    v = np.asarray(values, dtype=float)
    return {'mean': float(v.mean()), 'std': float(v.std(ddof=1)) if v.size > 1 else 0.0}


def aggregate(per_seed: Sequence[Dict], cfg: StudyConfig) -> Dict:
    """Return mean ± std of every variant and the shares of the oracle's gain."""
    by_key: Dict[str, List[Dict]] = {}
    meta: Dict[str, Dict] = {}
    for result in per_seed:
        for row in result['rows']:
            by_key.setdefault(row['key'], []).append(row)
            meta[row['key']] = row['variant']
    table = {}
    for key, rows in by_key.items():
        m = {k: _mean([r['metrics'][k] for r in rows])
             for k in ('acc_rms_continuous', 'acc_2norm', 'power_w')}
        if 'road_error_m' in rows[0]:
            m['road_error_m'] = _mean([r['road_error_m'] for r in rows])
        if 'preview' in rows[0]:
            m['preview'] = {k: float(np.mean([r['preview'][k] for r in rows]))
                            for k in rows[0]['preview']}
        table[key] = {'variant': meta[key], **m}

    def get(name, alpha, speed, n=0, e=0.0, delay=False):
        return table.get(Variant(name, alpha, speed, n, e, delay).key())

    def share(row, alpha, speed, delay=False, measure='acc_rms_continuous'):
        o = get('oracle', alpha, speed, delay=delay)
        np_ = get('no_preview', alpha, speed, delay=delay)
        if row is None or o is None or np_ is None:
            return None
        if alpha[1] > 0 and alpha[0] == 0:
            gain = o['power_w']['mean'] - np_['power_w']['mean']
            return 100 * (row['power_w']['mean'] - np_['power_w']['mean']) / gain if gain else None
        gain = np_[measure]['mean'] - o[measure]['mean']
        return 100 * (np_[measure]['mean'] - row[measure]['mean']) / gain if gain else None

    for key, row in table.items():
        v = row['variant']
        base_delay = v['delay']
        row['share_pct'] = share(row, tuple(v['alpha']), v['speed'], False)
        row['share_pct_sampled'] = share(row, tuple(v['alpha']), v['speed'], False, 'acc_2norm')
        row['share_pct_own_delay'] = share(row, tuple(v['alpha']), v['speed'], base_delay)
    goal = {}
    for alpha, target in (((1.0, 0.0), 80.0), ((0.0, 1.0), 70.0)):
        row = get('map', alpha, cfg.map_speed, cfg.goal_drives, cfg.goal_odometry_m, True)
        if row is not None:
            goal[f'{alpha[0]:g},{alpha[1]:g}'] = {'share_pct': row['share_pct'],
                                                  'target_pct': target,
                                                  'met': (row['share_pct'] or 0) >= target}
    refused = {}
    for r in per_seed:
        for e, n in r.get('drives_refused', {}).items():
            refused[e] = refused.get(e, 0) + n
    return {'rows': table, 'goal': goal, 'drives_refused': refused,
            'drive_error_m': _mean([e for r in per_seed for e in r['drive_errors_m']]),
            'road_detail_rms_m': _mean([r['road_detail_rms_m'] for r in per_seed]),
            'map_errors': {k: {q: _mean([r['map_errors'][k][q] for r in per_seed])
                               for q in ('rms_m', 'predicted_std_m', 'variance_scale')}
                           for k in per_seed[0]['map_errors']}}


def default_config(**overrides) -> StudyConfig:
    """Return the study's configuration with ``overrides`` (None values ignored)."""
    return replace(StudyConfig(), **{k: v for k, v in overrides.items() if v is not None})


__all__ = ['FIRST_SEED', 'StudyConfig', 'Variant', 'variants', 'run_seed', 'aggregate',
           'default_config']
