"""The scenario of a live run as plain Python: the road and the preview error model.

Built from the live parameters (config/live.yaml, :mod:`erva_ros.ros.parameters`) by
road_preview_node, by `erva run` to validate before any process starts, and by the
tests that compare a lock-step run with the offline closed loop, so all three build
exactly the same seeded road.
"""

import os
from typing import Any, Mapping

import numpy as np

from erva_ros.core.params import ParamError
from erva_ros.core.preview import PreviewErrorModel
from erva_ros.core.roads import make_road, Road, RoadError


def load_road_file(path: str) -> np.ndarray:
    """Return the (n, 2) rows time (s), height (m) of a CSV road file; one-line errors."""
    if not os.path.isfile(path):
        raise ParamError(f'road_file {path!r} does not exist')
    try:
        with open(path, 'rb') as fh:
            raw = fh.read()
    except OSError as exc:
        raise ParamError(f'road_file {path!r} cannot be read ({exc.strerror or exc})') from None
    try:
        if b'\x00' in raw:
            raise UnicodeDecodeError('utf-8', raw, raw.index(b'\x00'), raw.index(b'\x00') + 1,
                                     'NUL byte')
        lines = raw.decode('utf-8').splitlines()
    except UnicodeDecodeError as exc:
        raise ParamError(f'road_file {path!r} is not a UTF-8 text CSV (byte {exc.start}: '
                         f'{exc.reason})') from None
    rows = []
    for lineno, line in enumerate(lines, 1):
        text = line.split('#', 1)[0].strip()
        if not text:
            continue
        cells = [c.strip() for c in text.replace(';', ',').split(',')]
        try:
            row = [float(cells[0]), float(cells[1])]
        except (ValueError, IndexError):
            if rows:  # only a header line may be non-numeric
                raise ParamError(f'road_file {path}:{lineno}: expected "time_s, height_m",'
                                 f' got {text[:60]!r}') from None
            continue
        if not np.all(np.isfinite(row)):
            raise ParamError(f'road_file {path}:{lineno}: {text[:60]!r} is not a finite '
                             f'"time_s, height_m" row')
        rows.append(row)
    if len(rows) < 2:
        raise ParamError(f'road_file {path!r} needs at least two "time_s, height_m" rows')
    return np.asarray(rows, dtype=float)


def build_road(cfg: Mapping[str, Any]) -> Road:
    """Return the road of the live parameters ``cfg`` (road, seed, duration_s, ...)."""
    kind = 'recorded' if cfg.get('road_file') else cfg['road']
    opts = {'speed_mps': cfg['speed_mps']}
    if kind == 'iso8608':
        opts['road_class'] = cfg['road_class']
    elif kind == 'bump':
        opts.update(height_m=cfg['bump_height_m'], length_m=cfg['bump_length_m'],
                    start_s=cfg['bump_start_s'])
    elif kind == 'recorded':
        rows = load_road_file(cfg['road_file'])
        opts.update(times=rows[:, 0], heights=rows[:, 1],
                    name=os.path.basename(cfg['road_file']))
    try:
        return make_road(kind, cfg['duration_s'], cfg['ts'], int(cfg['seed']), **opts)
    except RoadError as exc:
        raise ParamError(str(exc)) from None


#: The preview noise is seeded with seed + this, as `erva sim` does (commands/
#: _closed_loop_options.py), so the road noise and the preview noise are independent.
PREVIEW_SEED_OFFSET = 7919


def build_preview_model(cfg: Mapping[str, Any]) -> PreviewErrorModel:
    """Return the preview error model of the live parameters (perfect unless configured)."""
    snr = float(cfg['preview_snr_db']) if cfg['preview_noise'] else None
    return PreviewErrorModel(snr, float(cfg['preview_delay_s']),
                             int(cfg['seed']) + PREVIEW_SEED_OFFSET, float(cfg['ts']))


def required_preview_steps(settings) -> int:
    """Return the preview intervals the controller needs (its horizon in samples)."""
    if settings.controller == 'preview_long':
        m = int(round(settings.long_step_s / settings.ts))
        return settings.horizon + m * settings.long_steps
    return settings.horizon


__all__ = ['PREVIEW_SEED_OFFSET', 'load_road_file', 'build_road', 'build_preview_model',
           'required_preview_steps']
