"""LIBERO-Gen as a benchmark (the contract of :mod:`bpp.core.contract`): its data, observation settings, task
sets, rollouts scored by LIBERO's predicates, and pictures.

Everything that touches LIBERO itself is imported when used, so the registry can list this benchmark (and
``bpp --help`` describe it) on an install without the ``libero`` extra; using it without LIBERO says what to install.
"""

from __future__ import annotations

import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from bpp.benchmarks.libero import dataset
from bpp.benchmarks.libero.rollouts import run_rollouts, task_problem
from bpp.benchmarks.libero.sim import CAMERAS, make_env, render_states, reset_scene
from bpp.core.contract import Metric, RolloutResult, TaskSet
from bpp.data.spec import ObservationPreset
from bpp.data.store import EpisodeStore, stored_or_made
from bpp.errors import UserError
from bpp.media import resize_frames

STATE = ObservationPreset(
    proprio_keys=("proprio",),
    lowdim_keys=("object_state",),
    goal_camera="agentview",
    description=(
        "state only: the robot's proprioception (LIBERO's robot0_proprio-state, 39) and every object's pose and "
        "pose relative to the gripper (object-state, 70), what the simulator knows; for CPUs. Not the paper's "
        "setting (cameras), and named as such wherever it is used"
    ),
)
STATE_EEF = replace(
    STATE,
    proprio_keys=("eef",),
    description=(
        "state only, with the robot's gripper pose and opening (9 features, robomimic's and LIBERO's low-dimensional "
        "choice) instead of all 39 proprioception features (joint angles and velocities left out); otherwise as state"
    ),
)
STATE_ABS = replace(
    STATE,
    action_key="action_abs",
    description=(
        "state only, acting with the controller's position goal (the gripper's position plus the OSC_POSE delta, "
        "in metres) instead of the delta: a chunk of actions stays anchored where the demonstration went, as "
        "Diffusion Policy's position control; otherwise as state"
    ),
)
IMAGE = ObservationPreset(
    image_keys=("agentview", "eye_in_hand"),
    proprio_keys=("proprio",),
    image_size=128,
    goal_camera="agentview",
    description="the paper's setting: the agent-view and wrist cameras at 128x128 and proprioception (for GPUs)",
)


class LiberoGen:
    """LIBERO-Gen: procedurally generated LIBERO tasks; a policy does an unseen task from one demonstration."""

    name = dataset.BENCHMARK
    command = "libero"
    control_hz = 20
    """Actions per second of its robot: LIBERO's control_freq, which :func:`make_env` leaves at its default."""
    command_table = "bpp.benchmarks.libero.commands:COMMANDS"
    description = (
        "LIBERO-Gen: pick-and-place tasks (Combination) and two-step chains (Chain) in LIBERO from one demonstration "
        "(success by LIBERO's predicates)"
    )
    data_config = dataset.LiberoDataConfig
    data_presets = dataset.PRESETS
    default_data_dir = Path("data/libero")
    derived_keys = dataset.DERIVED_KEYS
    """``eef``: the gripper's pose and opening out of the robot's proprioception (the ``state-eef`` observations)."""
    observations: Mapping[str, ObservationPreset] = {
        "state": STATE,
        "state-eef": STATE_EEF,
        "state-abs": STATE_ABS,
        "image": IMAGE,
    }
    metric = Metric(
        "success",
        lower_is_better=False,
        good_threshold=1.0,
        description=(
            "1 if the task's goal predicates (LIBERO's own check) held at some step of the rollout, else 0; a Chain "
            "task's two steps must be done in their order (its final_goal column ignores the order, first_step "
            "counts the first step alone)"
        ),
    )
    max_steps = 550
    """The authors' step limit (ANCHORS.md)."""
    _task_sets = {
        "held-out": (
            "held-out Combination tasks",
            "the Combination suite's 10 held-out tasks x 5 demonstrations (generated on first use)",
        ),
        "chain-held-out": (
            "unseen Chain chains (success: both steps, in their order)",
            "the Chain suite's 10 unseen chains x 5 demonstrations (generated on first use)",
        ),
        "libero-spatial": (
            "LIBERO-Spatial's own tasks",
            "LIBERO-Spatial's own 10 tasks x 5 demonstrations, from LIBERO's initial states",
        ),
        "libero-goal": (
            "LIBERO-Goal's own tasks",
            "LIBERO-Goal's own 10 tasks x 5 demonstrations, from LIBERO's initial states",
        ),
    }
    """Named task sets: (label in reports, description). Each is the data preset of the same name."""
    task_sets = {name: description for name, (_, description) in _task_sets.items()}

    def default_observation(self, size: str) -> str:
        return "image" if size == "paper" else "state"

    def generate(self, cfg, out: Path, *, workers: int = 0, overwrite: bool = False, progress: bool = True):
        return dataset.generate(cfg, out, workers=workers, overwrite=overwrite, progress=progress)

    def frames(
        self, store: EpisodeStore, episode: int, key: str, size: int, last_only: bool = False, steps=None
    ) -> np.ndarray:
        """Stored frames if generation rendered them (resized if need be), else rendered from the stored states."""
        if key not in CAMERAS:
            raise UserError(f"LIBERO-Gen has the cameras {', '.join(CAMERAS)}; got {key!r}")
        if last_only and key == "agentview":
            try:
                return resize_frames(store.column(dataset.GOAL_KEY)[episode][None], size)
            except KeyError:
                pass
        sl = store.episode_slice(episode)
        if last_only:
            sl = slice(sl.stop - 1, sl.stop)
        elif steps is not None:
            sl = sl.start + np.asarray(steps, dtype=np.int64)
        source = key if key in store.keys else "sim_state"
        rows = store[source][sl] if isinstance(sl, slice) else store[source].oindex[sl]
        if key in store.keys:
            return resize_frames(rows, size)
        return _render(store, episode, rows, CAMERAS[key], size)

    # ------------------------------------------------------------ evaluation
    def task_set(self, name: str, data_dir: Path, workers: int = 0) -> TaskSet:
        if name not in self.task_sets:
            raise UserError(f"LIBERO-Gen has no task set {name!r}; named sets: {', '.join(self.task_sets)}")
        cfg = dataset.PRESETS[name]
        path = Path(data_dir) / f"task-set-{name}.zarr"

        def make(path: Path) -> EpisodeStore:
            print(f"[eval] generating the task set {name!r} into {path} (once; minutes)")
            return dataset.generate(cfg, path, workers, overwrite=True)

        return TaskSet(stored_or_made(path, make, cfg), self._task_sets[name][0])

    def task_set_from_files(self, files: Sequence[Path], data_dir: Path, workers: int = 0) -> TaskSet:
        raise UserError("LIBERO-Gen takes no task files yet; evaluate on a named task set (held-out) or a store")

    def rollout_conditions(self, rng: np.random.Generator) -> dict:
        return {"init_seed": int(rng.integers(0, 2**31 - 1))}

    def run_rollouts(self, agent, store, rollouts, max_steps, record_frames) -> list[RolloutResult]:
        return run_rollouts(agent, store, rollouts, max_steps, record_frames)

    def prompt_picture(self, store: EpisodeStore, episode: int, size: int = 256) -> np.ndarray:
        return self.frames(store, episode, "agentview", size, last_only=True)[0]

    def describe_rollout(self, row: Mapping) -> str:
        return f"initial state {row['init_seed']}"


_RENDER_ENV: dict = {}
"""One env kept for rendering stored states: its problem text, env and folder."""


def _render(store: EpisodeStore, episode: int, states: np.ndarray, camera: str, size: int) -> np.ndarray:
    """Frames of stored states of `episode`. The env is reset with the episode's own seed and its fixtures are put
    where the episode had them: their placement (cabinet, stove: about 1.5 cm between resets) is part of the model,
    not of the stored state."""
    problem = task_problem(store, episode)
    if _RENDER_ENV.get("problem") != problem:
        if "env" in _RENDER_ENV:
            _RENDER_ENV.pop("env").close()
            _RENDER_ENV.pop("folder").cleanup()
        folder = tempfile.TemporaryDirectory(prefix="libero-render-")  # the env may read its problem again
        path = Path(folder.name) / "task.bddl"
        path.write_text(problem)
        _RENDER_ENV.update(problem=problem, env=make_env(path, render=True), folder=folder)
    env = _RENDER_ENV["env"]
    reset_scene(env, int(store.column("seed")[episode]), dataset.episode_fixtures(store, episode))
    return render_states(env, states, camera, size)


BENCHMARK = LiberoGen()
