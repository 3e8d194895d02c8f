"""Property tests of clipping and resampling against shapely and plain geometry."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.geometry import Range, clip_polylines, resample_polylines

# shapely warns on the degenerate (zero-length) lines that hypothesis generates on purpose
pytestmark = pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")

BOX = (-15.0, 15.0, -30.0, 30.0)
coord = st.floats(-50, 50, allow_nan=False).map(lambda v: round(v, 3))
polyline = st.lists(st.tuples(coord, coord), min_size=2, max_size=12).map(lambda p: np.array(p, np.float64))


def clip(lines):
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in lines])])
    return clip_polylines(np.concatenate(lines), offsets, *BOX)


@settings(max_examples=300, deadline=None)
@given(st.lists(polyline, min_size=1, max_size=5))
def test_clip_matches_shapely(lines):
    points, offsets, line_of, has_start, has_end = clip(lines)
    x, y = points[:, 0], points[:, 1]
    assert (x >= BOX[0]).all() and (x <= BOX[1]).all() and (y >= BOX[2]).all() and (y <= BOX[3]).all()
    box = shapely.box(BOX[0], BOX[2], BOX[1], BOX[3])
    for i, line in enumerate(lines):
        mine = [points[offsets[k] : offsets[k + 1]] for k in np.flatnonzero(line_of == i)]
        length = sum(np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in mine)
        if np.linalg.norm(np.diff(line, axis=0), axis=1).sum() == 0:
            assert not mine
            continue
        # segment by segment: shapely merges the parts of a line that run over themselves
        segments = shapely.linestrings(np.stack([line[:-1], line[1:]], 1))
        expected = shapely.length(shapely.intersection(segments, box)).sum()
        assert abs(length - expected) < 1e-6 * max(1.0, expected)
        for p in mine:  # pieces keep the driving direction: they run forwards along the line
            assert (np.linalg.norm(np.diff(p, axis=0), axis=1) > 0).all()
            if not shapely.LineString(line).is_simple or shapely.LineString(line).is_closed:
                continue
            along = [shapely.LineString(line).project(shapely.Point(q)) for q in p]
            assert all(b >= a - 1e-6 for a, b in zip(along, along[1:]))
        inside = lambda q: BOX[0] <= q[0] <= BOX[1] and BOX[2] <= q[1] <= BOX[3]  # noqa: E731
        if mine:
            first, last = np.flatnonzero(line_of == i)[[0, -1]]
            assert has_start[first] == (inside(line[0]) and (mine[0][0] == line[0]).all())
            assert has_end[last] == (inside(line[-1]) and (mine[-1][-1] == line[-1]).all())


def test_clip_lane_that_leaves_and_reenters():
    s_bend = np.array([[0.0, -25], [0, -10], [25, -5], [25, 5], [0, 10], [0, 25]])
    points, offsets, line_of, has_start, has_end = clip([s_bend])
    assert len(offsets) == 3  # two pieces
    assert has_start.tolist() == [True, False] and has_end.tolist() == [False, True]
    np.testing.assert_allclose(points[offsets[1] - 1], [15, -7])
    np.testing.assert_allclose(points[offsets[1]], [15, 7])


@settings(max_examples=200, deadline=None)
@given(polyline, st.sampled_from([2, 10, 20, 30, 40]))
def test_resample_is_even_and_on_the_line(line, n):
    if np.linalg.norm(np.diff(line, axis=0), axis=1).sum() == 0:
        return
    out, lengths = resample_polylines(line, np.array([0, len(line)]), n)
    out = out[0]
    geometry = shapely.LineString(line)
    assert abs(lengths[0] - geometry.length) < 1e-6 * max(1, geometry.length)
    np.testing.assert_array_equal(out[0], line[0])
    np.testing.assert_array_equal(out[-1], line[-1])
    along = np.array([geometry.project(shapely.Point(p)) for p in out])
    distance = np.array([geometry.distance(shapely.Point(p)) for p in out])
    assert (distance < 1e-6).all()
    # evenly spaced by arc length (projection is exact for lines that do not cross themselves)
    if geometry.is_simple and not geometry.is_closed:
        tolerance = 1e-6 * max(1, geometry.length)
        np.testing.assert_allclose(along, np.linspace(0, geometry.length, n), atol=tolerance)


def test_range_parse():
    assert Range.parse("30x60") == Range(-15, 15, -30, 30)
    assert Range.parse("50x100") == Range(-25, 25, -50, 50)
    assert Range.parse("50x100").text == "50x100"
