import numpy as np
import pytest

from bpp.drawing.geometry import canvas_to_upright, unit_to_canvas
from bpp.drawing.metric import EMPTY_DISTANCE, _segment_band, chamfer_distance, ink_mask, pen_band
from bpp.drawing.raster import centers, polyline_segments


def _line(y):
    return np.array([[x, y] for x in range(156, 357, 10)], float)


def _circle(r):
    th = np.deg2rad(np.arange(0, 360))
    return np.round(np.stack([256 + r * np.cos(th), 256 + r * np.sin(th)], 1))


def test_parity_with_authors_metric():
    # Values measured with the authors' implementation (docs/drawanything.md, "Parity with the authors' metric").
    assert chamfer_distance(ink_mask([_line(256)]), ink_mask([_line(266)])) == pytest.approx(9.18, abs=0.02)
    assert chamfer_distance(ink_mask([_circle(100)]), ink_mask([_circle(110)])) == pytest.approx(9.69, abs=0.03)


@pytest.mark.parametrize("angle", [0.0, 0.3, -0.7, np.pi / 4])
def test_identical_drawings_score_zero_at_any_angle(angle, rng):
    stroke = np.cumsum(rng.normal(0, 0.02, (80, 2)), axis=0) + 0.5
    target = ink_mask([unit_to_canvas(stroke, 0.0)])
    rollout = ink_mask([canvas_to_upright(unit_to_canvas(stroke, angle), angle)])
    assert chamfer_distance(target, rollout) == 0.0


def test_thin_line_shift_gives_shift_in_each_direction():
    a = np.zeros((512, 512), bool)
    b = np.zeros((512, 512), bool)
    a[200, 100:400] = True
    b[207, 100:400] = True
    # The score is a sum of the two directions, so a shift of d scores 2d.
    assert chamfer_distance(a, b) == pytest.approx(14.0)
    assert chamfer_distance(a, b) == chamfer_distance(b, a)


def test_empty_canvases_are_defined():
    ink = ink_mask([_line(256)])
    empty = np.zeros_like(ink)
    assert chamfer_distance(ink, empty) == EMPTY_DISTANCE
    assert chamfer_distance(empty, ink) == EMPTY_DISTANCE
    assert chamfer_distance(empty, empty) == 0.0


def test_cropping_does_not_change_the_score(rng):
    # The implementation crops to the joint bounding box; compare with brute force on a small case.
    a = rng.random((64, 64)) > 0.97
    b = rng.random((64, 64)) > 0.97
    pa, pb = np.argwhere(a), np.argwhere(b)
    d = np.linalg.norm(pa[:, None] - pb[None], axis=-1)
    assert chamfer_distance(a, b) == pytest.approx(d.min(1).mean() + d.min(0).mean())


def test_incremental_tracker_matches_direct_computation(rng):
    from bpp.drawing.metric import ChamferTracker, InkMask

    target = ink_mask([_circle(80)])
    tracker = ChamferTracker(target)
    assert tracker.score() == EMPTY_DISTANCE
    ink = InkMask()
    walk = np.cumsum(rng.normal(0, 6, (60, 2)), axis=0) + 256
    for a, b in zip(walk[:-1], walk[1:], strict=True):
        score = tracker.add(ink.add(np.stack([a, b])))
        assert score == pytest.approx(chamfer_distance(target, ink.mask), rel=1e-9)


@pytest.mark.parametrize("start", [(150.0, 150.0), (256.0, 300.0), (400.0, 120.0)])
def test_the_best_score_found_by_bisection_is_the_lowest_after_any_addition(start, rng):
    """Scored only when asked, the tracker finds exactly the lowest of the scores it would have given after every
    addition, computing the rollout's distance field for fewer additions than there are; a walk that passes the
    target and goes on has its best score in the middle."""
    from bpp.drawing.metric import ChamferTracker, InkMask

    target = ink_mask([_circle(60), _line(330)])
    every, lazy, ink, patches = ChamferTracker(target), ChamferTracker(target), InkMask(), InkMask()
    walk = np.cumsum(rng.normal(0, 7, (120, 2)), axis=0) + start
    scores = [every.score()]
    for a, b in zip(walk[:-1], walk[1:], strict=True):
        stamp, painted = ink.add(np.stack([a, b])), patches.paint(np.stack([a, b]))
        if stamp is not None:
            scores.append(every.add(stamp))
            lazy.book(painted[1], painted[0])  # the patch of the canvas the segment may ink, not the whole canvas
    assert lazy.best() == min(scores) and lazy.score() == scores[-1]
    assert len(lazy.coverage) < len(lazy.to_target_means) == len(every.coverage)
    assert lazy.score() == pytest.approx(chamfer_distance(target, ink.mask), rel=1e-9)


def test_an_empty_target_or_rollout_scores_as_documented():
    from bpp.drawing.metric import ChamferTracker

    nothing, dot = np.zeros((64, 64), bool), np.zeros((64, 64), bool)
    dot[30, 30] = True
    assert ChamferTracker(nothing).best() == 0.0 and ChamferTracker(dot).best() == EMPTY_DISTANCE
    blank = ChamferTracker(nothing)
    blank.book(dot)
    assert (blank.score(), blank.best()) == (EMPTY_DISTANCE, 0.0)


def test_each_segment_inks_only_within_its_reach(rng):
    """The pen's band is tested per segment near the segment only, or for an env step's few segments together; over
    the whole canvas it inks exactly the same pixels (a dense sub-pixel path, as a simulator records, one env step of
    it, long segments at every slope, short ones in every direction with a point repeated)."""
    dense = np.cumsum(rng.normal(0, 0.4, (600, 2)), axis=0) + 256
    long = rng.uniform(-20, 530, (12, 2))
    turns = np.array([[100.0, 100.0], [103.5, 101.2], [103.5, 101.2], [101.1, 106.7], [96.3, 104.0], [99.0, 97.25]])
    x = centers(512)
    for path in (dense, dense[:11], long, turns, np.array([[100.0, 100.0], [100.0, 100.0]])):
        segments = polyline_segments(path)
        everywhere = np.zeros((512, 512), bool)
        for segment in segments:
            everywhere |= _segment_band(x[None, :], x[:, None], segment[None])
        assert np.array_equal(pen_band(x, x, segments), everywhere)
        assert everywhere.any()
