"""The preview from the map: alignment by profile matching, anchoring, fallbacks counted."""

import numpy as np
import pytest

from erva_ros.core.roadmap import MapError
from erva_ros.core.roadmap.preview import MapPreview, MapPreviewSettings
from erva_ros.core.roadmap.profile import highpass
from erva_ros.core.roadmap.store import MapProfile
from erva_ros.core.roadmap.vehicle import Route
from erva_ros.core.road.profiles import make_road

import road_helpers as rh

GRID, HP, TS, V = 0.1, 6.0, 0.02, 20.0


def _map(rt, start=10.0, end=140.0, gap=None):
    s = np.arange(start, end + 1e-9, GRID)
    h = highpass(rt.height(s), GRID, HP)
    info = np.full(s.size, 1e8)                 # 0.1 mm std per node
    if gap is not None:
        info[(s >= gap[0]) & (s <= gap[1])] = 0.0
    return MapProfile('r', GRID, HP, int(round(start / GRID)), info, h * info,
                      (info > 0).astype(int))


def _drive(mp, rt, odo_offset, n, start=20.0, drift=1e-3, points=11, settings=None):
    """Drive at V from ``start``; odometry reads ``odo_offset`` m too far; ŵ drifts."""
    p = MapPreview(mp, TS, settings or MapPreviewSettings())
    out = []
    for k in range(n):
        s = start + V * TS * k
        w_hat = rt.height(s) + drift * k * TS + 0.5        # the estimator's frame: offset
        res = p.step(s + odo_offset, V, w_hat, 1e-9, points)
        x = s + V * TS * np.arange(points)
        expect = w_hat + rt.height(x) - rt.height(s) + drift * TS * np.arange(points)
        out.append((res, expect))
    return p, out


def test_alignment_finds_the_odometry_error_and_the_preview_follows_the_road():
    rt = rh.route(0)
    mp = _map(rt)
    p, out = _drive(mp, rt, 0.7, 150)
    assert p.aligned and p.offset == pytest.approx(-0.7, abs=0.05)
    assert p.counts.alignments >= 25 and p.counts.alignments_refused == 0
    assert p.counts.fallback_points == 0
    late = [(r, e) for r, e in out[60:]]
    err = np.concatenate([r.heights - e for r, e in late])
    # The road's detail is 0.8 mm RMS; 0.7 m off, the preview would be ~0.3 mm wrong.
    assert np.sqrt(np.mean(err ** 2)) < 0.06e-3
    r = late[-1][0]
    assert r.variance[0] == pytest.approx(1e-9) and np.all(r.variance[1:] > 1e-9)
    assert 0.9 < r.correlation <= 1.0 and r.offset_std_m < 0.2
    # Without the alignment (a search too narrow to reach it) the same drive is worse.
    _, bad = _drive(mp, rt, 0.7, 150, settings=MapPreviewSettings(search_m=0.2, track_m=0.2))
    err_bad = np.concatenate([r.heights - e for r, e in bad[60:]])
    assert np.sqrt(np.mean(err_bad ** 2)) > 3 * np.sqrt(np.mean(err ** 2))


def test_points_off_the_map_fall_back_to_no_preview_and_are_counted():
    rt = rh.route(0)
    mp = _map(rt, start=10.0, end=60.0, gap=(40.0, 41.0))
    p, out = _drive(mp, rt, 0.0, 120, start=12.0)
    c = p.counts
    assert c.gap_points > 0 and c.beyond_end_points > 0 and c.before_start_points == 0
    assert c.position_off_map_samples > 0
    assert c.unmatched_points == 0
    assert c.fallback_points == c.gap_points + c.beyond_end_points + c.before_start_points
    for r, _ in out:
        assert np.all(np.isfinite(r.heights))
        fallback = ~np.isfinite(r.variance)
        assert fallback.sum() == r.fallback_points
        assert np.all(r.heights[fallback] == r.heights[0])       # ŵ_k held
    # A vehicle before the map's start: every point of those samples falls back.
    p, out = _drive(mp, rt, -5.0, 7, start=12.0)          # odometry 7.0 .. 9.4 m
    assert p.counts.before_start_points == 7 * 11 and p.counts.position_off_map_samples == 7


def test_a_map_of_another_route_never_matches_and_falls_back():
    # ISO 8608 roads: two seeds share nothing.  (Two seeds of the paper road share its
    # sine: 10 m windows of them correlate 0.8-0.9; `erva run` refuses such a map by its
    # route name before anything starts.)
    iso = [Route.of(make_road('iso8608', 12.0, seed=s, road_class='B')) for s in (0, 5)]
    mp = _map(iso[1])
    p, out = _drive(mp, iso[0], 0.0, 150)
    c = p.counts
    assert c.alignments == 0 and c.alignments_refused > 0
    # Until max_unmatched_m (20 m: 50 samples of 0.4 m) the odometry position is used,
    # then nothing: the samples after the 51st.
    assert c.unmatched_samples == 150 - 51 and c.unmatched_points == 99 * 11
    assert c.fallback_points == c.unmatched_points
    assert all(np.all(r.heights == r.heights[0]) for r, _ in out[51:])


def test_variance_weighting_shrinks_uncertain_points_towards_no_preview():
    rt = rh.route(0)
    mp = _map(rt)
    mp.info[:] = 1e5
    mp.info_height[:] = mp.info * highpass(rt.height(mp.s), GRID, HP)
    plain = MapPreview(mp, TS, MapPreviewSettings(slope=False))
    weighted = MapPreview(mp, TS, MapPreviewSettings(slope=False, weighting='variance'))
    a = plain.step(50.0, V, 0.0, 0.0, 11)
    b = weighted.step(50.0, V, 0.0, 0.0, 11)
    # 3 mm std per node against a road of 0.8 mm: the increments shrink, none grows.
    assert np.all(np.abs(b.heights[1:]) < np.abs(a.heights[1:]))
    assert b.heights[0] == a.heights[0] == 0.0


def test_settings_are_checked():
    with pytest.raises(MapError, match='weighting'):
        MapPreviewSettings(weighting='maybe')
    with pytest.raises(MapError, match='window_m'):
        MapPreviewSettings(window_m=0.0)
    empty = MapProfile('r', GRID, HP, 0, np.zeros(5), np.zeros(5), np.zeros(5, dtype=int))
    with pytest.raises(MapError, match='empty'):
        MapPreview(empty, TS)


def test_a_session_checks_the_map_before_it_starts():
    mp = _map(rh.route(0), start=10.0, end=60.0, gap=(40.0, 41.0))
    mp.route = 'paper:seed=0@20m/s'
    mp.check_covers('paper:seed=0@20m/s', 14.0, 30.0)
    for route, lo, hi, needle in (
            ('paper:seed=5@20m/s', 14.0, 30.0, "drives 'paper:seed=5@20m/s'"),
            ('', 5.0, 30.0, 'the map covers 10.0..60.0 m, the session needs 2.0..33.0 m'),
            ('', 14.0, 80.0, 'needs 11.0..83.0 m'),
            ('', 14.0, 50.0, r'gap at 40\.\d\.\.41\.0 m')):
        with pytest.raises(MapError, match=needle):
            mp.check_covers(route, lo, hi)
