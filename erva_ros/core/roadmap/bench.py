"""``erva map bench``: how a map's cost grows with a fleet -- writers, a rebuild, a fetch.

**The drives.**  A route of L km (the paper road of one seed, by distance: the road model
of every study here).  One survey drive over the whole route defines the map's distance
axis; then N drives of D km each start at seeded positions along it, with the odometry
error of :class:`~erva_ros.core.roadmap.vehicle.OdometryError` (bias, scale) and the
estimator's error: each drive's detail is the route's true detail (high-passed as the map
is) at its true positions plus Gaussian noise of the smoothed road estimate's error, and
reports the estimator's variance.  Both numbers come from the project's road estimator:
:func:`calibrate` runs the RoadEKF and its RTS smoother over a simulated drive of the
route (ECU sensors at the shipped noise) and measures them.  Synthetic, so that 1,000
drives cost seconds to make, not the estimator's minutes; the map sees what it would see.

**What is timed.**  :func:`run_writers`: the N drives added by W processes at once (each
drive one transaction, :meth:`RoadMap.add_drives`), after a barrier: drives/s over the
wall time, and per drive the whole add and its write transaction (waiting for the lock,
the sums, the commit).  :func:`rebuild_jobs`: the whole map again from the drives and
their stored registrations, as independent jobs (local processes or Dask) and one bulk
write.  :func:`time_fetch`: a route section into a local cache (what a vehicle does
before a drive).
"""

from dataclasses import dataclass
import math
import multiprocessing
import os
import threading
import time
from typing import Dict, Sequence, Tuple

import numpy as np

from erva_ros.core.controllers import ControllerSettings, make_controller
from erva_ros.core.model.params import paper_params
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.road.profiles import make_road
from erva_ros.core.roadmap import MapError
from erva_ros.core.roadmap.drive import estimate_drive, grid_profile, GridProfile
from erva_ros.core.roadmap.profile import gaussian_lowpass, highpass
from erva_ros.core.roadmap.store import DriveItem, RoadMap

SPEED_MPS = 20.0


@dataclass(frozen=True)
class Fleet:
    """The synthetic fleet: route, drives, the estimator's error (module doc)."""

    route_km: float = 20.0
    drives: int = 1000
    drive_km: float = 1.0
    seed: int = 0
    grid_m: float = 0.1
    highpass_m: float = 6.0
    error_std_m: float = 2e-4     # the smoothed estimate's detail error (calibrate)
    var_m2: float = 4e-8          # the variance the estimator reports (calibrate)
    bias_m: float = 1.0           # odometry bias, ± (seeded sign and size)
    scale: float = 0.003          # odometry scale error, ±

    @property
    def route_name(self) -> str:
        return f'paper:seed={self.seed}@{SPEED_MPS:g}m/s, {self.route_km:g} km'


_TRUTH: Dict[Tuple, Tuple[np.ndarray, np.ndarray]] = {}


def truth(fleet: Fleet) -> Tuple[np.ndarray, np.ndarray]:
    """Return the route's true detail on a fine grid (x, h), cached per process."""
    key = (fleet.route_km, fleet.seed, fleet.highpass_m)
    if key not in _TRUTH:
        road = make_road('paper', fleet.route_km * 1e3 / SPEED_MPS + 2.0, seed=fleet.seed,
                         speed_mps=SPEED_MPS)
        x = road.times * SPEED_MPS
        step = 0.05
        xs = np.arange(0.0, x[-1], step)
        _TRUTH[key] = xs, highpass(np.interp(xs, x, road.heights), step, fleet.highpass_m)
    return _TRUTH[key]


def calibrate(seed: int = 0, seconds: float = 8.0) -> Tuple[float, float]:
    """Return (detail error std, mean reported variance) of the road estimator on the route.

    A passive drive of ``seconds`` on the paper road of ``seed`` with the ECU's sensors,
    the RoadEKF and its RTS smoother (core/roadmap/drive.py), against the true detail,
    18 m (3 high-pass σ) from either end.
    """
    from erva_ros.core.roadmap.vehicle import Route, simulate_vehicle

    model = make_model(paper_params())
    route = Route.of(make_road('paper', seconds + 5, seed=seed, speed_mps=SPEED_MPS))
    passive = make_controller('passive', model, ControllerSettings())
    run = simulate_vehicle(model, passive, route.drive(SPEED_MPS), seconds, sensor_seed=7)
    g = grid_profile(estimate_drive(run.record('calibration', route.name, SPEED_MPS), model),
                     0.1, 6.0)
    true = highpass(route.height(g.s), 0.1, 6.0)
    # Away from the drive's ends by 3 high-pass σ: there the finite high-pass bends both.
    ok = np.isfinite(g.h) & (g.s > g.s[0] + 18.0) & (g.s < g.s[-1] - 18.0)
    return float(np.std(g.h[ok] - true[ok])), float(np.mean(g.var[ok]))


def survey(fleet: Fleet) -> GridProfile:
    """Return the survey drive: the whole route, no odometry error (defines the axis)."""
    return _drive(fleet, 0.0, fleet.route_km * 1e3, 0.0, 0.0, np.random.default_rng(
        [fleet.seed, 10 ** 6]))


def drive(fleet: Fleet, k: int) -> GridProfile:
    """Return drive ``k`` of the fleet (seeded: the same on every machine and worker)."""
    rng = np.random.default_rng([fleet.seed, k])
    length = fleet.drive_km * 1e3
    start = rng.uniform(30.0, fleet.route_km * 1e3 - length - 30.0)
    return _drive(fleet, start, length, rng.uniform(-1, 1) * fleet.bias_m,
                  rng.uniform(-1, 1) * fleet.scale, rng)


def _drive(fleet: Fleet, start: float, length: float, bias: float, scale: float,
           rng) -> GridProfile:
    xs, hs = truth(fleet)
    g = fleet.grid_m
    first = int(math.ceil((start + bias) / g))
    last = int(math.floor((start + bias + (1 + scale) * length) / g))
    odo = np.arange(first, last + 1) * g
    true_s = start + (odo - start - bias) / (1 + scale)
    noise = gaussian_lowpass(rng.standard_normal(odo.size), g, 0.3)
    noise *= fleet.error_std_m / max(float(np.std(noise)), 1e-300)
    h = np.interp(true_s, xs, hs) + noise
    return GridProfile(first, h, np.full(odo.size, fleet.var_m2), g)


def digest(fleet: Fleet, k: int) -> str:
    """Return the digest of drive ``k`` (the survey is -1)."""
    return f'bench-{fleet.seed}-{fleet.route_km:g}-{fleet.drive_km:g}-{k}'


# -- writers ------------------------------------------------------------------------------
def _writer(fleet: Fleet, location, ks: Sequence[int], barrier, results) -> None:
    """Add drives ``ks`` to the map, one transaction each, after the barrier; their times."""
    try:
        items = [DriveItem(drive(fleet, k), digest(fleet, k), f'drive {k}',
                           f'writer {os.getpid()}', search_m=3.0) for k in ks]
        out = []
        with RoadMap.open(location) as m:
            barrier.wait()
            for it in items:
                t = {}
                t0 = time.perf_counter()
                m.add_drives([it], timing=t)
                t['add'] = time.perf_counter() - t0
                out.append(t)
        results.put(out)
    except BaseException as exc:            # the parent reports it, in one line
        barrier.abort()
        results.put(f'{type(exc).__name__}: {exc}')


def run_writers(fleet: Fleet, location, writers: int) -> Dict:
    """Add the fleet's N drives with ``writers`` processes at once; return the figures."""
    ctx = multiprocessing.get_context('fork')
    barrier, results = ctx.Barrier(writers + 1), ctx.Queue()
    procs = [ctx.Process(target=_writer, args=(
        fleet, location, list(range(w, fleet.drives, writers)), barrier, results))
        for w in range(writers)]
    for p in procs:
        p.start()
    try:
        barrier.wait()
    except threading.BrokenBarrierError:
        pass
    t0 = time.perf_counter()
    per = [results.get() for _ in procs]
    wall = time.perf_counter() - t0
    for p in procs:
        p.join()
    failed = [r for r in per if isinstance(r, str)]
    if failed:
        raise MapError(f'map bench: a writer failed: {failed[0]}')
    rows = [r for w in per for r in w]
    return {'writers': writers, 'drives': len(rows), 'wall_s': wall,
            'drives_per_s': len(rows) / wall, 'add_s': stats([r['add'] for r in rows]),
            'write_s': stats([r['write'] for r in rows]),
            'registered_again': int(sum(r['again'] for r in rows)),
            'retries': int(sum(r['retries'] for r in rows))}


def stats(values: Sequence[float]) -> Dict:
    """Return p50 / p99 / max and the sample count of ``values``."""
    v = np.asarray(values, dtype=float)
    return {'p50': float(np.percentile(v, 50)), 'p99': float(np.percentile(v, 99)),
            'max': float(v.max()), 'samples': int(v.size)}


# -- rebuild ------------------------------------------------------------------------------
def rebuild_job(job) -> Tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """Return the node sums (first node, Σ 1/v, Σ h/v, count) of the drives in ``job``.

    ``job`` = (fleet, [(k, offset_m, scale, origin_m), ...]): each drive made again and
    placed with its stored registration, as the incremental adds placed it.
    """
    fleet, regs = job
    n = int(round(fleet.route_km * 1e3 / fleet.grid_m)) + 400
    lo = -200
    info, ih, cnt = np.zeros(n), np.zeros(n), np.zeros(n, dtype=np.int64)
    for k, off, sc, org in regs:
        g = survey(fleet) if k < 0 else drive(fleet, k)
        if k >= 0:
            g = g.shifted(off, sc, org)
        ok = np.isfinite(g.h) & (g.var > 0)
        idx = g.nodes[ok] - lo
        np.add.at(info, idx, 1.0 / g.var[ok])
        np.add.at(ih, idx, g.h[ok] / g.var[ok])
        np.add.at(cnt, idx, 1)
    return lo, info, ih, cnt


__all__ = ['Fleet', 'calibrate', 'survey', 'drive', 'digest', 'run_writers', 'stats',
           'rebuild_job', 'truth']
