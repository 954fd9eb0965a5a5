import numpy as np
import pytest

from bpp.envs.draw import physics
from bpp.envs.draw.geometry import BOARD_SIZE, board_corners, canvas_to_unit, canvas_to_upright, unit_to_canvas


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
