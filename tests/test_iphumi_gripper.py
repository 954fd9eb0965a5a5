"""Gripper width from the ultrawide camera's finger tags: synthetic frames rendered by OpenCV at a known width are
detected back to within a millimetre, a synthetic calibration recovers the range, a hidden tag is predicted, and
demonstration widths are clipped, zeroed at closed and interpolated."""

from __future__ import annotations

import math

import numpy as np
import pytest

from helpers import import_optional

pytestmark = pytest.mark.iphumi
import_optional("cv2", "iphumi")

from bpp.benchmarks.iphumi.gripper import (  # noqa: E402
    TAG_IDS,
    GripperCalibration,
    calibrate,
    detect_fingers,
    finger_positions,
    render_fingers,
    tag_ids,
    width_from_tags,
    width_series,
)
from bpp.errors import UserError  # noqa: E402

K = np.array([[350.0, 0.0, 320.0], [0.0, 350.0, 240.0], [0.0, 0.0, 1.0]])  # a wide 640x480 ultrawide camera
GREY = 110  # render_fingers's default background
BLANK = np.full((480, 640, 3), GREY, np.uint8)
MIN_W, MAX_W = 0.03, 0.09


def hide(frame: np.ndarray, tag: int, width: float, side: str) -> np.ndarray:
    """`frame` with the tag `tag` painted over by the background."""
    centre = finger_positions(width, side)[tag]
    u, v = (K @ centre)[:2] / centre[2]
    out = frame.copy()
    out[max(int(v) - 45, 0) : int(v) + 46, max(int(u) - 45, 0) : int(u) + 46] = GREY
    return out


@pytest.fixture(scope="module")
def calibration() -> GripperCalibration:
    """From a synthetic calibration recording: 30 frames, opened and closed twice, with pose jitter and noise."""
    rng = np.random.default_rng(0)
    widths = MIN_W + (MAX_W - MIN_W) * (1 - np.cos(np.linspace(0, 4 * np.pi, 30))) / 2
    return calibrate((render_fingers(w, K, "right", rng=rng) for w in widths), K, "right")


def test_tag_ids_per_side():
    assert tag_ids("right") == (0, 1) and tag_ids("left") == (6, 7) and TAG_IDS["right"] == (0, 1)
    for side in ("head", "middle"):
        with pytest.raises(ValueError, match=side):
            tag_ids(side)


@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("jitter", [False, True])
def test_render_detect_round_trip_within_a_millimetre(side, jitter):
    rng = np.random.default_rng(1) if jitter else None
    errors = []
    for width in np.linspace(0.025, 0.09, 6):
        found = detect_fingers(render_fingers(width, K, side, rng=rng), K, side)
        assert sorted(found) == list(tag_ids(side))
        if not jitter:
            for tag, centre in finger_positions(width, side).items():
                assert np.linalg.norm(found[tag] - centre) < 0.002
        errors.append(width_from_tags(found, side) - width)
    assert np.max(np.abs(errors)) < 0.001, np.round(np.array(errors) * 1000, 3)


def test_other_sides_tags_and_bad_inputs():
    assert detect_fingers(render_fingers(0.05, K, "left"), K, "right") == {}
    assert detect_fingers(BLANK, K, "right") == {}
    assert math.isnan(width_from_tags({}, "right"))
    with pytest.raises(UserError, match="uint8"):
        detect_fingers(BLANK[..., 0], K, "right")
    with pytest.raises(UserError, match="intrinsics"):
        detect_fingers(BLANK, np.eye(2), "right")
    with pytest.raises(UserError, match="head"):
        detect_fingers(BLANK, K, "head")


def test_calibration_recovers_range_and_maps(calibration):
    assert calibration.side == "right" and calibration.n_frames == 30
    assert abs(calibration.min_width - MIN_W) < 0.001 and abs(calibration.max_width - MAX_W) < 0.001
    for a, b in (calibration.x1_from_x0, calibration.x0_from_x1):  # symmetric fingers: x1 = -x0
        assert abs(a) < 0.001 and abs(b + 1) < 0.05
    assert GripperCalibration.from_json(calibration.to_json()) == calibration


@pytest.mark.parametrize("hidden", [0, 1])
def test_hidden_tag_predicted_by_the_calibration_map(calibration, hidden):
    width = 0.062
    found = detect_fingers(hide(render_fingers(width, K, "right"), hidden, width, "right"), K, "right")
    assert sorted(found) == [1 - hidden]
    assert abs(width_from_tags(found, "right", calibration) - width) < 0.002
    assert math.isnan(width_from_tags(found, "right"))  # without a calibration one tag is not enough
    with pytest.raises(UserError, match="'right', not 'left'"):
        width_from_tags(found, "left", GripperCalibration("right", MIN_W, MAX_W, (0, -1), (0, -1), 5))


def test_width_series_clips_zeroes_and_fills_gaps():
    cal = GripperCalibration("right", MIN_W, MAX_W, (0.0, -1.0), (0.0, -1.0), 10)
    truth = [None, 0.05, None, None, 0.08, 0.1, 0.026, None]  # None: no tag in view
    frames = [BLANK if w is None else render_fingers(w, K, "right") for w in truth]
    frames[2] = hide(render_fingers(0.06, K, "right"), 0, 0.06, "right")  # one tag: the map gives 0.06
    series = width_series(frames, K, "right", cal)
    expected = [0.02, 0.02, 0.03, 0.04, 0.05, 0.06, 0.0, 0.0]
    assert series.shape == (8,) and series.dtype == np.float64
    assert np.max(np.abs(series - expected)) < 0.0015, np.round(series * 1000, 2)
    with pytest.raises(UserError, match="no gripper width"):
        width_series([BLANK, BLANK], K, "right", cal)


def test_calibrate_refuses_missing_tags_and_a_gripper_never_opened():
    with pytest.raises(UserError, match=r"only 0 frames show both finger tags 0 and 1"):
        calibrate([BLANK] * 12, K, "right")
    rng = np.random.default_rng(2)
    with pytest.raises(UserError, match="open and close the gripper"):
        calibrate([render_fingers(0.03, K, "left", rng=rng) for _ in range(12)], K, "left")


GOOD = {
    "side": "left",
    "min_width": 0.03,
    "max_width": 0.09,
    "x1_from_x0": [0, -1],
    "x0_from_x1": [0, -1],
    "n_frames": 9,
}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"side": "head"}, "head"),
        ({"min_width": 0.1}, "min_width < max_width"),
        ({"max_width": "wide"}, "max_width"),
        ({"min_width": float("nan")}, "min_width"),
        ({"x1_from_x0": [1.0]}, "x1_from_x0"),
        ({"x0_from_x1": [0, float("inf")]}, "x0_from_x1"),
        ({"n_frames": 0}, "n_frames"),
        ({"n_frames": True}, "n_frames"),
        ({"extra": 1}, r"unexpected \['extra'\]"),
        ({"side": None}, "None"),
    ],
)
def test_from_json_rejects_bad_input(change, message):
    assert GripperCalibration.from_json(GOOD).to_json() == GOOD
    with pytest.raises(UserError, match=message):
        GripperCalibration.from_json({**GOOD, **change})


def test_from_json_rejects_missing_fields_and_non_objects():
    with pytest.raises(UserError, match=r"missing \['n_frames'\]"):
        GripperCalibration.from_json({k: v for k, v in GOOD.items() if k != "n_frames"})
    with pytest.raises(UserError, match="JSON object"):
        GripperCalibration.from_json([GOOD])
