"""What a wrong model or a degraded input costs the NMPC: one factor at a time.

The plant is the nominal device (the params file); the NMPC is the same controller with
one thing wrong -- the paper names "sensitivity analysis of NMPC" as its own future work:

* a **parameter mismatch**: the NMPC's model has parameter p × (1 + δ), δ = ±10, ±20 %
  (each of the equations-of-motion parameters; c_e0 is a command value, not a property
  of the device);
* **preview error**: Gaussian noise at an SNR (dB) on the preview beyond its first point,
  or a preview that is late by a delay (s) (:class:`erva_ros.core.road.preview.PreviewErrorModel`);
* an **unmodelled command delay**: each command acts that long after its sample, and the
  NMPC does not know it (its ``command_delay_s`` stays 0).

Each run is a job: (factor, level, weighting, road seed) -> J = α1·acc² − α2·P_avg and its
two terms, with the comfort the NMPC minimises (continuous ∫z̈_s² dt for the continuous
cost, sampled at t_k for the paper's).  A factor's row gives, per level, the change of J
against the nominal run in per cent of |J_nominal| (positive = worse), averaged over the
seeds, and of the comfort and the power.
"""

from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from erva_ros.core.controllers import make_controller
from erva_ros.core.identify.fit import PARAMETERS
from erva_ros.core.metrics import evaluation_objective
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.road.preview import PreviewErrorModel
from erva_ros.core.road.profiles import make_road
from erva_ros.core.studies.closed_loop import simulate_closed_loop

#: Factors besides the parameters, with their default levels and units.
INPUT_FACTORS = {
    'preview_snr': ((20.0, 10.0), 'dB'),
    'preview_delay': ((0.02, 0.04), 's'),
    'command_delay': ((0.006, 0.012), 's'),
}
#: Default relative parameter mismatches (%).
DEFAULT_LEVELS = (-20.0, -10.0, 10.0, 20.0)
FACTORS = PARAMETERS + tuple(INPUT_FACTORS)


@dataclass(frozen=True)
class Run:
    """One closed-loop run of the study: what is wrong, how much, at which weighting."""

    factor: str              # '' for the nominal run
    level: float             # % for a parameter, dB or s otherwise
    alpha: Tuple[float, float]
    seed: int


def run_one(job) -> Dict:
    """Run the NMPC with ``run``'s error on the nominal plant; return J and its terms."""
    params, settings, run, duration, road_kind = job
    s = settings.with_(alpha1=run.alpha[0], alpha2=run.alpha[1])
    believed, preview, delay = params, None, 0.0
    if run.factor in PARAMETERS:
        believed = params.with_(**{run.factor: getattr(params, run.factor)
                                   * (1 + run.level / 100)})
    elif run.factor == 'preview_snr':
        preview = PreviewErrorModel(snr_db=run.level, seed=run.seed, ts=s.ts)
    elif run.factor == 'preview_delay':
        preview = PreviewErrorModel(delay_s=run.level, seed=run.seed, ts=s.ts)
    elif run.factor == 'command_delay':
        delay = run.level
    road = make_road(road_kind, duration, seed=run.seed)
    # The plant is the true device; the NMPC's model, the believed one.
    res = simulate_closed_loop(make_model(params),
                               make_controller(s.controller, make_model(believed), s), road,
                               duration, s.ts, preview_model=preview, actuation_delay_s=delay)
    m = res.metrics
    comfort = m['acc_rms_continuous'] if s.cost == 'continuous' else m['acc_rms']
    return {'factor': run.factor, 'level': run.level, 'alpha': list(run.alpha),
            'seed': run.seed, 'comfort': comfort, 'power_w': m['power_w'],
            'J': evaluation_objective(dict(m, acc_rms=comfort), run.alpha)}


def plan(factors: Sequence[str], levels: Sequence[float],
         input_levels: Dict[str, Sequence[float]], weights, seeds) -> List[Run]:
    """Return every run: the nominal one and each (factor, level), per weighting and seed."""
    runs = []
    for alpha in weights:
        for seed in seeds:
            runs.append(Run('', 0.0, tuple(alpha), seed))
            for f in factors:
                for lv in (levels if f in PARAMETERS else input_levels[f]):
                    runs.append(Run(f, float(lv), tuple(alpha), seed))
    return runs


def table(results: Sequence[Dict]) -> List[Dict]:
    """Return one row per (weighting, factor): per level ΔJ %, Δcomfort %, Δpower % (mean)."""
    by_key: Dict[Tuple, List[Dict]] = {}
    for r in results:
        by_key.setdefault((tuple(r['alpha']), r['factor'], r['level']), []).append(r)
    nominal = {}
    for (alpha, factor, _), rs in by_key.items():
        if factor == '':
            nominal[alpha] = {k: float(np.mean([r[k] for r in rs]))
                              for k in ('J', 'comfort', 'power_w')}
    rows: Dict[Tuple, Dict] = {}
    for (alpha, factor, level), rs in sorted(by_key.items(), key=lambda kv: kv[0][2]):
        if factor == '':
            continue
        nom = nominal[alpha]
        mean = {k: float(np.mean([r[k] for r in rs])) for k in ('J', 'comfort', 'power_w')}
        row = rows.setdefault((alpha, factor), {'weights': list(alpha), 'factor': factor,
                                                'nominal': nom, 'levels': []})
        row['levels'].append({
            'level': level, **mean,
            'dJ_pct': 100 * (mean['J'] - nom['J']) / abs(nom['J']) if nom['J'] else None,
            'dcomfort_pct': 100 * (mean['comfort'] / nom['comfort'] - 1),
            'dpower_pct': 100 * (mean['power_w'] / nom['power_w'] - 1)
            if nom['power_w'] else None})
    out = list(rows.values())
    for row in out:
        row['swing_pct'] = max(abs(lv['dJ_pct']) for lv in row['levels']
                               if lv['dJ_pct'] is not None)
    order = {f: i for i, f in enumerate(FACTORS)}
    first = {}
    for r in results:
        first.setdefault(tuple(r['alpha']), len(first))
    out.sort(key=lambda r: (first[tuple(r['weights'])], order.get(r['factor'], 99)))
    return out


def unit(factor: str) -> str:
    """Return the unit of a factor's levels."""
    return '%' if factor in PARAMETERS else INPUT_FACTORS[factor][1]


def markdown(rows: Sequence[Dict], header: Optional[str] = None) -> str:
    """Return the table: one row per factor, ΔJ (Δcomfort / Δpower) % per level."""
    lines = [header] if header else []
    for alpha in dict.fromkeys(tuple(r['weights']) for r in rows):
        mine = [r for r in rows if tuple(r['weights']) == alpha]
        nom = mine[0]['nominal']
        lines += ['', f'(α1, α2) = ({alpha[0]:g}, {alpha[1]:g}): nominal J {nom["J"]:.5g}, '
                  f'comfort {nom["comfort"]:.4g} m/s², power {nom["power_w"]:.4g} W', '',
                  '| factor | levels | ΔJ % per level (Δcomfort % / Δpower %) | largest |ΔJ| % |',
                  '|---|---|---|---|']
        for r in sorted(mine, key=lambda r: -r['swing_pct']):
            cells = '; '.join(
                f'{v["level"]:+g}: {v["dJ_pct"]:+.2f} ({v["dcomfort_pct"]:+.2f} / '
                f'{v["dpower_pct"]:+.2f})' if r['factor'] in PARAMETERS else
                f'{v["level"]:g}: {v["dJ_pct"]:+.2f} ({v["dcomfort_pct"]:+.2f} / '
                f'{v["dpower_pct"]:+.2f})' for v in r['levels'])
            lines.append(f'| {r["factor"]} | {unit(r["factor"])} | {cells} | '
                         f'{r["swing_pct"]:.2f} |')
    return '\n'.join(lines) + '\n'


__all__ = ['INPUT_FACTORS', 'DEFAULT_LEVELS', 'FACTORS', 'Run', 'run_one', 'plan', 'table',
           'markdown', 'unit']
