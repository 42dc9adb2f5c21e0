"""kf_train.io.track: points onto a polyline, along-track s and signed cross-track d."""

from kf_train.io.track import (
    polyline_arc_lengths_m, polyline_segments, project_onto_polyline, project_onto_segments)
import numpy as np
import pytest

# An L: 100 m east, then 50 m north (a repeated vertex, which must change nothing).
L_SHAPE = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 0.0], [100.0, 50.0]])


def test_arc_lengths():
    """The arc length adds the segments' lengths (the repeated vertex adds 0)."""
    np.testing.assert_allclose(polyline_arc_lengths_m(L_SHAPE), [0.0, 100.0, 100.0, 150.0])


def test_feet_and_sides():
    """Known feet: s along the L, d positive to the left of travel."""
    points = np.array([[30.0, 4.0],     # left of the eastward leg
                       [30.0, -4.0],    # right of it
                       [103.0, 20.0],   # right of the northward leg (east of it)
                       [97.0, 20.0],    # left of it
                       [-5.0, 0.0],     # before the start: the start, 5 m away
                       [100.0, 60.0]])  # past the end: the end, 10 m away
    s, d = project_onto_polyline(points, L_SHAPE)
    np.testing.assert_allclose(s, [30.0, 30.0, 120.0, 120.0, 0.0, 150.0], atol=1e-12)
    np.testing.assert_allclose(np.abs(d), [4.0, 4.0, 3.0, 3.0, 5.0, 10.0], atol=1e-12)
    assert list(np.sign(d[:4])) == [1.0, -1.0, -1.0, 1.0]


def test_random_points_match_brute_force():
    """Seeded random points: |d| is the distance to a dense grid on the line; s is its foot."""
    rng = np.random.default_rng(24)
    angles = np.cumsum(rng.uniform(-0.6, 0.6, 30))
    vertices = np.cumsum(np.column_stack([np.cos(angles), np.sin(angles)]) * 40.0, axis=0)
    points = vertices[rng.integers(0, 30, 100)] + rng.normal(0.0, 15.0, (100, 2))
    s, d = project_onto_polyline(points, vertices)
    arc = polyline_arc_lengths_m(vertices)
    dense_s = np.linspace(0.0, arc[-1], 50_001)      # a ~2.4-cm grid on ~1.2 km

    def on_line(s_m):
        return np.column_stack([np.interp(s_m, arc, vertices[:, i]) for i in (0, 1)])

    dense = on_line(dense_s)
    nearest = np.hypot(points[:, None, 0] - dense[None, :, 0],
                       points[:, None, 1] - dense[None, :, 1]).min(axis=1)
    # The grid's nearest point is at most half a spacing from the true foot point.
    assert np.all(np.abs(d) <= nearest + 1e-9)
    assert np.all(np.abs(d) >= nearest - dense_s[1] / 2.0)
    # s names the foot point: the point on the line at s is |d| away.
    np.testing.assert_allclose(np.hypot(*(points - on_line(s)).T), np.abs(d), atol=1e-9)


def test_window_picks_the_copy_of_a_track_run_twice():
    """Out and back on one line: the window decides which pass a point belongs to."""
    there_and_back = np.array([[0.0, 0.0], [100.0, 0.0], [0.0, 0.0]])
    point = np.array([[60.0, 2.0]])
    s_out, d_out = project_onto_polyline(point, there_and_back, 0.0, 100.0)
    s_back, d_back = project_onto_polyline(point, there_and_back, 100.0, 200.0)
    assert s_out[0] == pytest.approx(60.0) and d_out[0] == pytest.approx(2.0)
    assert s_back[0] == pytest.approx(140.0) and d_back[0] == pytest.approx(-2.0)


def test_window_clamps_to_its_end():
    """A point beyond its window's end lands on the window's end."""
    s, d = project_onto_polyline(np.array([[80.0, 0.0]]), L_SHAPE, 0.0, 50.0)
    assert s[0] == pytest.approx(50.0) and d[0] == pytest.approx(30.0)


def test_bad_inputs():
    """Too few vertices and empty windows are refused."""
    with pytest.raises(ValueError):
        project_onto_polyline(np.zeros((1, 2)), np.array([[1.0, 1.0], [1.0, 1.0]]))
    with pytest.raises(ValueError):
        project_onto_polyline(np.zeros((1, 2)), L_SHAPE, 80.0, 20.0)


def test_some_segments_as_the_whole_line():
    """On the segments that may hold a point's nearest (a superset of them): the same bits."""
    rng = np.random.default_rng(26)
    angles = np.cumsum(rng.uniform(-0.6, 0.6, 30))
    vertices = np.cumsum(np.column_stack([np.cos(angles), np.sin(angles)]) * 40.0, axis=0)
    vertices = np.insert(vertices, 7, vertices[6], axis=0)      # a repeated vertex
    points = vertices[rng.integers(0, 30, 200)] + rng.normal(0.0, 30.0, (200, 2))
    s, d = project_onto_polyline(points, vertices)
    segments = polyline_segments(vertices)
    whole = project_onto_segments(points, segments)
    assert np.array_equal(whole[0], s) and np.array_equal(whole[1], d)
    each = np.abs(np.array([project_onto_segments(points, segments, [j])[1]
                            for j in range(segments.length.size)]))     # (M, N)
    for k, point in enumerate(points):
        index = np.flatnonzero(each[:, k] <= np.abs(d[k]) + rng.uniform(0.0, 50.0))
        some = project_onto_segments(point, segments, index)
        assert (some[0][0], some[1][0]) == (s[k], d[k])
