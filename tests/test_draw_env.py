import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import bpp.benchmarks  # noqa: F401  (registers the environments)
from bpp.benchmarks.draw.demonstrator import demonstrate
from bpp.benchmarks.draw.env import ENV_ID as DRAW_ENV_ID
from bpp.benchmarks.draw.env import DrawEnv
from bpp.benchmarks.draw.render import CURSOR_RGB, SceneRenderer
from bpp.drawing.geometry import canvas_to_upright, unit_to_canvas
from bpp.drawing.human import glyph_drawing


@pytest.mark.filterwarnings("ignore:.*symmetric and normalized space")
@pytest.mark.parametrize("image_size", [None, 64])
def test_gymnasium_env_checker(image_size):
    env = gym.make(DRAW_ENV_ID, image_size=image_size)
    check_env(env.unwrapped, skip_render_check=True)


def test_observation_layout_and_seeding():
    env = DrawEnv(image_size=96)
    obs1, info1 = env.reset(seed=3)
    obs2, info2 = env.reset(seed=3)
    assert obs1["image"].shape == (96, 96, 3) and obs1["image"].dtype == np.uint8
    assert set(obs1) == {"image", "agent_pos", "pen_down", "board_pose", "cursor_on_board", "ink_length"}
    assert info1["board_angle"] == info2["board_angle"]
    for k in obs1:
        np.testing.assert_array_equal(obs1[k], obs2[k])
    assert abs(info1["board_angle"]) <= np.pi / 4
    np.testing.assert_allclose(
        obs1["board_pose"], [np.cos(info1["board_angle"]), np.sin(info1["board_angle"])], rtol=1e-6
    )
    assert obs1["agent_pos"].min() >= 50 and obs1["agent_pos"].max() <= 450
    assert obs1["pen_down"][0] == 0.0


def test_image_rendered_directly_at_each_resolution():
    for size in (64, 96, 224):
        env = DrawEnv(image_size=size)
        obs, _ = env.reset(seed=0, options={"board_angle": 0.0, "cursor": (256.0, 256.0)})
        image = obs["image"]
        assert image.shape == (size, size, 3)
        # The cursor is drawn where it is: the centre pixel is cursor green.
        np.testing.assert_array_equal(image[size // 2, size // 2], CURSOR_RGB)
        # The upright board's top edge (y = 81 px on the canvas) is red.
        rows = slice(int(77 * size / 512), int(86 * size / 512) + 1)
        red = image[rows, :, 0].astype(int) - image[rows, :, 1].astype(int) > 100
        assert red.any(axis=0).sum() > size // 2
        assert not (image[size // 2 + 5 :, :, 0].astype(int) - image[size // 2 + 5 :, :, 1] > 100).any()


def test_pen_inks_and_ink_is_split_invariant():
    env = DrawEnv(image_size=96)
    env.reset(seed=0, options={"board_angle": 0.2, "cursor": (150.0, 150.0)})
    blank = env.renderers["image"].canvas.copy()
    for target in [(300, 150), (300, 300), (150, 300)]:
        env.step(np.array([*target, 1.0]))
    assert (env.renderers["image"].canvas != blank).any()
    # Adding the same ink path all at once gives a bit-identical image (ink coverage is a max over segments).
    whole = SceneRenderer(96, 0.2)
    whole.add_ink(np.concatenate([env.paths[0], *[p[1:] for p in env.paths[1:]]]))
    np.testing.assert_array_equal(whole.canvas, env.renderers["image"].canvas)


def test_pen_up_leaves_no_ink():
    env = DrawEnv(image_size=64)
    env.reset(seed=0)
    blank = env.renderers["image"].canvas.copy()
    for target in [(300, 150), (100, 400)]:
        env.step(np.array([*target, 0.0]))
    np.testing.assert_array_equal(env.renderers["image"].canvas, blank)


def test_early_stop_and_time_limit():
    env = DrawEnv(image_size=None, max_episode_steps=400)
    env.reset(seed=0, options={"cursor": (200.0, 200.0)})
    steps, terminated = 0, False
    while not terminated and steps < 100:
        _, _, terminated, truncated, _ = env.step(np.array([200.0, 200.0, 0.0]))
        steps += 1
    assert terminated and steps == 20  # still for the whole 20-step window
    env = DrawEnv(image_size=None, max_episode_steps=30, early_stop=False)
    env.reset(seed=0)
    for t in range(1, 31):
        _, _, terminated, truncated, _ = env.step(np.array([100.0 + 10 * t, 100.0, 0.0]))
    assert truncated and not terminated


def test_moving_cursor_is_not_stopped():
    env = DrawEnv(image_size=None)
    env.reset(seed=0, options={"cursor": (100.0, 256.0)})
    for t in range(60):
        x = 256 + 150 * np.cos(t / 5)
        y = 256 + 150 * np.sin(t / 5)
        _, _, terminated, _, _ = env.step(np.array([x, y, 1.0]))
        assert not terminated


def test_replaying_a_demo_reaches_zero_chamfer_against_its_own_ink(rng):
    drawing = glyph_drawing("futural", "S", "S")
    demo = demonstrate(drawing, 0.4, np.array([100.0, 400.0]), rng)
    env = DrawEnv(image_size=None)
    # Target: the demo's own ink, un-rotated (what the evaluator uses as the target for a prompt).
    live = DrawEnv(image_size=None, early_stop=False)
    live.reset(options={"board_angle": 0.4, "cursor": demo.states[0, :2]})
    for a in demo.actions:
        live.step(a)
    target = [canvas_to_upright(p, 0.4) for p in live.paths]
    env.reset(options={"board_angle": -0.3, "cursor": (256.0, 256.0), "target": target})
    assert env.chamfer > 100  # nothing drawn yet
    # Drawing the same upright ink on a differently rotated board scores exactly 0.
    env.reset(options={"board_angle": 0.4, "cursor": demo.states[0, :2], "target": target})
    for a in demo.actions:
        *_, info = env.step(a)
    assert info["chamfer"] == 0.0 and info["best_chamfer"] == 0.0


def test_scoring_only_at_the_end_gives_the_scores_of_every_step(rng):
    """An evaluation's env scores once, at the step that ends the episode: the same final and best score as an env
    that scores every step, and no score or reward before."""
    drawing = glyph_drawing("futural", "S", "S")
    target = [unit_to_canvas(s, 0.0) for s in drawing.strokes]
    demo = demonstrate(drawing, 0.0, np.array([100.0, 400.0]), rng)
    # The demonstration drawn, then scribbled over: the best score lies before the end.
    actions = [*demo.actions, *([450.0, 60.0, 1.0] + rng.normal(0, 30, (30, 3)) * [1, 1, 0])]
    every, once = (
        DrawEnv(image_size=None, early_stop=False),
        DrawEnv(image_size=None, early_stop=False, score_every_step=False),
    )
    for env in (every, once):
        env.max_episode_steps = len(actions)
        env.reset(options={"board_angle": 0.2, "cursor": demo.states[0, :2], "target": target})
    for i, a in enumerate(actions):
        *_, reward, _, truncated, info = every.step(a)
        *_, lazy_reward, _, lazy_truncated, lazy_info = once.step(a)
        assert truncated == lazy_truncated == (i == len(actions) - 1)
        if not truncated:
            assert lazy_reward == 0.0 and "chamfer" not in lazy_info
    assert (lazy_reward, lazy_info["chamfer"], lazy_info["best_chamfer"]) == (
        reward,
        info["chamfer"],
        info["best_chamfer"],
    )
    assert info["best_chamfer"] < info["chamfer"]


def test_bad_actions_and_options_are_refused():
    env = DrawEnv(image_size=None)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="3 finite numbers"):
        env.step(np.array([1.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="3 finite numbers"):
        env.step(np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="unknown reset options"):
        env.reset(options={"angle": 0.1})


def test_board_frame_actions_replay_the_demo_like_canvas_actions(debug_store):
    """A stored demo executed as board-frame actions (action_on_board) inks exactly what its canvas actions ink."""
    ep = debug_store.episode(3, ("state", "action", "action_on_board"))
    angle = float(debug_store.column("board_angle")[3])
    paths = {}
    for frame, key in (("canvas", "action"), ("board", "action_on_board")):
        env = DrawEnv(image_size=None, action_frame=frame)
        env.reset(options={"board_angle": angle, "cursor": ep["state"][0, :2]})
        for action in ep[key]:
            env.step(action)
        paths[frame] = np.concatenate(env.paths)
    np.testing.assert_allclose(paths["board"], paths["canvas"], atol=1e-3)
