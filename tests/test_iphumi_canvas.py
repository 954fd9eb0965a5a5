"""Drawings recorded with an iPhUMI phone on DrawAnything-Real's marked canvas: the phone's main camera measures the
canvas, processing writes the pen in the canvas's frame, and the result becomes demonstrations of the simulated arm's
benchmark, with the keys, ink and goal photos of the arm's own."""

from __future__ import annotations

import numpy as np
import pytest

from bpp.core.poses import invert, rotation_angle, vector_to_pose
from helpers import import_optional

pytestmark = [pytest.mark.iphumi, pytest.mark.slow]  # a synthetic export and its processing
import_optional("cv2", "iphumi")

from bpp.benchmarks.iphumi import synthetic  # noqa: E402
from bpp.benchmarks.iphumi.synthetic import SyntheticSettings, write_export  # noqa: E402
from bpp.cli import main  # noqa: E402
from bpp.data.store import EpisodeStore  # noqa: E402
from bpp.drawing.drawing import task_drawing  # noqa: E402
from bpp.drawing.marked_canvas import drawing_to_canvas  # noqa: E402

SEED = 5


@pytest.fixture(scope="module")
def canvas_export(tmp_path_factory):
    """One demonstration of two drawings on the marked canvas, the phone held above it as each starts, and its store
    processed with --canvas at the arm's 20 Hz (one episode a drawing); the gripper calibrations are cached in a
    folder of this module's own."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("BPP_CACHE", str(tmp_path_factory.mktemp("cache")))
        out = tmp_path_factory.mktemp("iphumi-canvas")
        truths = write_export(out / "export", SyntheticSettings(1, 2, 2, canvas=True, main_size=(320, 240), seed=SEED))
        main(["iphumi", "process", str(out / "export"), "--canvas", "--fps", "20", "--out", str(out / "phone.zarr"),
              "--workers", "1"])  # fmt: skip
        yield next(iter(truths.values())), EpisodeStore(out / "phone.zarr")


def test_a_drawing_is_written_in_the_frame_of_the_canvas_the_phone_measured(canvas_export):
    truth, store = canvas_export
    assert store.num_episodes == 2
    for episode in range(store.num_episodes):
        steps = store.episode(episode, ["pose", "canvas_pose", "tip_in_canvas"])
        start = truth.times[0] + float(store.column("start_s")[episode])
        tcp, _ = truth.motion(start + np.arange(len(steps["pose"])) / 20)
        expected = invert(truth.canvas) @ tcp
        tip = vector_to_pose(steps["tip_in_canvas"].astype(np.float64))
        error_mm = np.linalg.norm(tip[:, :3, 3] - expected[:, :3, 3], axis=1) * 1e3
        assert np.median(error_mm) < 2.0 and error_mm.max() < 5.0, (np.median(error_mm), error_mm.max())
        assert rotation_angle(tip[:, :3, :3], expected[:, :3, :3]).max() < np.deg2rad(1.0)
        # the pen touches the canvas (z = 0) while drawing, after the look at it from above
        assert np.abs(steps["tip_in_canvas"][:, 2]).min() < 0.002 and steps["tip_in_canvas"][0, 2] > 0.3
        # the canvas is one pose, in the frame of the episode's poses
        canvas = vector_to_pose(steps["canvas_pose"].astype(np.float64))
        np.testing.assert_allclose(canvas, canvas[:1].repeat(len(canvas), 0), atol=1e-6)
        np.testing.assert_allclose(invert(canvas) @ vector_to_pose(steps["pose"].astype(np.float64)), tip, atol=1e-4)


@pytest.mark.libero
def test_processed_drawings_become_the_arm_s_demonstrations_with_its_keys_and_their_own_ink(canvas_export, tmp_path):
    from bpp.benchmarks.draw3d.benchmark import BENCHMARK  # MuJoCo: the libero extra
    from bpp.benchmarks.draw3d.demonstrator import ink_chamfer

    converted = tmp_path / "draw3d.zarr"
    main(["draw3d", "from-iphumi", str(canvas_export[1].path), "--out", str(converted), "--goal-size", "32"])
    store = EpisodeStore(converted)
    assert store.benchmark == "draw3d" and store.num_tasks == 2 and store.num_episodes == 2
    assert set(store.keys) == {"tip_pose", "tip_in_canvas", "target_in_canvas", "canvas_pose", "ink_length",
                               "pen_down", "action"}  # fmt: skip
    for episode in range(store.num_episodes):
        steps = store.episode(episode, ["tip_in_canvas", "target_in_canvas", "pen_down", "ink_length"])
        down = steps["pen_down"][:, 0] > 0.5
        assert steps["tip_in_canvas"][0, 2] <= 0.15 and down.any() and not down[0]  # the look at the canvas is cut
        # the ink drawn so far only grows, by the pen's moves while it touches
        assert np.all(np.diff(steps["ink_length"][:, 0]) >= 0) and steps["ink_length"][-1, 0] > 0.1
        # each target is the next pose, pressed 1 mm into the canvas where the pen is down there
        np.testing.assert_allclose(steps["target_in_canvas"][:-1, :2], steps["tip_in_canvas"][1:, :2], atol=1e-6)
        pressed = steps["tip_in_canvas"][1:, 2] - steps["target_in_canvas"][:-1, 2]
        np.testing.assert_allclose(pressed, np.where(down[1:], 0.001, 0.0), atol=1e-6)
        # the task's drawing is its own ink: the ink is at 0 px from it; the goal photo shows a dark line on the canvas
        assert float(store.column("chamfer")[episode]) < 1.0
        assert store.column("goal_scene")[episode].shape == (32, 32, 3)
    picture = BENCHMARK.prompt_picture(store, 0, 64)
    assert picture.min() < 100 and picture.max() > 200  # ink on paper
    # each task's drawing is the synthetic drawing the phone traced, up to the measurement (DrawAnything px)
    for task in range(store.num_tasks):
        _, traced = synthetic.task_drawing(int(store.tasks[task]["id"].rsplit("-", 1)[-1]), SEED)  # "draw task N"
        ink = [drawing_to_canvas(s) for s in task_drawing(store, task).strokes]
        assert ink_chamfer(ink, traced.strokes) < 2.0
