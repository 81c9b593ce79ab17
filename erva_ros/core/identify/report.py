"""What `erva identify` prints and writes: the parameter table, the params file, JSON.

The params file has the layout of ``config/erva_paper.yaml`` (a ROS 2 params file with
every physical parameter in ``/**``), so every node (``--params-file``), `erva sim
--params` and `erva run --params` take it as it is; the comments say, per parameter,
the 95 % interval or why it kept its prior value.
"""

from typing import Dict, List, Sequence

from erva_ros.core.identify.fit import FitResult, UNITS
from erva_ros.core.settings.erva import ERVA_SPECS


def _num(v: float) -> str:
    return f'{v:.6g}'


def _yaml_float(v: float) -> str:
    """Return ``v`` exactly, always read back as a float (YAML 1.1 wants 1.0e+20, not 1e+20)."""
    text = repr(float(v))
    mantissa, _, exponent = text.partition('e')
    if exponent and '.' not in mantissa:
        text = f'{mantissa}.0e{exponent}'
    return text


def _pct(v) -> str:
    return '-' if v is None else f'{100 * v:.2g} %' if v < 0.1 else f'{100 * v:.0f} %'


def as_dict(result: FitResult, sources: Sequence[str] = ()) -> Dict:
    """Return the result as plain data (the --json output)."""
    return {
        'sources': list(sources),
        'parameters': [{
            'name': p.name, 'unit': ERVA_SPECS[p.name].unit, 'prior': p.prior, 'value': p.value,
            'free': p.free, 'rel_std': p.rel_std, 'rel_std_data': p.rel_std_data,
            'ci95': list(p.ci95) if p.ci95 else None, 'reason': p.reason or None,
            'rel_std_by_channel': p.by_channel or None,
            **({'truth': p.truth} if p.truth is not None else {})}
            for p in result.parameters],
        'free': result.free(), 'fixed': result.fixed(),
        'channels': list(result.channels),
        'units': {c: UNITS[c] for c in result.channels},
        'sigma': result.sigma, 'residual_lag1': result.residual_lag1,
        'fit_pct': result.fit_pct, 'heldout_fit_pct': result.heldout_fit_pct or None,
        'heldout_prior_fit_pct': result.heldout_prior_fit_pct or None,
        'iterations': result.iterations, 'segments': result.segments,
        'fit_samples': result.fit_samples, 'heldout_samples': result.heldout_samples,
        'condition': result.condition, 'substeps': result.substeps, 'notes': result.notes,
        'params': result.params.as_dict(),
    }


def table(result: FitResult) -> str:
    """Return the human-readable report: parameters, signals, fit."""
    ch = list(result.channels)
    lines = ['parameter  unit    prior        estimate     95 % interval            '
             'rel. sd   ' + '  '.join(f'{c[:15]:>15s}' for c in ch)]
    for p in result.parameters:
        unit = ERVA_SPECS[p.name].unit
        if p.free:
            ci = f'[{_num(p.ci95[0])}, {_num(p.ci95[1])}]'
            by = '  '.join(f'{_pct(p.by_channel.get(c)):>15s}' for c in ch)
            lines.append(f'{p.name:10s} {unit:7s} {_num(p.prior):12s} {_num(p.value):12s} '
                         f'{ci:24s} {_pct(p.rel_std):>8s}  {by}')
        else:
            lines.append(f'{p.name:10s} {unit:7s} {_num(p.prior):12s} {"fixed":12s} {p.reason}')
    lines.append('(rel. sd: with the ±20 % prior spread of the undetermined fixed parameters; '
                 'per signal: what that signal alone would determine, every other free '
                 'parameter estimated too; - = not determined by it alone)')
    lines.append(f'fit: {result.fit_samples} samples in {result.segments} segments, '
                 f'{result.iterations} iterations, condition {result.condition:.3g}')
    lines.append('residual RMS (noise) per signal: ' + ', '.join(
        f'{c} {result.sigma[c]:.3g} {UNITS[c]}' for c in ch))
    lines.append('residual lag-1 autocorrelation: ' + ', '.join(
        f'{c} {result.residual_lag1[c]:+.2f}' for c in ch))
    lines.append('fit (normalised RMS, %) on the fitted data: ' + ', '.join(
        f'{c} {result.fit_pct[c]:.1f}' for c in ch))
    if result.heldout_fit_pct:
        lines.append(f'held-out fit ({result.heldout_samples} samples), identified / prior '
                     f'model: ' + ', '.join(
                         f'{c} {result.heldout_fit_pct[c]:.1f} / '
                         f'{result.heldout_prior_fit_pct[c]:.1f}' for c in ch))
    lines += [f'note: {n}' for n in result.notes]
    return '\n'.join(lines)


def params_yaml(result: FitResult, sources: Sequence[str] = ()) -> str:
    """Return the params file (module doc)."""
    lines: List[str] = [
        '# ERVA quarter car: physical parameters identified by `erva identify` (SI units).',
        '# A ROS 2 parameter file like config/erva_paper.yaml: nodes take it with',
        '# --params-file, `erva sim` and `erva run` with --params.']
    if sources:
        lines.append('# From: ' + ', '.join(sources))
    if result.heldout_fit_pct:
        lines.append('# Held-out fit (normalised RMS, %), identified / prior: ' + ', '.join(
            f'{c} {result.heldout_fit_pct[c]:.1f} / {result.heldout_prior_fit_pct[c]:.1f}'
            for c in result.channels))
    lines += ['/**:', '  ros__parameters:']
    for p in result.parameters:
        unit = ERVA_SPECS[p.name].unit
        if p.free:
            note = (f'identified, 95 % [{_num(p.ci95[0])}, {_num(p.ci95[1])}], '
                    f'prior {_num(p.prior)}')
        else:
            note = f'prior (fixed: {p.reason})'
        lines.append(f'{"    " + p.name + ": " + _yaml_float(p.value):<30s}  # {unit}, {note}')
    return '\n'.join(lines) + '\n'


__all__ = ['as_dict', 'table', 'params_yaml']
