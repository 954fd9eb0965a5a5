"""LIBERO's simulator, reached through one place: where its problems are, and an env for a BDDL problem.

LIBERO is the ``libero`` extra (``pip install -e ".[libero]"``; ``make test`` installs it). Rendering goes through
MuJoCo's headless OpenGL: ``MUJOCO_GL`` defaults to ``egl`` here (Debian's Mesa provides it; ``osmesa`` needs
``libosmesa6``). An env without cameras renders nothing and is what demonstration generation uses (physics is about
10x faster than rendering two cameras on a CPU).
"""

from __future__ import annotations

import atexit
import contextlib
import os
import weakref
from pathlib import Path

import numpy as np

from bpp.errors import UserError


class LiberoUnavailable(UserError):
    """LIBERO (or its renderer) is missing; the message says what to install or set."""


RENDERER_LIBRARIES = {
    "egl": ("EGL", "libegl1 and libgl1-mesa-dri"),
    "osmesa": ("OSMesa", "libosmesa6"),
    "glfw": ("glfw", "libglfw3 (and a display)"),
}
"""MUJOCO_GL value -> (the shared library it loads, the Debian packages that provide it)."""


def _check_renderer() -> None:
    import ctypes.util

    backend = os.environ["MUJOCO_GL"]
    if backend not in RENDERER_LIBRARIES:
        raise LiberoUnavailable(f"MUJOCO_GL={backend!r} is not a renderer; use one of {', '.join(RENDERER_LIBRARIES)}")
    library, packages = RENDERER_LIBRARIES[backend]
    if ctypes.util.find_library(library) is None:
        raise LiberoUnavailable(
            f"MUJOCO_GL={backend} needs lib{library}, which is not installed: apt-get install {packages}, or choose "
            f"another renderer ({', '.join(k for k in RENDERER_LIBRARIES if k != backend)})"
        )


def _libero():
    os.environ.setdefault("MUJOCO_GL", "egl")
    _check_renderer()
    # Mesa's software renderer links its own LLVM, and so does triton (which torch loads lazily, e.g. on its first
    # optimizer step): loading triton after a GL context exists crashes the process, loading it first is safe.
    with contextlib.suppress(ImportError):
        import triton._C.libtriton  # noqa: F401
    try:
        import libero.libero as libero
    except ImportError:
        raise LiberoUnavailable(
            'LIBERO is not installed: pip install -e ".[libero]" (`make test` installs it; 2.1 GB)'
        ) from None
    return libero


def problems_folder() -> Path:
    """The folder of LIBERO's own BDDL problems (one subfolder per suite, e.g. ``libero_spatial``)."""
    return Path(_libero().get_libero_path("bddl_files"))


def libero_problem(suite: str, name: str) -> str:
    """The text of LIBERO's problem `name` (a file stem) of its suite `suite` (e.g. ``libero_goal``)."""
    path = problems_folder() / suite / f"{name}.bddl"
    if not path.is_file():
        raise UserError(f"no {suite} problem {name!r} in {path.parent}")
    return path.read_text()


def spatial_problem(name: str) -> str:
    """The text of LIBERO-Spatial problem `name` (a file stem, e.g. a Combination scene's ``base``)."""
    return libero_problem("libero_spatial", name)


GOAL_BASE = "turn_on_the_stove"
"""The LIBERO-Goal problem Chain tasks are written from (the ten share one scene and initial state)."""


CAMERAS = {"agentview": "agentview", "eye_in_hand": "robot0_eye_in_hand"}
"""Image observation keys -> LIBERO's camera names: the paper's agent view (the whole work area) and wrist camera."""


def initial_states(name: str):
    """LIBERO's own initial states of one of its tasks, (N, 92) flattened simulator states; `name` is relative to
    LIBERO's init_files folder, e.g. ``libero_spatial/<problem>.pruned_init``."""
    path = Path(_libero().get_libero_path("init_states")) / name
    path = path if path.suffix == ".npz" else path.with_name(path.name + ".npz")
    if not path.is_file():
        raise UserError(f"LIBERO has no initial states {name!r} ({path})")
    with np.load(path, allow_pickle=False) as data:
        return data["states"]


def has_initial_states(suite: str, stem: str) -> bool:
    """Whether LIBERO ships initial states for its problem `stem` of `suite` (what :func:`initial_states` reads as
    ``<suite>/<stem>.pruned_init``)."""
    return (Path(_libero().get_libero_path("init_states")) / suite / f"{stem}.pruned_init.npz").is_file()


HORIZON = 100_000
"""Steps after which robosuite ends an episode and refuses further actions (its default is 1000): our callers keep
their own limits (a Chain demonstration: 1200 steps; a Chain rollout: 1100), so it must not cut them first."""


def make_env(problem: str | Path, cameras: tuple[str, ...] = (), image_size: int = 128, render: bool = False):
    """A LIBERO env for the BDDL problem file `problem`: physics only without `cameras`, else rendering those
    cameras (LIBERO names, e.g. ``agentview``, ``robot0_eye_in_hand``) at `image_size` every step. With `render`
    and no cameras, steps render nothing but :func:`render_states` / :func:`render_now` can draw any camera on
    demand. Takes seconds (it compiles the scene)."""
    _libero()
    from libero.libero.envs.env_wrapper import ControlEnv, OffScreenRenderEnv

    path = Path(problem)
    if not path.is_file():
        raise UserError(f"{path}: no such BDDL problem")
    try:
        if not cameras:
            env = ControlEnv(
                bddl_file_name=str(path),
                horizon=HORIZON,
                has_renderer=False,
                has_offscreen_renderer=render,
                use_camera_obs=False,
                camera_names=list(CAMERAS.values()),
            )
        else:
            env = OffScreenRenderEnv(
                bddl_file_name=str(path),
                horizon=HORIZON,
                camera_names=list(cameras),
                camera_heights=image_size,
                camera_widths=image_size,
            )
    except Exception as err:
        if "gl" in str(err).lower() or "egl" in type(err).__name__.lower():
            raise LiberoUnavailable(
                f"MuJoCo cannot render with MUJOCO_GL={os.environ.get('MUJOCO_GL')!r} ({err}); install Debian's "
                "libegl1 and libgl1-mesa-dri for egl, or libosmesa6 and set MUJOCO_GL=osmesa"
            ) from None
        raise
    if render or cameras:
        _close_at_exit(env)
    return env


_RENDERING: weakref.WeakSet = weakref.WeakSet()
"""The rendering envs not yet garbage: closed at exit, while their OpenGL display still exists."""
_CLOSING_REGISTERED = False


def _close_at_exit(env) -> None:
    # The renderer terminates its EGL display at exit, from an exit handler it registers with its first context; ours,
    # registered after it (with the first rendering env made), runs first. Left to the garbage collector after that,
    # every context's release fails with an EGL error printed as a traceback.
    global _CLOSING_REGISTERED
    if not _CLOSING_REGISTERED:
        atexit.register(_close_rendering_envs)
        _CLOSING_REGISTERED = True
    _RENDERING.add(env)


def _close_rendering_envs() -> None:
    for env in list(_RENDERING):
        with contextlib.suppress(Exception):
            env.close()


def holds(env, predicate: str) -> bool:
    """Whether the BDDL predicate `predicate` (e.g. ``(On plate_1 main_table_stove_front_region)``, ``(Turnon
    flat_stove_1)``) holds in `env` now, by LIBERO's own predicate functions."""
    name, *args = predicate.strip("()").split()
    return bool(env.env._eval_predicate([name.lower(), *args]))


def render_now(env, camera: str = "agentview", size: int = 128):
    """(size, size, 3) uint8: the env's current state seen from LIBERO camera `camera`, upright. MuJoCo's
    offscreen images come out rotated by 180 degrees (LIBERO's own observations too); every frame bpp stores,
    trains on or shows is turned upright here."""
    frame = env.env.sim.render(camera_name=camera, height=size, width=size)
    return np.ascontiguousarray(np.asarray(frame, dtype=np.uint8)[::-1, ::-1])


def render_states(env, states, camera: str = "agentview", size: int = 128):
    """(T, size, size, 3) uint8 upright frames of LIBERO camera `camera` for flattened simulator states (e.g. a
    stored episode's ``sim_state``), rendered by setting each state and drawing it. Training frames come from here,
    not from the env's observation dictionary: robosuite samples camera observables inside its control loop, so
    those lag the state stored at the end of a step (see docs/libero-gen.md). `env` must be able to render (made with
    cameras or with ``render=True``); its state is restored afterwards."""
    sim = env.env.sim
    saved = sim.get_state().flatten()
    frames = []
    try:
        for state in states:
            sim.set_state_from_flattened(np.asarray(state, dtype=np.float64))
            sim.forward()
            frames.append(render_now(env, camera, size))
    finally:
        sim.set_state_from_flattened(saved)
        sim.forward()
    return np.stack(frames)


def place_object(env, name: str, position) -> None:
    """Move object `name` (its free joint) to `position` (x, y, z), keeping its orientation (for tests and
    scripted checks of a problem's goal)."""
    sim = env.env.sim
    joint = f"{name}_joint0"
    qpos = np.array(sim.data.get_joint_qpos(joint), dtype=float)
    qpos[:3] = position
    sim.data.set_joint_qpos(joint, qpos)
    sim.forward()


MAX_FIXTURES = 8
"""Fixtures per scene a store keeps the pose of (LIBERO's scenes have up to 4: the table, a cabinet, a stove, a
rack)."""


def fixture_poses(env) -> tuple[list[str], np.ndarray]:
    """(names, (n, 7) position + wxyz quaternion) of the env's fixtures (table, cabinet, stove, ...) as its last reset
    placed them. LIBERO samples their placement at every reset (about a centimetre between seeds), and a fixture has
    no joint, so its pose is part of the model, not of the simulator state a demonstration stores."""
    inner = env.env
    names = sorted(inner.fixtures_dict)
    ids = [inner.sim.model.body_name2id(inner.fixtures_dict[name].root_body) for name in names]
    model = inner.sim.model
    return names, np.concatenate([model.body_pos[ids], model.body_quat[ids]], axis=1).astype(np.float64)


def fixture_row(env) -> tuple[list[str], np.ndarray]:
    """(names, (MAX_FIXTURES, 7) poses, NaN below the scene's fixtures): :func:`fixture_poses` as a store's
    per-episode column keeps them."""
    names, poses = fixture_poses(env)
    row = np.full((MAX_FIXTURES, 7), np.nan)
    row[: len(poses)] = poses
    return names, row


def place_fixtures(env, names: list[str], poses) -> None:
    """Put the env's fixtures where :func:`fixture_poses` found them (after a reset, before setting a state)."""
    inner = env.env
    if sorted(inner.fixtures_dict) != list(names):
        raise UserError(f"the scene's fixtures {sorted(inner.fixtures_dict)} are not the stored {list(names)}")
    for name, pose in zip(names, poses, strict=False):
        body = inner.sim.model.body_name2id(inner.fixtures_dict[name].root_body)
        inner.sim.model.body_pos[body] = pose[:3]
        inner.sim.model.body_quat[body] = pose[3:7]
    inner.sim.forward()


def seat(env, state=None) -> dict:
    """Start the env from simulator state `state` (default: its current one) with nothing else carried over from
    before: MuJoCo's solver warm start is cleared and the controllers recompute what they cache from the state. A
    demonstration starts this way and :func:`replay` starts this way, so that replaying its actions reproduces its
    states bit for bit (the physics is chaotic: a 1e-10 difference in the controller's cached end-effector pose grew to
    centimetres). Returns the observation."""
    inner = env.env
    obs = env.set_init_state(inner.sim.get_state().flatten() if state is None else np.asarray(state, np.float64))
    inner.sim.data.qacc_warmstart[:] = 0.0
    for robot in inner.robots:
        robot.controller.update(force=True)
    return obs


def reset_scene(env, seed: int, fixtures: tuple[list[str], np.ndarray] | None = None) -> None:
    """Reset `env` with `seed` and put its fixtures where a demonstration had them (``fixtures``: names and poses;
    None: where this reset put them, which only approximates the demonstration's scene)."""
    env.seed(int(seed))
    env.reset()
    if fixtures is not None:
        place_fixtures(env, *fixtures)


def replay(env, seed: int, states, actions, fixtures: tuple[list[str], np.ndarray] | None = None):
    """Replay a demonstration open-loop: rebuild its scene in `env` (made from its problem; :func:`reset_scene`), set
    its first simulator state and execute every action. Returns the simulator states before each action (as stored)
    and after the last one, and whether LIBERO's goal holds at the end."""
    reset_scene(env, seed, fixtures)
    seat(env, states[0])
    sim = env.env.sim
    seen = [sim.get_state().flatten()]
    for action in actions:
        env.step(np.asarray(action, dtype=np.float64))
        seen.append(sim.get_state().flatten())
    return np.stack(seen), bool(env.env._check_success())


class GoalOrder:
    """Whether the terms of an env's goal (a Chain's steps, in the problem's order) were reached in that order. Term k
    counts as reached at the first step where it holds, provided it last became true no earlier than term k-1 was
    reached; :attr:`done` when every term is reached and all of them hold. So a chain whose two steps are done the
    other way round is not done, although its final goal holds (LIBERO's own success, :meth:`final`). Construct it
    once the episode's start has settled, then call :meth:`update` after every step."""

    @classmethod
    def of(cls, env) -> GoalOrder | None:
        """The order of `env`'s goal, or None for a goal of one term (nothing to order)."""
        return cls(env) if len(env.env.parsed_problem["goal_state"]) > 1 else None

    def __init__(self, env):
        self.env = env
        self.terms = [list(t) for t in env.env.parsed_problem["goal_state"]]
        self.reached: list[int] = []
        self.rose = [0] * len(self.terms)
        self.held = [False] * len(self.terms)
        self.t = 0
        self._observe()

    def update(self) -> None:
        self.t += 1
        self._observe()

    def _observe(self) -> None:
        now = [bool(self.env.env._eval_predicate(term)) for term in self.terms]
        for k, (holds_now, held) in enumerate(zip(now, self.held, strict=True)):
            if holds_now and not held:
                self.rose[k] = self.t
        self.held = now
        while len(self.reached) < len(self.terms):
            k = len(self.reached)
            if not (now[k] and (k == 0 or self.rose[k] >= self.reached[-1])):
                break
            self.reached.append(self.t)

    @property
    def done(self) -> bool:
        return len(self.reached) == len(self.terms) and all(self.held)

    @property
    def final(self) -> bool:
        """Every term holds now, whatever the order (LIBERO's own success)."""
        return all(self.held)

    @property
    def first_reached(self) -> bool:
        return bool(self.reached)
