"""A scripted demonstrator for LIBERO-Gen's pick-and-place tasks, from simulator ground truth.

It drives the robot's OSC_POSE controller (7-D actions: position and rotation deltas in [-1, 1], then the
gripper: -1 open, +1 closed) through waypoints. It moves above a grasp point on the bowl's rim, goes down, closes
the gripper, lifts, carries the bowl above the target (an object's position, or a region's site), lowers it,
releases, and rises. The grasp side, the point on the rim, the heights and a mid-air waypoint vary with the seed,
as teleoperated demonstrations do. LIBERO's own predicate judges every demonstration: a failure is returned as
such, never stored as a success.

A bowl in the cabinet's open top drawer has the drawer's walls close around it: the gripper first turns so that
its fingers close across the drawer's width (the roomier axis), half-closes, and then takes the rim on that axis.

LIBERO-Goal's scene (the Chain suite) needs more than pick-and-place: :data:`OPERATORS` holds the other
operators, each a function of an :class:`Arm` (the recorded robot) and a seeded generator: turning the stove on,
pushing the plate, opening or closing the top or the middle drawer, and placing the bowl, the cream cheese or the
wine bottle on an object or a region (the wine rack, which holds bottles tilted, takes a bottle put down upright
about half the time). Closing is in no LIBERO-Gen suite (LIBERO-Goal has no closing task); LIBERO-10's tasks close
a drawer and a microwave.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation

from bpp.benchmarks.libero.chain import parse_step
from bpp.benchmarks.libero.sim import GoalOrder, derive_constants, holds, reset_env, seat
from bpp.benchmarks.libero.suites import BOWL, BOWLS, LOCATION_TARGETS, PickPlace

TIGHT_PLACES = ("TC", "BPR", "NP", "NR", "NB")
"""Table regions: LIBERO's goal check wants the bowl's centre inside a range of a few centimetres."""
NARROW_PICKS = ("TD",)
"""Starts with walls close around the bowl: in the open top drawer the front and back panels are about 8 cm from
the bowl's centre and the sides about 10 cm, where a fully open gripper's outer finger reaches 9.5 cm."""
DOWN = Rotation.from_matrix([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
"""The hand pointing straight down, its fingers closing along world y, as the robot starts (its frame's columns: x,
y, z)."""
SETTLE_STEPS = 10
"""No-op steps after a reset: LIBERO's initial placements start objects slightly in the air."""


@dataclass(frozen=True)
class DemoConfig:
    rim_offset: float = 0.055
    """Distance from the bowl's centre to the grasp point on its rim (m), across the fingers' closing axis."""
    grasp_height: tuple[float, float] = (0.02, 0.04)
    """Range of the grasp height above the bowl's origin (m). Lower, the fingers hold the rim's wall at its foot,
    and a bowl lifted at full speed slipped out in 4 of 50 demonstrations from one task's initial states (BENCHMARKS,
    "LIBERO-Gen Combination")."""
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
    far_reach: float = 0.76
    """A bowl farther than this from the robot's shoulder, horizontally (m), is taken on its near rim: taken on the
    side, the lifted arm was stretched to its elbow's limit, and the controller could not bring it back."""
    max_steps: int = 600
    rim_side: Literal["random", "near"] = "random"
    """Which side of a bowl's rim the fingers take where the scene leaves the choice open: either, with even odds
    (two ways to do one task, as people vary), or the side nearer the gripper when the demonstration starts (one
    way, a function of the state a policy observes)."""
    action_noise: float = 0.0
    """Std of Gaussian noise added to the position part of each action the robot executes, not of the action
    recorded (DART: the demonstrator is closed-loop, so the stored demonstrations show it correcting the push)."""


@dataclass
class Demonstration:
    actions: np.ndarray
    """(T, 7) OSC_POSE actions."""
    observations: dict[str, np.ndarray] = field(default_factory=dict)
    """Per-step low-dimensional observations (robot proprioception and object poses), before each action."""
    states: np.ndarray | None = None
    """(T, S) flattened simulator states before each action (to re-render any camera later)."""
    success: bool = False
    """LIBERO's goal holds at the end, and a goal of several terms (a Chain's steps) was reached in their order."""
    executed: np.ndarray | None = None
    """(T, 7) the actions the controller received, when they differ from `actions` (``DemoConfig.action_noise``)."""


def target_position(env, obs: dict, task: PickPlace) -> np.ndarray:
    """Where the bowl goes: the other bowl's or an object's position, or a region's site."""
    if task.place == BOWL:
        return np.asarray(obs[f"{BOWLS[2 - task.bowl]}_pos"], dtype=float)
    name = LOCATION_TARGETS[task.place][1]
    if f"{name}_pos" in obs:
        return np.asarray(obs[f"{name}_pos"], dtype=float)
    return np.asarray(env.env.sim.data.get_site_xpos(name), dtype=float).copy()


class Arm:
    """The robot of a LIBERO env driven through waypoints, every step recorded (the state and observation before it,
    and the action). :meth:`start` resets and settles the env; the operators below move the arm; :meth:`result`
    judges the whole demonstration by LIBERO's predicate, and a goal of several terms by their order too."""

    def __init__(self, env, cfg: DemoConfig, upright: bool = False, seed: int = 0):
        self.env, self.cfg = env, cfg
        self.noise = np.random.default_rng([seed, 7])  # the executed actions' perturbations (cfg.action_noise)
        self.upright = upright
        """Hold the hand pointing straight down while it moves (the controller takes rotation *deltas*, so without
        this its tracking errors add up: after a drawer was pulled the hand was 9 degrees off and missed a rim)."""
        self.actions: list[np.ndarray] = []
        self.executed: list[np.ndarray] = []
        self.states: list[np.ndarray] = []
        self.observed: list[dict] = []
        self.obs: dict = {}
        self.order: GoalOrder | None = None

    @classmethod
    def start(cls, env, seed: int, cfg: DemoConfig = DemoConfig(), upright: bool = False) -> Arm:
        arm = cls(env, cfg, upright, seed)
        arm.obs = reset_env(env, seed)
        derive_constants(env)  # as its exported scene file compiles: a replay in that file follows it
        for _ in range(SETTLE_STEPS):
            env.step(np.zeros(7))
        arm.obs = seat(env)  # as a replay starts
        arm.order = GoalOrder.of(env)
        return arm

    def step(self, action) -> None:
        if len(self.actions) >= self.cfg.max_steps:
            raise _OutOfSteps
        self.states.append(self.env.env.sim.get_state().flatten())
        self.observed.append(
            {k: np.asarray(v, dtype=np.float32) for k, v in self.obs.items() if not k.endswith("_image")}
        )
        self.actions.append(np.asarray(action, dtype=np.float64))
        executed = np.array(action, dtype=np.float64)
        if self.cfg.action_noise:
            executed[:3] = np.clip(executed[:3] + self.noise.normal(0.0, self.cfg.action_noise, 3), -1.0, 1.0)
        self.executed.append(executed)
        self.obs, *_ = self.env.step(executed)
        if self.order is not None:
            self.order.update()

    def go(self, target, grip: float, tol: float = 0.005, limit: int = 80, across=None, pose=None) -> None:
        """Move the gripper to `target`; with `across` (a horizontal axis), also yaw it until its fingers close
        along that axis, at the same time; with `pose` (a :class:`~scipy.spatial.transform.Rotation`, the hand's
        frame in the world's), turn it to that orientation instead."""
        for _ in range(limit):
            delta = np.asarray(target) - self.obs["robot0_eef_pos"]
            if pose is not None:
                rotation = (pose * self.hand().inv()).as_rotvec()  # world-frame axis times angle, as OSC_POSE takes
                done = np.linalg.norm(rotation) < 0.05
            else:
                yaw = 0.0 if across is None else self.yaw_error(across)
                rotation = (self.tilt() if self.upright else np.zeros(3)) + [0.0, 0.0, yaw]
                done = abs(yaw) < 0.03
            if np.linalg.norm(delta) < tol and done:
                return
            self.step(np.r_[np.clip(delta / self.cfg.max_step, -1.0, 1.0), np.clip(rotation / 0.5, -1.0, 1.0), grip])

    def hand(self) -> Rotation:
        return Rotation.from_quat(self.obs["robot0_eef_quat"])  # robosuite's (x, y, z, w) order

    def hold(self, grip: float, steps: int) -> None:
        for _ in range(steps):
            self.step(np.r_[np.zeros(6), grip])

    def yaw_error(self, axis: np.ndarray) -> float:
        """The yaw (rad, either way round) that makes the fingers close along the horizontal `axis`."""
        closing = self.hand().as_matrix()[:2, 1]  # the fingers close along the hand's y axis
        error = np.arctan2(closing[0] * axis[1] - closing[1] * axis[0], closing @ axis)
        return (error + np.pi / 2) % np.pi - np.pi / 2

    def tilt(self) -> np.ndarray:
        """The rotation (world-frame axis times angle, as OSC_POSE takes it) that points the hand straight down."""
        pointing = self.hand().as_matrix()[:, 2]
        axis = np.cross(pointing, [0.0, 0.0, -1.0])
        angle = np.arctan2(np.linalg.norm(axis), -pointing[2])
        return axis / max(np.linalg.norm(axis), 1e-9) * angle

    def turn(self, axis: np.ndarray, grip: float, limit: int = 40) -> None:
        """Yaw the gripper until its fingers close along the horizontal `axis` (either way round)."""
        for _ in range(limit):
            error = self.yaw_error(axis)
            if abs(error) < 0.03:
                return
            self.step(np.r_[np.zeros(5), np.clip(error / 0.5, -1.0, 1.0), grip])

    def result(self) -> Demonstration:
        keys = self.observed[0].keys() if self.observed else ()
        in_order = self.order is None or self.order.done
        return Demonstration(
            np.array(self.actions),
            {k: np.stack([o[k] for o in self.observed]) for k in keys},
            np.array(self.states),
            bool(self.env.env._check_success()) and in_order,
            np.array(self.executed) if self.cfg.action_noise else None,
        )


def demonstrate(env, task: PickPlace, seed: int, cfg: DemoConfig = DemoConfig()) -> Demonstration:
    """Reset `env` (made from `task`'s problem) with `seed` and demonstrate the task once."""
    rng = np.random.default_rng(seed)
    arm = Arm.start(env, seed, cfg)
    bowl = BOWLS[task.bowl - 1]
    start = np.asarray(arm.obs[f"{bowl}_pos"], dtype=float).copy()
    narrow, level = task.pick in NARROW_PICKS, level_axis(arm.obs[f"{bowl}_quat"])
    across = np.array([0.0, 1.0]) if level is None else level  # the fingers' axis
    if narrow:
        across = drawer_width_axis(env)
    side = rim_side(arm, rng, start, across)  # which side of the rim the fingers take
    sim = env.env.sim
    inward = (sim.data.body_xpos[sim.model.body_name2id("robot0_link1")] - start)[:2]
    far = not narrow and level is None and np.linalg.norm(inward) > cfg.far_reach
    if far:  # the near rim: fingers along the line to the robot
        across, side = inward / np.linalg.norm(inward), 1.0
    rim = np.r_[side * cfg.rim_offset * across + rng.normal(0.0, cfg.jitter, 2), 0.0]
    carry = rng.uniform(*cfg.carry_height)
    try:
        arm.go(start + rim + [0.0, 0.0, 0.12], -1.0)
        grip = -1.0
        if narrow or level is not None or far:
            arm.turn(across, grip)
            arm.go(start + rim + [0.0, 0.0, 0.12], -1.0)
        if narrow:  # fingers across the drawer, half-closed: the outer one clears its walls
            arm.hold(1.0, cfg.narrow_close_steps)
            grip = 0.0  # the gripper holds its opening
        # Where the bowl is now: LIBERO's placements drop it from a few centimetres, and one still falling or settling
        # on a neighbour's rim after the settling steps ends up to 4 cm lower than it started (taken from there, the
        # fingers closed above its rim).
        start = np.asarray(arm.obs[f"{bowl}_pos"], dtype=float).copy()
        arm.go(start + rim + [0.0, 0.0, rng.uniform(*cfg.grasp_height)], grip, tol=0.003)
        arm.hold(1.0, 15)
        arm.go(start + rim + [0.0, 0.0, carry], 1.0)
        # Where the bowl actually sits in the hand (it may have slipped): the release point puts its centre, not
        # the gripper's, over the target (table regions are only a few centimetres wide).
        obs = arm.obs
        held = np.r_[(obs[f"{bowl}_pos"] - obs["robot0_eef_pos"])[:2], 0.0]
        jitter = 0.0 if task.place in TIGHT_PLACES else cfg.jitter
        target = target_position(env, obs, task) - held + np.r_[rng.normal(0.0, jitter, 2), 0.0]
        middle = (start + target) / 2 + np.r_[rng.normal(0.0, 0.03, 2), carry]  # a varied path through the air
        arm.go(middle, 1.0, tol=0.02)
        arm.go(target + [0.0, 0.0, carry], 1.0)
        arm.go(target + [0.0, 0.0, cfg.release_height], 1.0, tol=0.003)
        arm.hold(-1.0, 10)
        arm.go(arm.obs["robot0_eef_pos"] + [0.0, 0.0, 0.1], -1.0)
        arm.hold(-1.0, 5)
    except _OutOfSteps:
        pass
    return arm.result()


def rim_side(arm: Arm, rng: np.random.Generator, bowl: np.ndarray, across: np.ndarray) -> float:
    """The side of the rim (+1 or -1 along the horizontal `across`) the fingers take, by ``DemoConfig.rim_side``.
    The random draw is made either way, so that the seed's later draws do not depend on the setting."""
    drawn = rng.choice([-1.0, 1.0])
    if arm.cfg.rim_side == "random":
        return float(drawn)
    return 1.0 if (arm.obs["robot0_eef_pos"] - bowl)[:2] @ across >= 0.0 else -1.0


def turn_on(arm: Arm, rng: np.random.Generator, stove: str = "flat_stove_1") -> None:
    """Turn the stove's knob on: take its lever between the fingers and carry it round the knob's axis (a hinge
    about world z) by about 0.9 rad, turning the hand with it; LIBERO counts 0.5 rad or more as on. The lever
    points along the knob body's x axis at the start; the grasp point and height along it vary with the seed."""
    sim = arm.env.env.sim
    body = sim.model.body_name2id(f"{stove}_button")
    axis = sim.data.body_xpos[body].copy()
    start = Rotation.from_quat(sim.data.body_xquat[body][[1, 2, 3, 0]]).as_matrix()[:2, 0]  # MuJoCo's (w, x, y, z)
    angle0 = np.arctan2(start[1], start[0])
    radius, height = rng.uniform(0.017, 0.021), rng.uniform(0.028, 0.034)

    def lever(turned: float) -> tuple[np.ndarray, np.ndarray]:
        a = angle0 + turned
        return axis + np.r_[radius * np.cos(a), radius * np.sin(a), height], np.array([-np.sin(a), np.cos(a)])

    point, across = lever(0.0)
    arm.go(point + [0.0, 0.0, rng.uniform(0.07, 0.1)], -1.0, across=across)
    arm.go(point, -1.0, across=across)
    arm.hold(1.0, 10)
    for turned in np.linspace(0.0, rng.uniform(0.85, 1.0), 10):
        point, across = lever(turned)
        arm.go(point, 1.0, tol=0.003, limit=12, across=across)
    arm.hold(-1.0, 5)
    arm.go(arm.obs["robot0_eef_pos"] + [0.0, 0.0, 0.08], -1.0)


def push(arm: Arm, rng: np.random.Generator, obj: str = "plate_1", region: str = "main_table_stove_front_region"):
    """Slide `obj` (a plate: its rim is low) over the table into `region`: the closed fingers go down inside it
    and drag it, steered by where its centre is now. The robot cannot reach low enough behind the plate's far side
    to push it from there.

    The path is an L, first along y, then along x, ending in the region's far half (jittered): in LIBERO-Goal's
    scene a straight path runs the plate over the cream cheese, which sits about 9 cm from the region's centre."""
    sim = arm.env.env.sim
    centre = sim.data.get_site_xpos(region)[:2]
    target = centre + np.r_[rng.normal(0.0, 0.008), 0.025 + rng.uniform(-0.005, 0.005)]
    here = np.asarray(arm.obs[f"{obj}_pos"], dtype=float)
    # Aimed a little below where the fingertips can go: they press on the plate's floor and do not ride over its rim
    # (pressing more lightly, or starting at the rim, tipped the plate up and lost it).
    floor = here[2] + 0.002
    arm.go(np.r_[here[:2], floor + rng.uniform(0.08, 0.12)], 1.0)
    arm.go(np.r_[here[:2], floor], 1.0, tol=0.006, limit=40)
    for waypoint in (np.r_[here[0], target[1]], target):
        for _ in range(250):
            plate = arm.obs[f"{obj}_pos"]
            remaining = waypoint - plate[:2]
            if np.linalg.norm(remaining) < 0.008 or np.linalg.norm(arm.obs["robot0_eef_pos"][:2] - plate[:2]) > 0.1:
                break  # there, or the plate was lost: LIBERO's predicate judges which
            down = floor - arm.obs["robot0_eef_pos"][2]
            arm.step(np.r_[np.clip(np.r_[remaining, down] / arm.cfg.max_step, -0.4, 0.4), 0.0, 0.0, 0.0, 1.0])
    arm.go(arm.obs["robot0_eef_pos"] + [0.0, 0.0, 0.1], 1.0)


def drawer_handle(env, cabinet: str, drawer: str) -> np.ndarray:
    """Where the handle of LIBERO-Goal's cabinet drawer `drawer` (top or middle) is now: a horizontal bar 2.7 cm in
    front of the drawer's face."""
    if drawer not in ("top", "middle"):
        raise ValueError(f"the demonstrator opens and closes the top and the middle drawer, not {drawer!r}")
    sim = env.env.sim
    bar = {"top": "g18", "middle": "g29"}[drawer]  # the handle's geom in the drawer's body
    return sim.data.geom_xpos[sim.model.geom_name2id(f"{cabinet}_{bar}")].copy()


def fingers_leading(rng: np.random.Generator, across: np.ndarray) -> Rotation:
    """A hand pitched 65-75 degrees from straight down about the horizontal axis `across` (a drawer's width), its
    fingers towards the cabinet: how the middle drawer's handle is reached under the top one's."""
    return Rotation.from_rotvec(-np.radians(rng.uniform(65.0, 75.0)) * np.r_[across, 0.0]) * DOWN


def open_drawer(arm: Arm, rng: np.random.Generator, cabinet: str = "wooden_cabinet_1", drawer: str = "top"):
    """Open a drawer of LIBERO-Goal's cabinet by its handle (a horizontal bar along x, 2.7 cm in front of the
    drawer's face) and pull it out along the way it slides (world +y) by 17-19 cm; LIBERO counts 14 cm out as open.

    The top drawer's handle is taken from above: the open hand comes down over it with its fingers closing along y,
    stops on it and closes. From above the middle handle cannot be reached (the fingers stop on the top handle,
    7.4 cm higher), and a level hand's palm hits the plate below: the hand comes at it pitched 65-75 degrees from
    straight down, fingers towards the cabinet, closing across the bar nearly vertically
    (docs/libero-gen/demonstrator.md)."""
    handle = drawer_handle(arm.env, cabinet, drawer)
    grasp = handle + np.r_[rng.uniform(-0.02, 0.02), 0.0, 0.0]
    pose = None
    if drawer == "top":
        arm.go(grasp + [0.0, 0.0, rng.uniform(0.07, 0.1)], -1.0, across=np.array([0.0, 1.0]))  # closing across the bar
        arm.go(grasp, -1.0, tol=0.004)
    else:
        pose = fingers_leading(rng, np.array([1.0, 0.0]))
        fingers = pose.as_matrix()[:, 2]  # where they point
        arm.go(grasp - 0.1 * fingers + [0.0, 0.0, 0.03], -1.0, tol=0.01, pose=pose)
        arm.go(grasp - 0.06 * fingers, -1.0, pose=pose)
        arm.go(grasp, -1.0, tol=0.004, limit=60, pose=pose)
    arm.hold(1.0, 12)
    pull = rng.uniform(0.17, 0.19)
    for k in range(1, 9):
        arm.go(grasp + [0.0, pull * k / 8, 0.0], 1.0, tol=0.004, limit=15, pose=pose)
    arm.hold(-1.0, 6)
    if pose is not None:  # back off the way the fingers came, then turn the hand down again
        arm.go(arm.obs["robot0_eef_pos"] - 0.08 * fingers, -1.0, tol=0.01, pose=pose)
        arm.go(arm.obs["robot0_eef_pos"] + [0.0, 0.0, 0.05], -1.0, tol=0.01, pose=DOWN)
    arm.go(arm.obs["robot0_eef_pos"] + [0.0, 0.03, 0.08], -1.0)
    arm.go(arm.obs["robot0_eef_pos"] + [-0.15, 0.0, 0.0], -1.0, tol=0.02)  # back over the table, clear of the drawer


def close_drawer(arm: Arm, rng: np.random.Generator, cabinet: str = "wooden_cabinet_1", drawer: str = "top"):
    """Close an open drawer of LIBERO-Goal's cabinet by pushing its handle back in: the closed fingers come down
    just in front of the bar, pads across it, and push along the way the drawer slides (towards the cabinet) until it
    is in, a little past where it stops. LIBERO counts a drawer as closed only at its stop (joint position > 0)."""
    handle = drawer_handle(arm.env, cabinet, drawer)
    sim = arm.env.env.sim
    body = sim.model.body_name2id(f"{cabinet}_cabinet_{drawer}")
    out = np.r_[drawer_pull_axis(arm.env, sim.data.body_xpos[body]), 0.0]
    across = np.array([out[1], -out[0]])
    joint = sim.model.jnt_qposadr[sim.model.body_jntadr[body]]
    opened = abs(float(sim.data.qpos[joint]))  # how far it is out
    start = handle + out * rng.uniform(0.035, 0.045) + np.r_[across * rng.uniform(-0.02, 0.02), 0.0]
    end = start - out * ((start - handle) @ out + opened + rng.uniform(0.01, 0.02))  # a little past its stop
    pose = None
    if drawer == "top":
        arm.go(start + [0.0, 0.0, rng.uniform(0.07, 0.1)], 1.0, across=across)
        arm.go(start, 1.0, tol=0.004)
    else:  # a hand pointing down would meet the top drawer's handle above: the fingers lead, pitched towards it
        pose = fingers_leading(rng, across)
        arm.go(start + out * 0.06 + [0.0, 0.0, 0.03], 1.0, tol=0.01, pose=pose)
        arm.go(start, 1.0, tol=0.004, limit=60, pose=pose)
    for k in range(1, 9):
        arm.go(start + (end - start) * k / 8, 1.0, tol=0.004, limit=15, pose=pose)
    for _ in range(4):  # pressed against its stop until it is in (the hand can stop a few millimetres short)
        if sim.data.qpos[joint] > 0.0005:
            break
        arm.go(arm.obs["robot0_eef_pos"] - out * 0.015, 1.0, tol=0.004, limit=12, pose=pose)
    arm.go(arm.obs["robot0_eef_pos"] + out * 0.06, 1.0, tol=0.01, pose=pose)
    arm.go(arm.obs["robot0_eef_pos"] + [0.0, 0.0, 0.08], 1.0, tol=0.01, pose=None if pose is None else DOWN)


def grasp_offset(arm: Arm, rng: np.random.Generator, obj: str) -> tuple[np.ndarray, np.ndarray]:
    """Where the fingers take `obj`, relative to its origin, and the horizontal axis they close along: a bowl by
    its rim (as in :func:`demonstrate`), anything else by the collision box that reaches highest (the cream cheese
    lying flat: its only box; the wine bottle: its neck), across the box's narrower side, 3 cm below the box's top
    or just above its centre, whichever is higher.

    With a drawer of the cabinet open, a bowl is taken on the rim away from the drawer, its fingers closing across
    the drawer's width: on the near rim the arm came down onto the pulled-out drawer's side wall and stalled 4 cm
    above the grasp, and a bowl put into the drawer (15 cm deep inside, the bowl about 12 cm wide) leaves room for the
    fingers only along its width (docs/libero-gen/demonstrator.md)."""
    if obj.startswith("akita_black_bowl"):
        across, away = np.array([0.0, 1.0]), 0.0
        drawer = open_drawer_body(arm.env)
        if drawer is not None:  # the rim on the side away from it, fingers across its width (see the docstring)
            across = drawer_width_axis(arm.env, drawer)
            away = (arm.obs[f"{obj}_pos"] - drawer)[:2] @ across
        side = rim_side(arm, rng, arm.obs[f"{obj}_pos"], across)
        side = np.sign(away) if abs(away) > 0.01 else side
        rim = side * arm.cfg.rim_offset * across + rng.normal(0.0, arm.cfg.jitter, 2)
        return np.r_[rim, rng.uniform(*arm.cfg.grasp_height)], across
    sim = arm.env.env.sim
    body = sim.model.body_name2id(f"{obj}_main")
    boxes = [i for i in range(sim.model.ngeom) if sim.model.geom_bodyid[i] == body and sim.model.geom_type[i] == 6]

    def frame(i):
        return sim.data.geom_xmat[i].reshape(3, 3), sim.model.geom_size[i]

    def top(i):
        axes, half = frame(i)
        return sim.data.geom_xpos[i][2] + np.abs(axes[2]) @ half

    box = max(boxes, key=top)
    axes, half = frame(box)
    horizontal = [k for k in range(3) if abs(axes[2, k]) < 0.5]  # the box's axes that lie flat
    narrow = min(horizontal, key=lambda k: half[k])
    across = axes[:2, narrow] / np.linalg.norm(axes[:2, narrow])
    origin = sim.data.body_xpos[body][2]
    # Lower than 3 cm under the top, the palm would press on it (it tipped the bottle over); lower than just above
    # the centre, the fingertips would meet the table (the cheese).
    height = max(sim.data.geom_xpos[box][2] + 0.008, top(box) - 0.03) - origin
    return np.r_[rng.normal(0.0, 0.003, 2), height], across


def place_on(arm: Arm, rng: np.random.Generator, obj: str, target: str) -> None:
    """Pick `obj` up and put it on `target` (an object, or a region's or a fixture's site): grasp, lift, carry
    through a varied mid-air point, hold the object's origin (not the hand) 5 cm above the target, open fully, and
    leave upwards (from lower, a box caught on a bowl's rim and the opening fingers carried both away)."""
    sim = arm.env.env.sim
    start = np.asarray(arm.obs[f"{obj}_pos"], dtype=float).copy()
    offset, across = grasp_offset(arm, rng, obj)
    carry = rng.uniform(*arm.cfg.carry_height)
    arm.go(start + offset + [0.0, 0.0, 0.12], -1.0, across=across)
    arm.go(start + offset, -1.0, tol=0.004, limit=40)
    arm.hold(1.0, 15)
    taken = start + offset + slide_out_from_under_drawer(arm, obj)  # where the hand holds it now
    goal = arm.obs[f"{target}_pos"] if f"{target}_pos" in arm.obs else sim.data.get_site_xpos(target)
    goal = np.asarray(goal, dtype=float) + np.r_[rng.normal(0.0, 0.004, 2), 0.05]
    # Straight up to the carrying height, 5 cm above the release point at least, before moving across: rising
    # on the way, a bowl swung into the open drawer's corner, dropped, and pushed the drawer 2 cm shut.
    lift = max(carry, goal[2] - start[2] + 0.05)
    arm.go(taken + [0.0, 0.0, lift], 1.0)
    held = arm.obs[f"{obj}_pos"] - arm.obs["robot0_eef_pos"]  # where the object hangs in the hand now
    goal -= held
    lift = max(carry, goal[2] - start[2] + 0.05)
    arm.go((start + goal) / 2 + np.r_[rng.normal(0.0, 0.03, 2), lift], 1.0, tol=0.02)
    arm.go(np.r_[goal[:2], start[2] + lift], 1.0)
    arm.go(goal, 1.0, tol=0.004, limit=40)
    arm.hold(-1.0, 15)
    arm.go(arm.obs["robot0_eef_pos"] + [0.0, 0.0, 0.1], -1.0)
    arm.hold(-1.0, 5)


DRAWER_HALF_SIZE = (0.105, 0.08)
"""Half the footprint of a drawer of LIBERO-Goal's cabinet (m): across its width, along the way it slides."""
BOWL_RADIUS = 0.06


def slide_out_from_under_drawer(arm: Arm, obj: str, margin: float = 0.02) -> np.ndarray:
    """A bowl just taken that sits partly under the cabinet's open drawer (it overhangs the table in LIBERO-Goal's
    scene) is slid out across the drawer's width, 2 cm off the table, until it clears the drawer by `margin`:
    lifted straight up, it met the drawer's floor and stalled, or pushed the drawer shut. Returns the hand's move
    (zero when there was nothing to do)."""
    drawer = open_drawer_body(arm.env) if obj.startswith("akita_black_bowl") else None
    if drawer is None:
        return np.zeros(3)
    width = drawer_width_axis(arm.env, drawer)
    pull = np.array([-width[1], width[0]])
    apart = (arm.obs[f"{obj}_pos"] - drawer)[:2]
    along, off = apart @ width, apart @ pull
    clear = DRAWER_HALF_SIZE[0] + BOWL_RADIUS + margin
    if abs(along) >= clear or abs(off) >= DRAWER_HALF_SIZE[1] + BOWL_RADIUS:
        return np.zeros(3)
    shift = np.r_[(np.sign(along) * clear - along) * width, 0.02]
    arm.go(arm.obs["robot0_eef_pos"] + shift, 1.0, tol=0.01)
    return shift


OPERATORS = {"turn_on": turn_on, "push": push, "open": open_drawer, "close": close_drawer, "place": place_on}
"""Operators other than pick-and-place, by the BDDL predicate they make true (LIBERO-Goal's scene)."""


def demonstrate_task(env, task, seed: int, cfg: DemoConfig = DemoConfig()) -> Demonstration:
    """Reset `env` (made from `task`'s problem) with `seed` and demonstrate a Combination task
    (:class:`~bpp.benchmarks.libero.suites.PickPlace`) or a Chain task
    (:class:`~bpp.benchmarks.libero.chain.ChainTask`: its steps, from the state its problem starts in)."""
    if isinstance(task, PickPlace):
        return demonstrate(env, task, seed, cfg)
    requires = parse_step(task.start).goal if task.start else None
    return demonstrate_steps(env, [(step.operator, step.kwargs) for step in task.steps], seed, cfg, requires)


def demonstrate_operator(env, operator: str, seed: int, cfg: DemoConfig = DemoConfig(), **kw) -> Demonstration:
    """Reset `env` with `seed` and run one operator of :data:`OPERATORS` (keyword arguments name its objects)."""
    return demonstrate_steps(env, [(operator, kw)], seed, cfg)


def demonstrate_steps(
    env, steps, seed: int, cfg: DemoConfig = DemoConfig(), requires: str | None = None
) -> Demonstration:
    """Reset `env` with `seed` and run `steps`, ``[(operator, {argument: value})]``, one after the other in one
    episode (a Chain task's two steps); LIBERO's predicate judges the end. With `requires`, a BDDL predicate that
    must hold once the scene has settled (a second-step task's start state), a reset where it does not is an
    unsuccessful demonstration with no steps."""
    for operator, _ in steps:
        if operator not in OPERATORS:
            raise ValueError(f"no operator {operator!r}; known: {', '.join(OPERATORS)}")
    # Held upright only across several steps, where the drift adds up: on single steps it helped the plate push (4 of
    # 4 seeds against 5 of 6) but knocked the wine bottle over (0 of 3 against 2 of 3).
    arm = Arm.start(env, seed, cfg, upright=len(steps) > 1)
    if requires is not None and not holds(env, requires):
        return Demonstration(np.zeros((0, 7)))
    rng = np.random.default_rng(seed)
    with contextlib.suppress(_OutOfSteps):  # a demonstration that ran out of steps is judged as it stands
        for operator, kw in steps:
            OPERATORS[operator](arm, rng, **kw)
    return arm.result()


def level_axis(quat, min_tilt: float = np.radians(4.0)) -> np.ndarray | None:
    """For a bowl tilted by more than `min_tilt` (one on the ramekin leans by 12 degrees), the horizontal
    direction from its centre in which its rim stays at the centre's height and its wall stands upright against
    closing fingers: perpendicular to the way it leans. None for a bowl standing level. Taken at the rim on the
    usual axis instead, the inner finger lands on the leaning wall, 3-4 cm above its grasp height."""
    up = Rotation.from_quat(quat).as_matrix()[:, 2]  # robosuite's (x, y, z, w) order
    lean = up[:2]
    if np.linalg.norm(lean) < np.sin(min_tilt):
        return None
    return np.array([-lean[1], lean[0]]) / np.linalg.norm(lean)


def drawer_width_axis(env, drawer: np.ndarray | None = None) -> np.ndarray:
    """The horizontal unit vector across a drawer of the wooden cabinet (perpendicular to the way it opens), given
    the open drawer's body position (default: the top drawer's)."""
    pull = drawer_pull_axis(env, drawer)
    return np.array([pull[1], -pull[0]])


def drawer_pull_axis(env, drawer: np.ndarray | None = None) -> np.ndarray:
    """The horizontal unit vector along which a drawer of the wooden cabinet opens (out of the cabinet), given the
    open drawer's body position (default: the top drawer's)."""
    sim = env.env.sim
    cabinet = sim.data.body_xpos[sim.model.body_name2id("wooden_cabinet_1_main")]
    if drawer is None:
        drawer = sim.data.body_xpos[sim.model.body_name2id("wooden_cabinet_1_cabinet_top")]
    return (drawer - cabinet)[:2] / np.linalg.norm((drawer - cabinet)[:2])


def open_drawer_body(env, cabinet: str = "wooden_cabinet_1") -> np.ndarray | None:
    """The position of the cabinet's open drawer (top or middle, by LIBERO's own predicate), or None when none is
    open or the scene has no such cabinet."""
    sim = env.env.sim
    for drawer in ("top", "middle"):
        body = f"{cabinet}_cabinet_{drawer}"
        if body in sim.model.body_names and holds(env, f"(Open {cabinet}_{drawer}_region)"):
            return sim.data.body_xpos[sim.model.body_name2id(body)].copy()
    return None


class _OutOfSteps(Exception):
    pass
