"""RoadBuffer (w(t) from received road samples) and KnownRoad (the session's road on the grid)."""

import math

import pytest

from erva_ros.core.hil.road_buffer import KnownRoad, RoadBuffer
from erva_ros.core.road.profiles import make_road

TS_NS = 20_000_000
ORIGIN = 1_700_000_000_000_000_000          # epoch ns of sample 0


def test_road_buffer_before_and_on_its_samples():
    buf = RoadBuffer(max_extrapolation_s=0.02)
    assert len(buf) == 0 and buf.latest is None
    assert buf.height(5.0) == 0.0 and buf.height(5.0, default=0.1) == 0.1
    assert buf.add(1.0, 0.01)
    # One sample: held everywhere (no slope to extrapolate with).
    assert buf.height(0.5) == buf.height(1.0) == buf.height(2.0) == 0.01
    assert buf.add(1.02, 0.03) and buf.add(1.05, -0.03)      # unequal spacing
    assert len(buf) == 3 and buf.latest == (1.05, -0.03)
    assert [buf.height(t) for t in (1.0, 1.02, 1.05)] == [0.01, 0.03, -0.03]   # exact
    assert buf.height(0.9) == 0.01                           # before the first: held


def test_road_buffer_is_linear_between_samples():
    buf = RoadBuffer()
    for t, w in ((0.0, 0.0), (0.02, 0.004), (0.04, -0.002), (0.06, 0.0)):
        buf.add(t, w)
    assert buf.height(0.005) == pytest.approx(0.001, abs=1e-15)
    assert buf.height(0.03) == pytest.approx(0.001, abs=1e-15)
    assert buf.height(0.055) == pytest.approx(-0.0005, abs=1e-15)


def test_road_buffer_extrapolates_one_period_then_holds():
    # A stalled road source never makes a runaway height.
    buf = RoadBuffer(max_extrapolation_s=0.02)
    buf.add(0.0, 0.0)
    buf.add(0.02, 0.002)                                     # slope 0.1 m/s
    assert buf.height(0.03) == pytest.approx(0.003, abs=1e-15)
    assert buf.height(0.04) == pytest.approx(0.004, abs=1e-15)
    assert buf.height(0.05) == buf.height(10.0) == pytest.approx(0.004, abs=1e-15)
    held = RoadBuffer(max_extrapolation_s=0.0)
    held.add(0.0, 0.0)
    held.add(0.02, 0.002)
    assert held.height(0.5) == 0.002


def test_road_buffer_refuses_repeated_and_older_samples_and_keeps_the_newest():
    buf = RoadBuffer(size=3)
    assert buf.add(0.0, 0.0) and buf.add(0.02, 0.001)
    assert not buf.add(0.02, 0.5) and not buf.add(0.01, 0.5)  # repeated, out of order
    assert buf.rejected == 2 and buf.latest == (0.02, 0.001)
    for k in (2, 3, 4):
        buf.add(0.02 * k, 0.001 * k)
    assert len(buf) == 3                                     # the oldest went
    assert buf.height(0.0) == pytest.approx(0.002)           # held at the oldest kept
    assert buf.height(0.07) == pytest.approx(0.0035)
    assert not buf.add(math.nan, 0.0) and not buf.add(1.0, math.inf)
    assert buf.rejected == 4 and buf.latest == (0.08, 0.004)


def test_known_road_samples_the_road_as_the_road_node_does():
    road = make_road('paper', 4.0, ts=0.02, seed=3)
    known = KnownRoad(road.height, road.speed_mps, 0.02)
    assert [known.sample(k) for k in range(60)] == [road.height(k * 0.02) for k in range(60)]
    assert known.sample(-3) == road.height(0.0)              # before the start: sample 0
    # The cache is bounded and refilled: values stay exact after it was cleared.
    values = [known.sample(k) for k in range(5000)]
    assert values[4500] == road.height(4500 * 0.02) and known.sample(7) == road.height(0.14)
    assert len(known._cache) <= 4097


def test_known_road_is_anchored_by_the_first_message_distance():
    road = make_road('paper', 4.0, ts=0.02, seed=3)
    known = KnownRoad(road.height, road.speed_mps, 0.02)
    with pytest.raises(RuntimeError, match='anchor'):
        known.height(ORIGIN * 1e-9)
    with pytest.raises(RuntimeError, match='anchor'):
        known.check(ORIGIN, 0.0)
    assert known.checked == 0
    # The first message the ECU sees is sample 12 (it started late): the grid's origin
    # is 12 periods before its stamp.
    known.anchor(ORIGIN + 12 * TS_NS, road.distance(12 * 0.02))
    assert known.origin_ns == ORIGIN
    assert known.check(ORIGIN + 13 * TS_NS, road.height(13 * 0.02))
    standing = KnownRoad(road.height, 0.0, 0.02)             # no speed: the first is sample 0
    standing.anchor(ORIGIN + 12 * TS_NS, 0.0)
    assert standing.origin_ns == ORIGIN + 12 * TS_NS


def test_known_road_counts_a_different_road_or_a_shifted_grid():
    road = make_road('paper', 4.0, ts=0.02, seed=3)
    other = make_road('paper', 4.0, ts=0.02, seed=4)
    known = KnownRoad(road.height, road.speed_mps, 0.02)
    known.anchor(ORIGIN, 0.0)
    assert known.check(ORIGIN + 20 * TS_NS, road.height(0.4))
    assert not known.check(ORIGIN + 20 * TS_NS, other.height(0.4))          # another road
    assert not known.check(ORIGIN + 20 * TS_NS + 1, road.height(0.4))       # off the grid
    assert not known.check(ORIGIN + 21 * TS_NS, road.height(0.4))           # a sample late
    assert known.check(ORIGIN + 21 * TS_NS, road.height(0.42) + 5e-10)      # within 1 nm
    assert (known.checked, known.mismatches) == (5, 3)


def test_known_road_height_between_and_on_the_grid():
    road = make_road('paper', 4.0, ts=0.02, seed=3)
    known = KnownRoad(road.height, road.speed_mps, 0.02)
    known.anchor(ORIGIN, 0.0)
    t10 = (ORIGIN + 10 * TS_NS) * 1e-9
    assert known.height(t10) == road.height(0.2)             # on the grid: exact
    # Epoch seconds as floats are 0.24 us coarse, and sums of them a few ulps off: on the
    # grid within GRID_SNAP of a period (2 us at Ts = 20 ms), the exact sample.
    assert known.height(t10 + 1e-8) == road.height(0.2)
    assert known.height(t10 + 5e-7) == road.height(0.2)       # two ulps late
    assert known.height(t10 - 5e-7) == road.height(0.2)
    w10, w11 = road.height(0.2), road.height(0.22)
    assert known.height(t10 + 0.005) == pytest.approx(w10 + 0.25 * (w11 - w10), abs=1e-8)
    assert known.height(t10 + 0.015) == pytest.approx(w10 + 0.75 * (w11 - w10), abs=1e-8)
