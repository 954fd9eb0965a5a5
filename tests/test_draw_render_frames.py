"""render_frames: only the wanted frames of a recorded episode, bit for bit those of a step-by-step replay."""

import numpy as np
import pytest

from bpp.benchmarks.draw import physics, render
from bpp.benchmarks.draw.dataset import render_episode, render_episode_steps
from bpp.benchmarks.draw.render import ink_segments, render_board, render_frames
from bpp.benchmarks.draw.viz import episode_frames
from bpp.drawing import raster
from bpp.drawing.geometry import CANVAS_SIZE, board_corners, unit_to_canvas
from bpp.drawing.raster import INK_WIDTH


def stored(store, episode: int):
    ep = store.episode(episode, ("state", "action"))
    return ep["state"], ep["action"].astype(np.float64), float(store.column("board_angle")[episode])


def rollout(start, actions) -> np.ndarray:
    """(T, 5) states of an episode started at `start` (the states an env would record)."""
    states = [np.asarray(start, dtype=np.float64)]
    for action in actions[:-1]:
        states.append(physics.control_step(states[-1], action)[0])
    return np.array(states)


def assert_matches_replay(states, actions, angle, size, rng, subset: int = 25):
    replay = np.stack(episode_frames(states, actions, angle, size))  # T + 1 frames: also the one after the end
    T = len(states)
    frames = render_frames(states, actions, angle, size, np.arange(T))
    assert frames.shape == (T, size, size, 3) and frames.dtype == np.uint8
    np.testing.assert_array_equal(frames, replay[:-1])
    steps = rng.integers(0, T + 1, subset)  # random order, repeats, and the frame after the last step
    steps[:2] = steps[2], T
    np.testing.assert_array_equal(render_frames(states, actions, angle, size, steps), replay[steps])


@pytest.mark.parametrize("size", [64, 96, 224])
def test_frames_of_stored_episodes_are_exactly_the_replay(debug_store, rng, size):
    for episode in (0, 8, 31):
        assert_matches_replay(*stored(debug_store, episode), size, rng)


def test_cached_segments_and_board_and_the_store_shortcut(debug_store, rng):
    states, actions, angle = stored(debug_store, 8)
    steps = rng.integers(0, len(states), 12)
    cached = render_frames(states, actions, angle, 96, steps, ink_segments(states, actions), render_board(96, angle))
    np.testing.assert_array_equal(cached, render_frames(states, actions, angle, 96, steps))
    np.testing.assert_array_equal(
        render_episode_steps(debug_store, 8, 96, steps), render_episode(debug_store, 8, 96)[steps]
    )
    assert render_frames(states, actions, angle, 32, []).shape == (0, 32, 32, 3)
    with pytest.raises(IndexError):
        render_frames(states, actions, angle, 32, [len(states) + 1])


def test_ink_segments_are_the_pen_down_steps_paths(debug_store):
    states, actions, angle = stored(debug_store, 0)
    segments, step = ink_segments(states, actions)
    down = np.flatnonzero(actions[:, 2] > physics.PEN_THRESHOLD)
    np.testing.assert_array_equal(step, np.repeat(down, physics.SUBSTEPS))
    path = physics.control_step(states[down[3]], actions[down[3]])[1]
    np.testing.assert_array_equal(segments[step == down[3]], np.c_[path[:-1], path[1:]])


def test_cursor_against_the_canvas_wall(rng):
    # Fast moves at every border with targets outside the canvas: the walled substeps clip the inked paths.
    starts = [
        (4.0, 250.0, -300.0, 40.0),
        (508.0, 30.0, 250.0, -200.0),
        (200.0, 509.0, 50.0, 400.0),
        (6.0, 6.0, -200.0, -90.0),
    ]
    targets = [(-60.0, 250.0), (700.0, -50.0), (200.0, 900.0), (-30.0, -30.0)]
    for (start, target), size in zip(zip(starts, targets, strict=True), (64, 96, 224, 96), strict=True):
        actions = np.array([[*target, 1.0]] * 4 + [[256.0, 256.0, 0.0], [*target, 1.0]] * 2)
        states = rollout([*start, 1.0], actions)
        paths = [physics.control_step(s, a)[1] for s, a in zip(states, actions, strict=True)]
        assert any(np.any((p == 0.0) | (p == CANVAS_SIZE)) for p in paths)  # the wall was hit
        assert_matches_replay(states, actions, 0.4, size, rng, subset=8)


def test_an_episode_without_ink(rng):
    actions = np.c_[rng.uniform(0, CANVAS_SIZE, (12, 2)), np.zeros(12)]
    states = rollout([100.0, 300.0, 0.0, 0.0, 0.0], actions)
    segments, step = ink_segments(states, actions)
    assert segments.shape == (0, 4) and step.shape == (0,)
    for size in (64, 224):
        assert_matches_replay(states, actions, -0.3, size, rng, subset=8)


def test_zero_length_segments_make_a_dot(rng):
    # At rest, pen down, target at the cursor: the cursor stays put, so the step inks a dot (in the corner exactly:
    # elsewhere the substep coefficients' rounding moves it by an ulp).
    for cursor in ((0.0, 0.0), (300.0, 200.0)):
        actions = np.array([[*cursor, 1.0], [*cursor, 1.0], [40.0, 60.0, 0.0], [320.0, 180.0, 0.0]])
        states = rollout([*cursor, 0.0, 0.0, 0.0], actions)
        segments, _ = ink_segments(states, actions)
        assert len(segments) == 2 * physics.SUBSTEPS
        assert np.abs(segments[:, :2] - segments[:, 2:]).max() == (0.0 if cursor == (0.0, 0.0) else pytest.approx(0))
        for size in (64, 96, 224):
            assert_matches_replay(states, actions, 0.2, size, rng, subset=6)
            # The last frame differs from the same frame without ink just around the dot.
            last = render_frames(states, actions, 0.2, size, [3])[0]
            inkless = render_frames(states, actions * [1.0, 1.0, 0.0], 0.2, size, [3])[0]
            rows, cols = np.nonzero(np.any(last != inkless, axis=-1))
            centers = (np.c_[cols, rows] + 0.5) * (CANVAS_SIZE / size)
            assert len(rows) and np.linalg.norm(centers - cursor, axis=1).max() < INK_WIDTH / 2 + CANVAS_SIZE / size


def whole_image_board(resolution: int, angle: float) -> np.ndarray:
    """The board as every pixel's distance to each line says (what render_board computes only near the lines)."""
    x, y = raster.pixel_centers(resolution)
    pixel = CANVAS_SIZE / resolution
    image = np.empty((resolution, resolution, 3))
    image[:] = render.BACKGROUND_RGB
    unit = np.array([[0, 0, 1, 1], [0, 1, 1, 0], [0.5, 0, 0.5, 1], [0, 0.5, 1, 0.5]], dtype=np.float64)
    helpers = unit_to_canvas(unit.reshape(-1, 2), angle).reshape(-1, 4)
    tl, tr, br, bl = board_corners(angle)
    for segments, width, rgb in (
        (helpers, render.HELPER_LINE_WIDTH, render.HELPER_LINE_RGB),
        (np.array([np.r_[tr, br], np.r_[br, bl], np.r_[bl, tl]]), render.BOARD_EDGE_WIDTH, render.BOARD_EDGE_RGB),
        (np.r_[tl, tr][None], render.BOARD_EDGE_WIDTH, render.BOARD_TOP_EDGE_RGB),
    ):
        cover = raster.coverage(raster.segment_distance(x, y, segments), width / 2, pixel)[..., None]
        image *= 1.0 - cover
        image += cover * np.asarray(rgb, dtype=np.float64)
    return image


@pytest.mark.parametrize("size", [8, 64, render.WHOLE_BOARD_PIXELS, 97, 100, 224, 301])
def test_the_board_measured_near_its_lines_is_the_whole_image_one(size, rng):
    for angle in (0.0, np.pi / 4, -np.pi / 4, *rng.uniform(-np.pi, np.pi, 3)):
        np.testing.assert_array_equal(render_board(size, angle), whole_image_board(size, angle))
    if size > render.WHOLE_BOARD_PIXELS:  # the tiles are in use, and they leave most pixels unmeasured
        pixels, _ = render.line_coverage(size, np.array([[100.0, 100.0, 400.0, 120.0]]), 4.0)
        assert 0 < len(pixels) < size * size / 4


@pytest.mark.parametrize("size", [32, 64])
def test_the_board_view_is_the_envs_step_by_step_and_stands_upright(debug_store, size):
    from bpp.benchmarks.draw.env import DrawEnv

    for episode in (0, 31):
        states, actions, angle = stored(debug_store, episode)
        env = DrawEnv(image_size=size, cameras=("image", "board_image"), early_stop=False)
        obs, _ = env.reset(options={"board_angle": angle, "cursor": states[0, :2]})
        np.testing.assert_array_equal(env.state, states[0])
        seen = {"image": [obs["image"]], "board_image": [obs["board_image"]]}
        for action in actions[:-1]:
            obs, *_ = env.step(action)
            for camera in seen:
                seen[camera].append(obs[camera])
        steps = np.arange(len(states))
        np.testing.assert_array_equal(np.stack(seen["image"]), render_frames(states, actions, angle, size, steps))
        board_view = render_frames(states, actions, angle, size, steps, upright=True)
        np.testing.assert_array_equal(np.stack(seen["board_image"]), board_view)
        # Upright: the first frame (no ink yet) is an unturned board's with the cursor turned with the board.
        turned = np.c_[render.upright_points(states[:1, :2], angle), states[:1, 2:]]
        np.testing.assert_array_equal(board_view[0], render_frames(turned, actions[:1], 0.0, size, [0])[0])
        assert angle != 0.0 and not np.array_equal(board_view[0], seen["image"][0])
