"""A scripted demonstrator for LIBERO-Gen's pick-and-place tasks, from simulator ground truth.

It drives the robot's OSC_POSE controller (7-D actions: position and rotation deltas in [-1, 1], then the
gripper: -1 open, +1 closed) through waypoints. It moves above a grasp point on the bowl's rim, goes down, closes
the gripper, lifts, carries the bowl above the target (an object's position, or a region's site), lowers it,
releases, and rises. The grasp side, the point on the rim, the heights and a mid-air waypoint vary with the seed,
as teleoperated demonstrations do. LIBERO's own predicate judges every demonstration: a failure is returned as
such, never stored as a success.

A bowl in the cabinet's open top drawer has the drawer's walls close around it: the gripper first turns so that
its fingers close across the drawer's width (the roomier axis), half-closes, and then takes the rim on that axis.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from bpp.envs.libero.bddl import BOWLS, LOCATION_TARGETS
from bpp.envs.libero.suites import BOWL, PickPlace

TIGHT_PLACES = ("TC", "BPR", "NP", "NR", "NB")
"""Table regions: LIBERO's goal check wants the bowl's centre inside a range of a few centimetres."""
NARROW_PICKS = ("TD",)
"""Starts with walls close around the bowl: in the open top drawer the front and back panels are about 8 cm from
the bowl's centre and the sides about 10 cm, where a fully open gripper's outer finger reaches 9.5 cm."""
SETTLE_STEPS = 10
"""No-op steps after a reset: LIBERO's initial placements start objects slightly in the air."""


@dataclass(frozen=True)
class DemoConfig:
    rim_offset: float = 0.055
    """Distance from the bowl's centre to the grasp point on its rim (m), across the fingers' closing axis."""
    grasp_height: tuple[float, float] = (0.01, 0.03)
    """Range of the grasp height above the bowl's origin (m)."""
    carry_height: tuple[float, float] = (0.13, 0.18)
    """Range of the carrying height above the bowl's start (m)."""
    release_height: float = 0.05
    """Height above the target at which the gripper opens (m)."""
    jitter: float = 0.005
    """Std of the grasp point's and the release point's horizontal jitter (m)."""
    narrow_close_steps: int = 4
    """Steps of closing before going down in a narrow start (the gripper moves a quarter of its range per step)."""
    max_step: float = 0.05
    """Position change per step at full action (the controller's output_max)."""
    max_steps: int = 600


@dataclass
class Demonstration:
    actions: np.ndarray
    """(T, 7) OSC_POSE actions."""
    observations: dict[str, np.ndarray] = field(default_factory=dict)
    """Per-step low-dimensional observations (robot proprioception and object poses), before each action."""
    states: np.ndarray | None = None
    """(T, S) flattened simulator states before each action (to re-render any camera later)."""
    success: bool = False


def target_position(env, obs: dict, task: PickPlace) -> np.ndarray:
    """Where the bowl goes: the other bowl's or an object's position, or a region's site."""
    if task.place == BOWL:
        return np.asarray(obs[f"{BOWLS[2 - task.bowl]}_pos"], dtype=float)
    name = LOCATION_TARGETS[task.place][1]
    if f"{name}_pos" in obs:
        return np.asarray(obs[f"{name}_pos"], dtype=float)
    return np.asarray(env.env.sim.data.get_site_xpos(name), dtype=float).copy()


def demonstrate(env, task: PickPlace, seed: int, cfg: DemoConfig = DemoConfig()) -> Demonstration:
    """Reset `env` (made from `task`'s problem) with `seed` and demonstrate the task once."""
    rng = np.random.default_rng(seed)
    env.seed(seed)
    obs = env.reset()
    for _ in range(SETTLE_STEPS):
        obs, *_ = env.step(np.zeros(7))
    actions, states, observed = [], [], []
    bowl = BOWLS[task.bowl - 1]

    def step(action) -> None:
        nonlocal obs
        if len(actions) >= cfg.max_steps:
            raise _OutOfSteps
        states.append(env.env.sim.get_state().flatten())
        observed.append({k: np.asarray(v, dtype=np.float32) for k, v in obs.items() if not k.endswith("_image")})
        actions.append(np.asarray(action, dtype=np.float64))
        obs, *_ = env.step(action)

    def go(target, grip: float, tol: float = 0.005, limit: int = 80) -> None:
        for _ in range(limit):
            delta = np.asarray(target) - obs["robot0_eef_pos"]
            if np.linalg.norm(delta) < tol:
                return
            step(np.r_[np.clip(delta / cfg.max_step, -1.0, 1.0), 0.0, 0.0, 0.0, grip])

    def hold(grip: float, steps: int) -> None:
        for _ in range(steps):
            step(np.r_[np.zeros(6), grip])

    def turn(axis: np.ndarray, grip: float, limit: int = 40) -> None:
        """Yaw the gripper until its fingers close along the horizontal `axis` (either way round)."""
        for _ in range(limit):
            hand = Rotation.from_quat(obs["robot0_eef_quat"]).as_matrix()  # robosuite's (x, y, z, w) order
            closing = hand[:2, 1]  # the fingers close along the hand's y axis
            error = np.arctan2(closing[0] * axis[1] - closing[1] * axis[0], closing @ axis)
            error = (error + np.pi / 2) % np.pi - np.pi / 2
            if abs(error) < 0.03:
                return
            step(np.r_[np.zeros(5), np.clip(error / 0.5, -1.0, 1.0), grip])

    start = np.asarray(obs[f"{bowl}_pos"], dtype=float).copy()
    side = rng.choice([-1.0, 1.0])  # which side of the rim the fingers take
    across = drawer_width_axis(env) if task.pick in NARROW_PICKS else np.array([0.0, 1.0])  # the fingers' axis
    rim = np.r_[side * cfg.rim_offset * across + rng.normal(0.0, cfg.jitter, 2), 0.0]
    carry = rng.uniform(*cfg.carry_height)
    try:
        go(start + rim + [0.0, 0.0, 0.12], -1.0)
        grip = -1.0
        if task.pick in NARROW_PICKS:  # fingers across the drawer, half-closed: the outer one clears its walls
            turn(across, grip)
            go(start + rim + [0.0, 0.0, 0.12], -1.0)
            hold(1.0, cfg.narrow_close_steps)
            grip = 0.0  # the gripper holds its opening
        go(start + rim + [0.0, 0.0, rng.uniform(*cfg.grasp_height)], grip, tol=0.003)
        hold(1.0, 15)
        go(start + rim + [0.0, 0.0, carry], 1.0)
        # Where the bowl actually sits in the hand (it may have slipped): the release point puts its centre, not
        # the gripper's, over the target (table regions are only a few centimetres wide).
        held = np.r_[(obs[f"{bowl}_pos"] - obs["robot0_eef_pos"])[:2], 0.0]
        jitter = 0.0 if task.place in TIGHT_PLACES else cfg.jitter
        target = target_position(env, obs, task) - held + np.r_[rng.normal(0.0, jitter, 2), 0.0]
        middle = (start + target) / 2 + np.r_[rng.normal(0.0, 0.03, 2), carry]  # a varied path through the air
        go(middle, 1.0, tol=0.02)
        go(target + [0.0, 0.0, carry], 1.0)
        go(target + [0.0, 0.0, cfg.release_height], 1.0, tol=0.003)
        hold(-1.0, 10)
        go(obs["robot0_eef_pos"] + [0.0, 0.0, 0.1], -1.0)
        hold(-1.0, 5)
    except _OutOfSteps:
        pass
    keys = observed[0].keys() if observed else ()
    return Demonstration(
        np.array(actions),
        {k: np.stack([o[k] for o in observed]) for k in keys},
        np.array(states),
        bool(env.env._check_success()),
    )


def drawer_width_axis(env) -> np.ndarray:
    """The horizontal unit vector across the wooden cabinet's top drawer (perpendicular to the way it opens)."""
    sim = env.env.sim
    cabinet, drawer = (
        sim.data.body_xpos[sim.model.body_name2id(f"wooden_cabinet_1_{b}")] for b in ("main", "cabinet_top")
    )
    pull = (drawer - cabinet)[:2] / np.linalg.norm((drawer - cabinet)[:2])
    return np.array([pull[1], -pull[0]])


class _OutOfSteps(Exception):
    pass
