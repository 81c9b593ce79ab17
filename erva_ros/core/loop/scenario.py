"""The scenario of a live run as plain Python: the road and the preview error model.

Built from the live parameters (config/live.yaml, :mod:`erva_ros.ros.parameters`) by
road_preview_node, by `erva run` to validate before any process starts, and by the
tests that compare a lock-step run with the offline closed loop, so all three build
exactly the same seeded road.
"""

import os
from typing import Any, Mapping

import numpy as np

from erva_ros.core.model.params import ParamError
from erva_ros.core.road.preview import PreviewErrorModel
from erva_ros.core.road.profiles import make_road, read_road_csv, Road, RoadError


def load_road_file(path: str) -> np.ndarray:
    """Return the (n, 2) rows time (s), height (m) of a CSV road file; one-line ParamError."""
    try:
        return read_road_csv(path)
    except RoadError as exc:
        raise ParamError(str(exc)) from None


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
