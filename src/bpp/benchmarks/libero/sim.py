"""LIBERO's simulator, reached through one place: where its problems are, and an env for a BDDL problem.

LIBERO is the ``libero`` extra (``pip install -e ".[libero]"``; ``make test`` installs it). Rendering goes through
MuJoCo's headless OpenGL: ``MUJOCO_GL`` defaults to ``egl`` here (Debian's Mesa provides it; ``osmesa`` needs
``libosmesa6``). An env without cameras renders nothing and is what demonstration generation uses (physics is about
10x faster than rendering two cameras on a CPU).

Two shortcuts keep LIBERO's results bit for bit and save most of its overhead: :func:`reset_env` resets without
rebuilding the model (LIBERO's own reset recompiles it and recreates the renderer's GL context every time), and
:func:`make_env` installs a step that runs MuJoCo's forward dynamics once per physics substep instead of three times
(:func:`_install_fast_step`). An env that renders nothing is compiled without the scene's textures
(:func:`without_textures`): the same physics, a third of the memory, a faster build.
"""

from __future__ import annotations

import atexit
import contextlib
import contextvars
import ctypes.util
import hashlib
import os
import weakref
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bpp.benchmarks.libero.substeps import pre_action
from bpp.errors import UserError
from bpp.media import headless_opengl


class LiberoUnavailable(UserError):
    """LIBERO (or its renderer) is missing; the message says what to install or set."""


RENDERER_LIBRARIES = {
    "egl": ("EGL", "libegl1 and libgl1-mesa-dri"),
    "osmesa": ("OSMesa", "libosmesa6"),
    "glfw": ("glfw", "libglfw3 (and a display)"),
}
"""MUJOCO_GL value -> (the shared library it loads, the Debian packages that provide it)."""


def _check_renderer() -> None:
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
    headless_opengl()
    _check_renderer()
    try:
        # LIBERO: the libero extra
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

POSITION_SCALE = 0.05
"""Metres per unit of an OSC_POSE action's position part: robosuite's controller sets its goal to the gripper's
position plus the action times this (its output_max over its input_max), LIBERO's setting."""


def absolute_actions(actions: np.ndarray, eef_pos: np.ndarray) -> np.ndarray:
    """OSC_POSE actions (..., 7) taken at gripper positions (..., 3) -> the same with the position part replaced by
    the position goal it gives the controller (m, the world frame of ``robot0_eef_pos``); rotation and gripper
    unchanged."""
    out = np.array(actions, dtype=np.float64)
    out[..., :3] = np.asarray(eef_pos, dtype=np.float64) + POSITION_SCALE * out[..., :3]
    return out


def delta_actions(actions: np.ndarray, eef_pos: np.ndarray) -> np.ndarray:
    """The inverse of :func:`absolute_actions`: position goals back to OSC_POSE deltas from `eef_pos`, clipped to the
    controller's [-1, 1] (a goal more than 5 cm away is approached at full speed)."""
    out = np.array(actions, dtype=np.float64)
    out[..., :3] = np.clip((out[..., :3] - np.asarray(eef_pos, dtype=np.float64)) / POSITION_SCALE, -1.0, 1.0)
    return out


def make_env(problem: str | Path, cameras: tuple[str, ...] = (), image_size: int = 128, render: bool = False):
    """A LIBERO env for the BDDL problem file `problem`: physics only without `cameras`, else rendering those
    cameras (LIBERO names, e.g. ``agentview``, ``robot0_eye_in_hand``) at `image_size` every step. With `render`
    and no cameras, steps render nothing but :func:`render_states` / :func:`render_now` can draw any camera on
    demand, through a renderer shared by every env of the same scene (:class:`SharedRenderer`); without either, it
    cannot draw, and its model is compiled without textures. Takes seconds (it compiles the scene). Reset it with
    :func:`reset_env`: its own ``env.reset()`` is LIBERO's, which builds and compiles the model again."""
    _libero()
    # LIBERO: the libero extra
    from libero.libero.envs.env_wrapper import ControlEnv, OffScreenRenderEnv

    _install_fast_step()
    _install_texture_free_build()

    path = Path(problem)
    if not path.is_file():
        raise UserError(f"{path}: no such BDDL problem")
    physics_only = _PHYSICS_ONLY.set(not cameras and not render)
    try:
        if not cameras:
            env = ControlEnv(
                bddl_file_name=str(path),
                horizon=HORIZON,
                has_renderer=False,
                has_offscreen_renderer=False,  # rendering goes through a SharedRenderer
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
        _raise_if_gl(err)
        raise
    finally:
        _PHYSICS_ONLY.reset(physics_only)
    # robosuite computes a reward at every step, and LIBERO's is one more evaluation of the goal's predicates: bpp
    # never reads it (success is the `done` a step returns, or the predicates themselves).
    env.env.reward = _no_reward
    _SOFT_RESETS[env.env] = _SoftReset.of(env.env)
    if render and not cameras:
        try:
            SharedRenderer.of(env.env.sim)
        except Exception as err:
            env.close()
            _raise_if_gl(err)
            raise
    if cameras:
        _close_at_exit(env)
    return env


_PHYSICS_ONLY = contextvars.ContextVar("physics_only", default=False)
"""Whether the env :func:`make_env` is building renders nothing (read when robosuite compiles its first model)."""


def without_textures(xml: str) -> str:
    """The MJCF model `xml` without its textures (and its materials without references to them). A LIBERO scene
    loads about 190 MB of texture images into every compiled model; physics never reads them: stepped with the same
    controls, a model with and one without them stay bit for bit the same (a test checks it)."""
    root = ET.fromstring(xml)
    for asset in root.iter("asset"):
        for texture in asset.findall("texture"):
            asset.remove(texture)
        for material in asset.findall("material"):
            material.attrib.pop("texture", None)
    return ET.tostring(root, encoding="unicode")


def _install_texture_free_build() -> None:
    """Make robosuite compile the models of an env that renders nothing without textures: its build (the first and
    every rebuild, LIBERO's hard resets included) passes the MJCF through :func:`without_textures`, robosuite's own
    hook for editing a model before it is compiled (``set_xml_processor``)."""
    global _ROBOSUITE_INITIALIZE_SIM
    if _ROBOSUITE_INITIALIZE_SIM is not None:
        return
    # robosuite: the libero extra
    from robosuite.environments.base import MujocoEnv

    initialize_sim = MujocoEnv._initialize_sim

    def _initialize_sim(self, xml_string=None):
        if _PHYSICS_ONLY.get() and self._xml_processor is None:
            self.set_xml_processor(without_textures)
        return initialize_sim(self, xml_string)

    _initialize_sim.__doc__ = initialize_sim.__doc__
    MujocoEnv._initialize_sim = _initialize_sim
    _ROBOSUITE_INITIALIZE_SIM = initialize_sim


_ROBOSUITE_INITIALIZE_SIM = None
"""robosuite's own ``MujocoEnv._initialize_sim``, once :func:`_install_texture_free_build` wrapped it."""


def _raise_if_gl(err: Exception) -> None:
    if "gl" in str(err).lower() or "egl" in type(err).__name__.lower():
        raise LiberoUnavailable(
            f"MuJoCo cannot render with MUJOCO_GL={os.environ.get('MUJOCO_GL')!r} ({err}); install Debian's "
            "libegl1 and libgl1-mesa-dri for egl, or libosmesa6 and set MUJOCO_GL=osmesa"
        ) from None


def _no_reward(action=None) -> float:
    return 0.0


def reset_env(env, seed: int) -> dict:
    """Reset `env` (made by :func:`make_env`) with placement seed `seed` and return the observation: the model,
    simulator state, fixture poses and observation LIBERO's own (hard) reset gives after the same history, bit for bit,
    without its cost. LIBERO's reset rebuilds the MJCF, compiles it, collects garbage and recreates the renderer's GL
    context (about 0.8 s physics only, 1.8 s with a renderer); this one resets the compiled model in place (about
    0.04 s), putting back what an episode changes in it and what a rebuilt model would start from (see
    :class:`_SoftReset`). After something else rebuilt the simulator (LIBERO's ``env.reset()``, or
    ``reset_from_xml_string``), it does LIBERO's reset once."""
    env.seed(int(seed))
    inner = env.env
    soft = _SOFT_RESETS.get(inner)
    if soft is None or soft.sim is not inner.sim:
        obs = env.reset()
        if soft is not None:
            _SOFT_RESETS[inner] = _SoftReset.of(inner, soft.initializers)
        return obs
    return soft.reset(inner)


@dataclass
class _SoftReset:
    """What a soft reset of one env puts back before resetting its compiled model in place (robosuite's
    ``hard_reset=False``), so that it gives what LIBERO's hard reset gives:

    - the fixtures' bodies at the pose the MJCF declares (none: the origin). LIBERO samples their placement at every
      reset and writes it into the compiled model, after placing the objects that stand in a fixture's region (a bowl
      in the cabinet's drawer) from where the region's site is in the model as it was before.
    - what MuJoCo derives from the bodies' poses when it compiles the model (``mj_setConst``: inverse weights, the
      mass matrix at the reference pose, cameras' offsets, the model's statistics), recomputed with the fixtures
      at the origin after :func:`derive_constants` recomputed it for a demonstration's fixtures.
    - the sites' colours as a new model has them: LIBERO shows a stove's burner when the stove is on, setting the
      colour after each step, and a state rendered right after a reset would show the last episode's. (The stove's
      flag that decides it needs nothing: LIBERO sets it from the knob's joint right before each use.)
    - the gripper's last command: robosuite's grippers integrate their commands, and a rebuilt model brings a new
      gripper at rest (kept, the next episode's first steps close or open it differently).
    - one more copy of the problem's joint initializers (a drawer opened or a stove turned on at the start): LIBERO
      appends them to a list at every model build and never clears it, and each draws from the seed's random stream
      before the objects' placements. A seed's scene depends on how many resets the env had; kept so that the same
      seed in the same history gives the same scene as before."""

    sim: object
    """The simulator this was taken of: another one (a rebuilt model) needs LIBERO's reset again."""
    body_pos: np.ndarray
    body_quat: np.ndarray
    site_rgba: np.ndarray
    initializers: list
    """The joint initializers one model build appends."""

    @classmethod
    def of(cls, inner, initializers: list | None = None) -> _SoftReset | None:
        """Taken of an env that has just been built or hard-reset (its model compiled from its own MJCF);
        `initializers`: those one build appends (default: all there are, right after construction). None if a fixture's
        MJCF declares a pose (its compiled pose is not known here; such an env always resets hard)."""
        model = inner.sim.model
        body_pos, body_quat = model.body_pos.copy(), model.body_quat.copy()
        bodies = {body.get("name"): body for body in inner.model.worldbody.iter("body")}
        for fixture in inner.fixtures_dict.values():
            declared = bodies[fixture.root_body]
            if declared.get("pos") is not None or declared.get("quat") is not None:
                return None
            index = model.body_name2id(fixture.root_body)
            body_pos[index], body_quat[index] = 0.0, (1.0, 0.0, 0.0, 0.0)
        initializers = list(inner.object_property_initializers if initializers is None else initializers)
        return cls(inner.sim, body_pos, body_quat, model.site_rgba.copy(), initializers)

    def reset(self, inner) -> dict:
        # robosuite: the libero extra
        from robosuite.utils.errors import RandomizationError

        hard = inner.hard_reset
        while True:  # LIBERO's ControlEnv.reset retries a placement that failed, rebuilding the model each time
            inner.object_property_initializers.extend(self.initializers)
            model = inner.sim.model
            model.body_pos[:], model.body_quat[:], model.site_rgba[:] = self.body_pos, self.body_quat, self.site_rgba
            if inner in _DERIVED:  # as compiling the model (the fixtures at the origin now) derives them
                _set_constants(model._model)
                _DERIVED.discard(inner)
            for robot in inner.robots:
                robot.gripper.current_action = np.zeros(robot.gripper.dof)
            inner.hard_reset = False
            try:
                return inner.reset()
            except RandomizationError:
                continue
            finally:
                inner.hard_reset = hard


_SOFT_RESETS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
"""LIBERO env -> its :class:`_SoftReset` (None: it always resets hard)."""


_ROBOSUITE_STEP = None
"""robosuite's own ``MujocoEnv.step``, once :func:`_install_fast_step` replaced it."""


def _install_fast_step() -> None:
    """Make robosuite's env step (``MujocoEnv.step``, which LIBERO's envs run) compute MuJoCo's forward dynamics once
    per physics substep instead of three times, with bit-identical results.

    robosuite's loop runs, per substep, ``mj_forward``, the robot's controller (whose update, robosuite's
    ``Controller.update`` or the ``libero_pro`` bridge's replacement, runs ``mj_forward`` again before reading the
    hand's pose, velocities, Jacobians and mass matrix) and ``mj_step``, which runs the forward dynamics a third time
    before integrating. Both extra calls compute what ``mj_step`` recomputes from the same state, so this step runs
    ``mj_step1`` (positions and velocities: everything the controller reads), the controller with its update's
    ``mj_forward`` skipped, then ``mj_step2`` (the controller's torques, accelerations, constraints, integration):
    ``mj_step``'s own work, split where MuJoCo provides for a controller. The split is exact for LIBERO's integrator,
    Euler; a model with another one steps as robosuite does. The first substep of a control step keeps one full
    ``mj_forward`` before the controller: there the robot also records the hand's force-torque sensor, a value of the
    acceleration stage. The observables are still updated at every substep: when they sample depends on a time
    counter each of them adds up substep by substep.

    The controller of a substep that is not a policy step runs without robosuite's per-call lookups
    (:mod:`bpp.benchmarks.libero.substeps`), with the same operations. A forced controller update (:func:`seat`)
    still runs its ``mj_forward``."""
    global _ROBOSUITE_STEP
    if _ROBOSUITE_STEP is not None:
        return
    # MuJoCo: the libero extra
    import mujoco
    from robosuite.environments.base import MujocoEnv

    robosuite_step = MujocoEnv.step

    def step(self, action):
        sim = self.sim
        model, data = sim.model._model, sim.data._data
        if model.opt.integrator != mujoco.mjtIntegrator.mjINT_EULER:
            return robosuite_step(self, action)
        if self.done:
            raise ValueError("executing action in terminated episode")
        self.timestep += 1
        for i in range(int(self.control_timestep / self.model_timestep)):
            if i == 0:
                sim.forward()
            else:
                mujoco.mj_step1(model, data)
            sim.forward = _computed  # the controller's update reads what was just computed
            try:
                pre_action(self, action, i == 0)
            finally:
                del sim.forward
            if i == 0:
                sim.step()
            else:
                mujoco.mj_step2(model, data)
            self._update_observables()
        self.cur_time += self.control_timestep
        reward, done, info = self._post_action(action)
        if self.viewer is not None and self.renderer != "mujoco":
            self.viewer.update()
        observations = self.viewer._get_observations() if self.viewer_get_obs else self._get_observations()
        return observations, reward, done, info

    step.__doc__ = robosuite_step.__doc__
    MujocoEnv.step = step
    _ROBOSUITE_STEP = robosuite_step
    _install_free_without_collection()


def _install_free_without_collection() -> None:
    """robosuite's ``MjSim.free`` (run when an env is closed) ends with ``gc.collect()``, a full collection of the
    process's heap: 0.1-0.3 s once torch is loaded, paid per task in generation and per rollout in evaluation. The
    references it drops free the model, its data and the renderer by reference counting, and Python's own collector
    takes any cycle left: closing ten envs in a row leaves the process's memory as flat as with the collection."""
    # robosuite: the libero extra
    from robosuite.utils.binding_utils import MjSim

    def free(self):
        del self._render_context_offscreen
        del self.data
        del self.model

    free.__doc__ = MjSim.free.__doc__
    MjSim.free = free


def _computed() -> None:
    """Stands in for ``MjSim.forward`` while the controller runs inside the fast step (the state is forwarded)."""


_RENDERING: weakref.WeakSet = weakref.WeakSet()
"""The envs with a renderer of their own (made with cameras) not yet garbage: closed at exit."""
_RELEASE_REGISTERED = False


def _close_at_exit(env) -> None:
    _RENDERING.add(env)
    _release_gl_at_exit()


def _release_gl_at_exit() -> None:
    # robosuite's GL context class terminates its EGL display at exit, from an exit handler it registers with its
    # first context; ours, registered after it (with the first context bpp makes or asks for), runs first. Left to
    # the garbage collector after that, every context's release fails with an EGL error printed as a traceback.
    global _RELEASE_REGISTERED
    if not _RELEASE_REGISTERED:
        atexit.register(_release_gl)
        _RELEASE_REGISTERED = True


def _release_gl() -> None:
    """Close the envs with renderers of their own and free the shared renderers, while the display still exists."""
    for env in list(_RENDERING):
        with contextlib.suppress(Exception):
            env.close()
    while SharedRenderer._kept:
        SharedRenderer._kept.popitem()[1].free()


def holds(env, predicate: str) -> bool:
    """Whether the BDDL predicate `predicate` (e.g. ``(On plate_1 main_table_stove_front_region)``, ``(Turnon
    flat_stove_1)``) holds in `env` now, by LIBERO's own predicate functions."""
    name, *args = predicate.strip("()").split()
    return bool(env.env._eval_predicate([name.lower(), *args]))


def render_now(env, camera: str = "agentview", size: int = 128):
    """(size, size, 3) uint8: the env's current state seen from LIBERO camera `camera`, upright. MuJoCo's
    offscreen images come out rotated by 180 degrees (LIBERO's own observations too); every frame bpp stores,
    trains on or shows is turned upright here.

    The state is drawn as it is, whatever MuJoCo computed last: after a step, the simulator's body and geom poses
    are those of the start of its last substep (MuJoCo integrates after computing them), so drawing them would show
    the scene 2 ms earlier than the state a rollout observes, and than the state a training frame is rendered from
    (:func:`render_states`). The poses are computed in a copy of the simulator's data (:meth:`_View.drawn`), so
    rendering never changes what the env computes next. (An env made with cameras draws through robosuite's own
    renderer, from the simulator's data as it is: tests compare the two.)"""
    sim = env.env.sim
    if sim._render_context_offscreen is not None:  # an env made with cameras: its own renderer
        sim._render_context_offscreen.gl_ctx.make_current()  # robosuite draws into whichever context is current
        frame = sim.render(camera_name=camera, height=size, width=size)
    elif env.env._xml_processor is without_textures:
        raise ValueError("this LIBERO env renders nothing (its model has no textures): make it with render=True")
    else:
        groups = {0: env.env.render_collision_mesh, 1: env.env.render_visual_mesh}  # as robosuite sets its renderer's
        frame = SharedRenderer.of(sim).render(sim, camera, size, groups)
    return np.ascontiguousarray(np.asarray(frame, dtype=np.uint8)[::-1, ::-1])


class SharedRenderer:
    """An OpenGL context with MuJoCo's render context (the scene's textures and meshes uploaded) for every env whose
    model has the same rendering assets: the tasks of one LIBERO scene differ in where things are, not in what they
    look like. Making one costs about a second on a CPU (0.8 s of it uploads the scene's 188 MB of textures to a
    software renderer), which robosuite paid for every env: per task in generation (for its goal frames), per
    rollout in an evaluation with cameras. Frames are drawn exactly as robosuite's own renderer draws them (its GL
    context class, the same MuJoCo calls and options): bit for bit the same, which a test checks.

    The last :data:`SHARED_RENDERERS` are kept (a worker visits the tasks of a scene together); they are freed at exit
    while their OpenGL display still exists."""

    _kept: dict[str, SharedRenderer] = {}

    def __init__(self, model):
        # robosuite: the libero extra
        from robosuite.utils.binding_utils import GLContext  # the class robosuite picks for MUJOCO_GL

        self.gl = GLContext(max_width=640, max_height=480, device_id=-1)
        self.gl.make_current()
        self._upload(model)
        _release_gl_at_exit()

    def _upload(self, model) -> None:
        """MuJoCo's render context for `model` (its assets and offscreen buffer), as robosuite's renderer makes it."""
        # MuJoCo: the libero extra
        import mujoco

        self.con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self.con)

    @classmethod
    def of(cls, sim) -> SharedRenderer:
        """The renderer for `sim`'s model (robosuite's ``MjSim``), made on first need."""
        key = _view(sim).assets
        renderer = cls._kept.pop(key, None) or cls(sim.model._model)
        cls._kept[key] = renderer  # the most recently used last
        while len(cls._kept) > SHARED_RENDERERS:
            cls._kept.pop(next(iter(cls._kept))).free()
        return renderer

    def render(self, sim, camera: str, size: int, groups: dict[int, bool]) -> np.ndarray:
        """(size, size, 3) uint8, as MuJoCo's offscreen buffer holds it (upside down): `sim`'s state from `camera`,
        with the geom groups `groups` (group -> shown) shown or hidden."""
        # MuJoCo: the libero extra
        import mujoco

        model = sim.model._model
        view = _view(sim)
        data = view.drawn(model, sim.data._data)
        view.camera.fixedcamid = model.camera(camera).id
        for group, shown in groups.items():
            view.option.geomgroup[group] = int(shown)
        self.gl.make_current()
        if size > self.con.offWidth or size > self.con.offHeight:  # as robosuite's renderer grows its buffer
            model.vis.global_.offwidth = max(size, model.vis.global_.offwidth)
            model.vis.global_.offheight = max(size, model.vis.global_.offheight)
            self.con.free()
            self._upload(model)
        viewport = mujoco.MjrRect(0, 0, size, size)
        mujoco.mjv_updateScene(
            model, data, view.option, view.perturb, view.camera, mujoco.mjtCatBit.mjCAT_ALL, view.scene
        )
        mujoco.mjr_render(viewport, view.scene, self.con)
        frame = np.empty((size, size, 3), dtype=np.uint8)
        mujoco.mjr_readPixels(frame, None, viewport, self.con)
        return frame

    def free(self) -> None:
        with contextlib.suppress(Exception):
            self.gl.make_current()
            self.con.free()
        with contextlib.suppress(Exception):
            self.gl.free()


SHARED_RENDERERS = 2
"""Renderers of different scenes one process keeps."""


class _View:
    """An env's scene, camera and options, as robosuite's renderer sets them up (default options, a fixed camera),
    the digest of its model's rendering assets (which shared renderer draws it), and the data it is drawn from."""

    def __init__(self, model):
        # MuJoCo: the libero extra
        import mujoco

        self.assets = render_assets_digest(model)
        self.scene = mujoco.MjvScene(model, maxgeom=1000)
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self.option = mujoco.MjvOption()
        self.perturb = mujoco.MjvPerturb()
        self.perturb.active = 0
        self.perturb.select = 0
        self.perturb.skinselect = -1
        self._drawn = None

    def drawn(self, model, data):
        """A copy of `data` with everything computed for its current state (what is drawn): the view's own, kept."""
        # MuJoCo: the libero extra
        import mujoco

        if self._drawn is None:
            self._drawn = mujoco.MjData(model)
        mujoco.mj_copyData(self._drawn, model, data)
        mujoco.mj_forward(model, self._drawn)
        return self._drawn


_VIEWS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
"""robosuite's ``MjSim`` -> its :class:`_View`."""


def _view(sim) -> _View:
    view = _VIEWS.get(sim)
    if view is None:
        view = _VIEWS[sim] = _View(sim.model._model)
    return view


_RENDER_ASSETS = ("tex_", "mesh_", "hfield_", "skin_", "flex_")
"""What MuJoCo's render context uploads from a model (with the model's visual settings)."""


def render_assets_digest(model) -> str:
    """A digest of what MuJoCo's render context takes from `model` (textures, meshes, height fields, skins, flexes and
    the visual settings): two models with the same one render the same with the same render context."""
    digest = hashlib.sha1(usedforsecurity=False)
    for name in sorted(n for n in dir(model) if n.startswith(_RENDER_ASSETS)):
        value = getattr(model, name)
        if isinstance(value, np.ndarray):
            digest.update(f"{name}{value.dtype}{value.shape}".encode())
            digest.update(np.ascontiguousarray(value).data)
    for group in ("global_", "quality", "headlight", "map", "scale", "rgba"):
        digest.update(repr(getattr(model.vis, group)).encode())
    return digest.hexdigest()


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


COMPILED_CONSTANTS = (
    "body_subtreemass",
    "body_invweight0",
    "dof_invweight0",
    "dof_M0",
    "cam_pos0",
    "cam_poscom0",
    "cam_mat0",
    "light_pos0",
    "light_poscom0",
    "light_dir0",
    "tendon_length0",
    "tendon_invweight0",
    "actuator_length0",
    "actuator_acc0",
    "dof_length",
    "eq_data",
)
"""The model's arrays MuJoCo derives from the bodies' poses when it compiles a scene (``mj_setConst``), besides its
statistics (``stat``)."""


_DERIVED: weakref.WeakSet = weakref.WeakSet()
"""The LIBERO envs whose constants :func:`derive_constants` recomputed since their last reset."""


def _set_constants(model) -> None:
    # MuJoCo: the libero extra
    import mujoco

    mujoco.mj_setConst(model, mujoco.MjData(model))  # a data of its own: the simulator's state is left as it is


def derive_constants(env) -> None:
    """Recompute what MuJoCo derives from the bodies' poses when it compiles a scene (``mj_setConst``: among them
    :data:`COMPILED_CONSTANTS`, the inverse weights its constraint solver scales contacts by and the cameras' and
    lights' offsets, and the model's statistics) for where the fixtures stand now, as compiling the scene's MJCF (an
    export's ``model_file``) gives them. LIBERO compiles a scene with its fixtures at the origin and then moves them,
    so its model keeps the origin's: a drawer joint's inverse weight then differs from the file's by about 6e-17, and
    a replay in the file leaves a demonstration where its hand pushes the drawer. The next :func:`reset_env` derives
    them again with the fixtures at the origin, as LIBERO's reset does."""
    _set_constants(env.env.sim.model._model)
    _DERIVED.add(env.env)


def place_fixtures(env, names: list[str], poses) -> None:
    """Put the env's fixtures where :func:`fixture_poses` found them (after a reset, before setting a state), with
    the constants MuJoCo derives from their poses (:func:`derive_constants`), as a demonstration had them."""
    inner = env.env
    if sorted(inner.fixtures_dict) != list(names):
        raise UserError(f"the scene's fixtures {sorted(inner.fixtures_dict)} are not the stored {list(names)}")
    for name, pose in zip(names, poses, strict=False):
        body = inner.sim.model.body_name2id(inner.fixtures_dict[name].root_body)
        inner.sim.model.body_pos[body] = pose[:3]
        inner.sim.model.body_quat[body] = pose[3:7]
    derive_constants(env)
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
    reset_env(env, seed)
    if fixtures is not None:
        place_fixtures(env, *fixtures)


def replay(env, seed: int, states, actions, fixtures: tuple[list[str], np.ndarray] | None = None):
    """Replay a demonstration open-loop: rebuild its scene in `env` (made from its problem; :func:`reset_scene`), set
    its first simulator state and execute every action. Returns the simulator states before each action (as stored)
    and after the last one, and whether LIBERO's goal holds at the end."""
    reset_scene(env, seed, fixtures)
    return replay_from(env, states[0], actions)


def replay_from(env, state, actions):
    """:func:`replay` in the scene `env` holds now: seated in simulator state `state`, then every action executed."""
    seat(env, state)
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
