import numpy as np
import pytest

from bpp.benchmarks.draw.dataset import (
    PRESETS,
    episode_paths,
    generate,
    render_episode,
    render_last_observation,
)
from bpp.benchmarks.draw.env import DrawEnv
from bpp.drawing.drawing import task_drawing
from bpp.drawing.geometry import BOARD_SIZE, MAX_BOARD_ANGLE


def test_store_contents(debug_store):
    s = debug_store
    assert s.benchmark == "drawanything"
    assert (s.num_tasks, s.num_episodes) == (12, 36)
    assert set(s.keys) == {
        "state",
        "action",
        "agent_pos",
        "pen_down",
        "board_pose",
        "cursor_on_board",
        "action_on_board",
        "ink_length",
    }
    assert s["state"].dtype == np.float64 and s["action"].dtype == np.float32
    for key in ("action", "agent_pos", "pen_down", "board_pose"):
        assert key in s.stats and len(s.stats[key]["mean"]) == s[key].shape[1]
    angles = s.column("board_angle")
    assert np.all(np.abs(angles) <= MAX_BOARD_ANGLE)
    for episodes in s.task_episodes():
        assert len(episodes) == 3
        # Stratified: the demos of a task are at clearly different rotations.
        assert np.diff(np.sort(angles[episodes])).min() > 0.0
        assert len(np.unique(np.floor((angles[episodes] + MAX_BOARD_ANGLE) / (2 * MAX_BOARD_ANGLE / 3)))) == 3
    assert s.tasks[0]["info"]["source"] == "procedural" and s.tasks[0]["info"]["parts"]
    assert task_drawing(s, 3).id == s.tasks[3]["id"]


def test_generation_is_independent_of_worker_count(debug_store, tmp_path):
    other = generate(PRESETS["debug"], tmp_path / "two.zarr", workers=2, progress=False)
    for key in debug_store.keys:
        np.testing.assert_array_equal(debug_store.array(key), other.array(key))
    np.testing.assert_array_equal(debug_store.column("board_angle"), other.column("board_angle"))


def test_images_are_exactly_reproducible_from_the_store(debug_store):
    """Datasets store no images: replaying the stored low-dimensional steps gives the env's frames bit for bit."""
    for episode in (0, 17):
        ep = debug_store.episode(episode)
        angle = float(debug_store.column("board_angle")[episode])
        frames = render_episode(debug_store, episode, 64)
        env = DrawEnv(image_size=64, early_stop=False)
        obs, _ = env.reset(options={"board_angle": angle, "cursor": ep["state"][0, :2]})
        for t, action in enumerate(ep["action"]):
            np.testing.assert_array_equal(obs["image"], frames[t])
            np.testing.assert_array_equal(obs["agent_pos"], ep["agent_pos"][t])
            np.testing.assert_array_equal(obs["pen_down"], ep["pen_down"][t])
            np.testing.assert_array_equal(obs["board_pose"], ep["board_pose"][t])
            np.testing.assert_array_equal(obs["cursor_on_board"], ep["cursor_on_board"][t])
            np.testing.assert_array_equal(obs["ink_length"], ep["ink_length"][t])
            obs, *_ = env.step(action)
        assert len(episode_paths(debug_store, episode)) == len(env.paths)
        # The ink length grows only while the pen is down, and ends at the drawn length of the stored paths.
        assert np.all(np.diff(ep["ink_length"][:, 0]) >= 0) and ep["ink_length"][0, 0] == 0
        drawn = sum(np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in episode_paths(debug_store, episode))
        assert obs["ink_length"][0] == pytest.approx(drawn / BOARD_SIZE, rel=0.05)


def test_the_last_observation_renders_alone_exactly(debug_store):
    for episode in (0, 9, 35):
        for size in (32, 96):
            np.testing.assert_array_equal(
                render_last_observation(debug_store, episode, size), render_episode(debug_store, episode, size)[-1]
            )


@pytest.mark.slow
def test_human_evaluation_set(tmp_path):
    s = generate(PRESETS["human"], tmp_path / "human.zarr", workers=1, progress=False)
    assert s.num_tasks >= 50 and s.num_episodes == 5 * s.num_tasks
    assert all(t["id"].startswith("hershey-") for t in s.tasks)
    lengths = np.diff(np.concatenate([[0], s.episode_ends]))
    assert lengths.max() <= 400
