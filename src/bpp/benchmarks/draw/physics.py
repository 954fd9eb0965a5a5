"""The cursor's dynamics: a PD controller on an absolute target, stepped at 100 Hz, controlled at 10 Hz.

The state of the simulation is ``[x, y, vx, vy, pen]`` (canvas px, px/s, 0/1). One control step is a pure
function of (state, action), so any stored step can be replayed exactly — that is how datasets avoid storing
images: the ink of step t is the path :func:`control_step` returns for the stored state and action.
"""

from __future__ import annotations

import numpy as np

from bpp.drawing.geometry import CANVAS_SIZE

KP = 100.0
KV = 20.0
PHYSICS_HZ = 100
CONTROL_HZ = 10
SUBSTEPS = PHYSICS_HZ // CONTROL_HZ
PEN_THRESHOLD = 0.5
STATE_DIM = 5
ACTION_DIM = 3


def _substep_matrices() -> np.ndarray:
    """(SUBSTEPS, 3) coefficients c so that position after k substeps = c[k] @ [pos0, vel0, target].

    The semi-implicit Euler update (v += (kp (target - p) - kv v) dt; p += v dt) is linear, so the ten
    substeps of a control step are three multiply-adds instead of a Python loop.
    """
    dt = 1.0 / PHYSICS_HZ
    # Rows: coefficients of (p0, v0, target) in p and in v.
    p = np.array([1.0, 0.0, 0.0])
    v = np.array([0.0, 1.0, 0.0])
    out = []
    for _ in range(SUBSTEPS):
        acc = KP * (np.array([0.0, 0.0, 1.0]) - p) - KV * v
        v = v + acc * dt
        p = p + v * dt
        out.append(np.concatenate([p, v]))
    return np.array(out)


_COEF = _substep_matrices()  # (SUBSTEPS, 6): position coefficients then velocity coefficients


def control_step(state: np.ndarray, action: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Advance one 10 Hz control step.

    Args:
        state: (5,) float64 ``[x, y, vx, vy, pen]``.
        action: (3,) ``[target_x, target_y, pen]``; the target is clipped to the canvas; pen down if > 0.5.

    Returns:
        next_state: (5,) float64.
        path: (SUBSTEPS + 1, 2) cursor positions from the start of the step through every physics substep.
    """
    pos, vel = state[0:2], state[2:4]
    target = np.clip(np.asarray(action[:2], dtype=np.float64), 0.0, CANVAS_SIZE)
    pen = 1.0 if action[2] > PEN_THRESHOLD else 0.0
    positions = _COEF[:, 0:1] * pos + _COEF[:, 1:2] * vel + _COEF[:, 2:3] * target
    velocities = _COEF[:, 3:4] * pos + _COEF[:, 4:5] * vel + _COEF[:, 5:6] * target
    if positions.min() < 0.0 or positions.max() > CANVAS_SIZE:
        positions, velocities = _walled_substeps(pos, vel, target)
    next_state = np.array([*positions[-1], *velocities[-1], pen])
    return next_state, np.concatenate([pos[None], positions], axis=0)


def control_steps(states: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`control_step` of N independent (state, action) pairs at once, with the same arithmetic, so the same
    bits (a test pins it): states (N, 5) float64 and actions (N, 3) -> next states (N, 5) and paths
    (N, SUBSTEPS + 1, 2). Replaying a stored episode's ink uses it; an env, one step at a time, keeps the
    scalar form, whose fewer array operations take 57 against 77 us for one step here."""
    states = np.asarray(states, dtype=np.float64)
    pos, vel = states[:, None, 0:2], states[:, None, 2:4]
    target = np.clip(np.asarray(actions[:, None, :2], dtype=np.float64), 0.0, CANVAS_SIZE)
    pen = np.where(np.asarray(actions)[:, 2] > PEN_THRESHOLD, 1.0, 0.0)
    positions = _COEF[:, 0:1] * pos + _COEF[:, 1:2] * vel + _COEF[:, 2:3] * target  # (N, SUBSTEPS, 2)
    velocities = _COEF[:, 3:4] * pos + _COEF[:, 4:5] * vel + _COEF[:, 5:6] * target
    for i in np.flatnonzero((positions.min(axis=(1, 2)) < 0.0) | (positions.max(axis=(1, 2)) > CANVAS_SIZE)):
        positions[i], velocities[i] = _walled_substeps(pos[i, 0], vel[i, 0], target[i, 0])
    next_states = np.concatenate([positions[:, -1], velocities[:, -1], pen[:, None]], axis=1)
    return next_states, np.concatenate([pos, positions], axis=1)


def _walled_substeps(pos: np.ndarray, vel: np.ndarray, target: np.ndarray):
    """Substeps with the canvas border as a wall (rare: only an overshoot past the border needs it)."""
    dt = 1.0 / PHYSICS_HZ
    pos, vel = pos.copy(), vel.copy()
    positions, velocities = [], []
    for _ in range(SUBSTEPS):
        vel = vel + (KP * (target - pos) - KV * vel) * dt
        pos = pos + vel * dt
        hit = (pos < 0.0) | (pos > CANVAS_SIZE)
        pos = np.clip(pos, 0.0, CANVAS_SIZE)
        vel = np.where(hit, 0.0, vel)
        positions.append(pos)
        velocities.append(vel)
    return np.array(positions), np.array(velocities)


def initial_state(cursor: np.ndarray, pen: bool = False) -> np.ndarray:
    """A resting cursor at `cursor` (canvas px)."""
    return np.array([cursor[0], cursor[1], 0.0, 0.0, float(pen)])
