import numpy as np
import pytest

from bpp.benchmarks.draw import physics
from bpp.drawing.geometry import BOARD_SIZE, board_corners, canvas_to_unit, canvas_to_upright, unit_to_canvas


@pytest.mark.parametrize("angle", [0.0, 0.3, -np.pi / 4, 2.0])
def test_unit_canvas_round_trip(angle, rng):
    pts = rng.uniform(0, 1, (50, 2))
    np.testing.assert_allclose(canvas_to_unit(unit_to_canvas(pts, angle), angle), pts, atol=1e-12)
    # Un-rotating canvas points gives the same points as drawing them on an upright board.
    np.testing.assert_allclose(canvas_to_upright(unit_to_canvas(pts, angle), angle), unit_to_canvas(pts, 0.0))


def test_board_layout_upright_and_rotated():
    tl, tr, br, bl = board_corners(0.0)
    # Upright board: 350 px square centred on the canvas, top edge (the red one) at small y (screen up).
    np.testing.assert_allclose(tl, [256 - BOARD_SIZE / 2, 256 - BOARD_SIZE / 2])
    np.testing.assert_allclose(br, [256 + BOARD_SIZE / 2, 256 + BOARD_SIZE / 2])
    # A positive angle turns the board counter-clockwise on screen: the top-right corner moves up (y smaller).
    tl_r, tr_r, _, _ = board_corners(0.2)
    assert tr_r[1] < tl_r[1]
    assert np.linalg.norm(tr_r - tl_r) == pytest.approx(BOARD_SIZE)


def test_closed_form_substeps_match_integrator(rng):
    for _ in range(20):
        state = np.r_[rng.uniform(100, 400, 2), rng.uniform(-50, 50, 2), 0.0]
        action = np.r_[rng.uniform(100, 400, 2), 1.0]
        _, path = physics.control_step(state, action)
        loop_pos, loop_vel = physics._walled_substeps(state[:2], state[2:4], action[:2])
        np.testing.assert_allclose(path[1:], loop_pos, atol=1e-9)
        np.testing.assert_allclose(physics.control_step(state, action)[0][2:4], loop_vel[-1], atol=1e-9)


def test_pd_controller_is_critically_damped_and_settles():
    state = physics.initial_state(np.array([100.0, 100.0]))
    action = np.array([300.0, 100.0, 1.0])
    xs = []
    for _ in range(15):
        state, path = physics.control_step(state, action)
        xs.extend(path[:, 0])
    assert max(xs) <= 300.0 + 1e-9  # no overshoot from rest
    assert abs(state[0] - 300.0) < 1.0  # settled within 1.5 s
    assert state[4] == 1.0


def test_targets_outside_canvas_are_clipped_and_cursor_stays_inside():
    state = np.array([500.0, 10.0, 3000.0, -3000.0, 0.0])
    for _ in range(5):
        state, path = physics.control_step(state, np.array([600.0, -50.0, 0.0]))
        assert path.min() >= 0.0 and path.max() <= 512.0


def test_batched_control_steps_are_the_single_steps_bit_for_bit(rng):
    # Free moves, pens up and down, and moves into every wall (targets outside the canvas) in one batch.
    states = np.c_[rng.uniform(0, 512, (40, 2)), rng.uniform(-3000, 3000, (40, 2)), rng.integers(0, 2, 40)]
    actions = np.c_[rng.uniform(-200, 700, (40, 2)), rng.uniform(0, 1, 40)]
    states[:8, :2], states[:8, 2:4] = [[5.0, 250.0], [508.0, 30.0]] * 4, [[-3000.0, 40.0], [2500.0, -2000.0]] * 4
    actions[:8, :2] = [[-60.0, 250.0], [700.0, -50.0]] * 4
    next_states, paths = physics.control_steps(states, actions)
    assert next_states.shape == (40, 5) and paths.shape == (40, physics.SUBSTEPS + 1, 2)
    walled = 0
    for i in range(40):
        state, path = physics.control_step(states[i], actions[i])
        np.testing.assert_array_equal(next_states[i], state)
        np.testing.assert_array_equal(paths[i], path)
        walled += bool(np.any((path == 0.0) | (path == 512.0)))
        unwalled = physics._COEF[:, 0:1] * states[i, :2] + physics._COEF[:, 1:2] * states[i, 2:4]
        free = unwalled + physics._COEF[:, 2:3] * np.clip(actions[i, :2], 0, 512)
        if free.min() >= 0 and free.max() <= 512:  # the closed form, exactly
            np.testing.assert_array_equal(path[1:], free)
    assert 0 < walled < 40
