"""Generate LIBERO-Gen demonstrations into the project's episode store (``bpp libero generate``).

    bpp libero generate --preset cpu --out data/libero/combination-train.zarr

Each task's problem is loaded without camera observations (physics only: rendering is about 10x slower than
physics on a CPU). The scripted demonstrator tries seeds until the task has ``demos_per_task`` demonstrations
that LIBERO's own predicate accepts, or ``max_tries`` have been spent; failures are counted, never stored. Per
step the store keeps the action (7-D OSC_POSE deltas and the gripper; also as ``action_abs``, its position part the
controller's position goal), LIBERO's ``robot0_proprio-state`` (39) and
``object-state`` (70) vectors, and the full simulator state, so that any camera can be rendered later from the
stored state. Per demonstration it keeps the final agent-view frame (the Goal-Image baseline's goal) and, if
``cameras`` are named, every step's frames, rendered from the stored states.

Tasks run in parallel over processes. Each finished task is written at once to a journal beside the store, so a
killed run resumes where it stopped (same command); the store itself is written atomically at the end and the
journal removed.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from tqdm import tqdm

from bpp.benchmarks.libero.chain import ChainTask
from bpp.benchmarks.libero.demonstrator import DemoConfig, demonstrate_task
from bpp.benchmarks.libero.sim import (
    CAMERAS,
    GOAL_BASE,
    absolute_actions,
    fixture_row,
    libero_problem,
    make_env,
    render_now,
    render_states,
    replay,
    spatial_problem,
)
from bpp.benchmarks.libero.suites import SUITES_BY_NAME, PickPlace, combination_problem, matches, parse_where
from bpp.data.destination import destination_lock
from bpp.data.integrity import StoreError, StoreKeyError
from bpp.data.store import EpisodeStore, EpisodeWriter
from bpp.errors import UserError
from bpp.executor import Executor, as_executor
from bpp.utils import atomic_path, check_fields, journal_folder, to_dict

BENCHMARK = "libero_gen"
GOAL_KEY = "goal_agentview"
"""Per-episode column: the demonstration's final agent-view frame (upright), the Goal-Image baseline's goal."""
FIXTURE_KEY = "fixture_pose"
"""Per-episode column: (8, 7) where the episode's reset put its scene's fixtures (position, wxyz quaternion), one row
per name in the task's ``info["fixtures"]``, NaN below them. With the episode's first ``sim_state`` it rebuilds the
exact scene (:func:`bpp.benchmarks.libero.sim.replay`)."""
ABSOLUTE_KEY = "action_abs"
"""Per-step key: the action with its position part as the controller's position goal (:func:`~bpp.benchmarks.libero.
sim.absolute_actions`), what the ``state-abs`` observations act with."""
STEP_KEYS = ("action", "proprio", "object_state", "sim_state")
PROPRIO_LAYOUT = {
    "joint_pos": range(0, 7),
    "joint_pos_cos": range(7, 14),
    "joint_pos_sin": range(14, 21),
    "joint_vel": range(21, 28),
    "eef_pos": range(28, 31),
    "eef_quat": range(31, 35),
    "gripper_qpos": range(35, 37),
    "gripper_qvel": range(37, 39),
}
"""The parts of LIBERO's (robosuite's) 39-D ``robot0_proprio-state``, by feature index."""
EEF = ("eef_pos", "eef_quat", "gripper_qpos")
"""The derived key ``eef``: the gripper's pose and opening (9 of the 39 features), what LIBERO's own datasets and
robomimic's low-dimensional policies observe of the robot; the joints' angles and velocities are left out."""
EEF_FEATURES = tuple(i for part in EEF for i in PROPRIO_LAYOUT[part])
"""The feature indices of ``eef`` in ``proprio``."""
DERIVED_KEYS = {"eef": ("proprio", EEF_FEATURES)}
"""The benchmark's derived per-step keys (:attr:`bpp.core.contract.Benchmark.derived_keys`): ``eef``, the gripper's
pose and opening out of the robot's proprioception (the ``state-eef`` observations)."""


@dataclass(frozen=True)
class LiberoDataConfig:
    """Which tasks to demonstrate, how many times, and which frames to render into the store."""

    suite: str = "combination"
    """combination or chain (LIBERO-Gen), chain_no_second_step (Chain without its second-step tasks),
    chain_candidates (every chain the candidate rule generates, 218 training + the 10 held out), or
    libero_spatial / libero_goal (LIBERO's own 10 tasks of that suite, evaluated from LIBERO's initial states)."""
    split: Literal["train", "test"] = "train"
    """train: the suite's training tasks; test: its held-out tasks."""
    num_tasks: int = 0
    """Tasks of the split to demonstrate, spread evenly over it (0: all)."""
    task_indices: tuple[int, ...] = ()
    """Exactly these tasks of the split (indices, as ``bpp libero tasks`` lists them) instead of num_tasks."""
    where: str | None = None
    """A view: only the split's tasks whose fields match, e.g. ``pick=TD`` or ``view!=second_step`` (see
    :func:`bpp.benchmarks.libero.suites.matches`; default: every task, and an empty view is refused). Tasks keep their
    index in the split, so their seeds too."""
    demos_per_task: int = 5
    max_tries: int = 0
    """Demonstration attempts per task at most (0: twice the demonstrations plus two)."""
    seed: int = 0
    cameras: tuple[str, ...] = ()
    """Cameras whose frames are rendered for every step into the store (agentview, eye_in_hand); image policies
    need them (the state-only preset does not)."""
    image_size: int = 128
    goal_size: int = 128
    """Size of each demonstration's stored final agent-view frame, the Goal-Image baseline's goal (0: none, a
    state-only store: generation builds its envs without textures and draws nothing; Goal-Image then renders each
    goal from the demonstration's last state when it first needs it)."""
    demo: DemoConfig = field(default_factory=DemoConfig)

    def __post_init__(self):
        check_fields(
            self,
            ("suite", self.suite in SUITES_BY_NAME, f"one of {', '.join(SUITES_BY_NAME)}"),
            ("num_tasks", self.num_tasks >= 0, ">= 0 (0: all)"),
            ("task_indices", all(i >= 0 for i in self.task_indices), "indices >= 0"),
            ("demos_per_task", 1 <= self.demos_per_task <= 1000, "in [1, 1000]"),
            ("max_tries", 0 <= self.max_tries <= 100_000, "in [0, 100000] (0: automatic)"),
            ("seed", self.seed >= 0, ">= 0"),
            ("cameras", set(self.cameras) <= set(CAMERAS), f"a subset of {', '.join(CAMERAS)}"),
            ("image_size", 8 <= self.image_size <= 512, "in [8, 512] px"),
            ("goal_size", self.goal_size == 0 or 8 <= self.goal_size <= 512, "0 or in [8, 512] px"),
            ("demo.action_noise", 0.0 <= self.demo.action_noise <= 1.0, "in [0, 1] (action units)"),
            ("demo.rim_side", self.demo.rim_side in ("random", "near"), "random or near"),
            ("demo.max_steps", self.demo.max_steps >= 1, ">= 1"),
        )
        if self.where is not None:
            parse_where(self.where)  # a malformed view is refused when the config is built, quoting it

    @property
    def tries(self) -> int:
        return self.max_tries or 2 * self.demos_per_task + 2

    @property
    def original(self) -> bool:
        """Whether the suite is one of LIBERO's own (its problems verbatim, its initial states for rollouts)."""
        return SUITES_BY_NAME[self.suite]().original

    def tasks(self) -> list[tuple[int, PickPlace | ChainTask]]:
        """(index in the split, task) of the tasks to demonstrate."""
        split = list(getattr(SUITES_BY_NAME[self.suite](), self.split))
        if not split:
            raise UserError(f"the {self.suite} suite has no {self.split} tasks")
        if self.task_indices:
            bad = [i for i in self.task_indices if i >= len(split)]
            if bad:
                raise UserError(f"task_indices {bad} out of range: {self.suite} {self.split} has {len(split)} tasks")
            outside = [i for i in self.task_indices if self.where is not None and not matches(split[i], self.where)]
            if outside:
                raise UserError(
                    f"task_indices {outside} are not in the view {self.where!r} (task_indices come from "
                    "--task-indices or the preset, e.g. debug's (0,)); give --task-indices with indices of tasks in "
                    "the view, or with none for all of them"
                )
            return [(i, split[i]) for i in sorted(set(self.task_indices))]
        chosen = [(i, t) for i, t in enumerate(split) if self.where is None or matches(t, self.where)]
        if not chosen:
            raise UserError(f"no {self.split} task of {self.suite} is in the view {self.where!r}")
        n = len(chosen) if not self.num_tasks else min(self.num_tasks, len(chosen))
        return [chosen[i] for i in np.unique(np.linspace(0, len(chosen) - 1, n).round().astype(int))]


PRESETS: dict[str, LiberoDataConfig] = {
    "cpu": LiberoDataConfig(demos_per_task=3),
    "held-out": LiberoDataConfig(split="test", demos_per_task=5),
    "libero-spatial": LiberoDataConfig(suite="libero_spatial", demos_per_task=5),
    "libero-goal": LiberoDataConfig(suite="libero_goal", demos_per_task=5, demo=DemoConfig(max_steps=1200)),
    "paper": LiberoDataConfig(demos_per_task=50, cameras=tuple(CAMERAS)),
    "debug": LiberoDataConfig(task_indices=(0,), demos_per_task=2, goal_size=32),
    "chain-cpu": LiberoDataConfig(suite="chain", demos_per_task=2, demo=DemoConfig(max_steps=1200)),
    "chain-held-out": LiberoDataConfig(suite="chain", split="test", demos_per_task=5, demo=DemoConfig(max_steps=1200)),
}
"""``cpu``: every Combination training task x 3 demonstrations, state only (about an hour on 2 cores);
``held-out``: the 10 held-out tasks x 5 (evaluation prompts); ``paper``: 50 per task with both cameras (LIBERO's
own count per task; the paper does not state LIBERO-Gen's); ``libero-spatial`` and ``libero-goal``: that LIBERO
suite's own 10 tasks x 5 (prompts for evaluating on it from LIBERO's initial states); ``debug``: one task x 2, for
tests; ``chain-cpu`` and ``chain-held-out``: ``cpu`` (with 2 demonstrations per task: a chain takes about twice as
long, so the 311 tasks also generate in about an hour on 2 cores) and ``held-out`` for the Chain suite (up to 1200
steps per demonstration: a chain is two operators in one episode, and the scripted push alone takes about 550)."""


def episode_fixtures(store: EpisodeStore, episode: int) -> tuple[list[str], np.ndarray] | None:
    """(names, poses) of the fixtures as `episode`'s reset placed them, or None for a store written before they were
    kept (its scenes are rebuilt from the episode's seed, which LIBERO does not reproduce exactly)."""
    try:
        poses = store.column(FIXTURE_KEY)[episode]
    except StoreKeyError:
        return None
    names = list(store.tasks[int(store.column("task_index")[episode])]["info"].get("fixtures", []))
    return names, np.asarray(poses[: len(names)], dtype=np.float64)


def replay_episode(env, store: EpisodeStore, episode: int) -> tuple[np.ndarray, bool]:
    """Replay stored `episode` open-loop in `env` (made from its task's problem) from its first simulator state,
    with its fixtures and the actions its controller received: (the simulator states before each action and after
    the last, whether LIBERO's goal holds at the end); see :func:`bpp.benchmarks.libero.sim.replay`."""
    actions = "executed_action" if "executed_action" in store.keys else "action"
    steps = store.episode(episode, ["sim_state", actions])
    seed = int(store.column("seed")[episode])
    return replay(env, seed, steps["sim_state"], steps[actions], episode_fixtures(store, episode))


def task_id(split: str, index: int, task: PickPlace | ChainTask) -> str:
    return f"{split}-{index:03d}-{task.name}"


def problem_text(task: PickPlace | ChainTask, original: bool = False) -> str:
    """The BDDL problem of a task: its scene's LIBERO problem, edited (or as LIBERO ships it, for `original` tasks)."""
    if original:
        return libero_problem(*task.libero_source)
    if isinstance(task, ChainTask):
        return task.problem(libero_problem("libero_goal", GOAL_BASE))
    return combination_problem(task, spatial_problem(task.scene.base))


# ----------------------------------------------------------------------------------------------- workers
def _task_job(job) -> tuple[dict, dict[str, np.ndarray]]:
    """Worker: demonstrate one task. Returns a summary (tries, demonstrations kept) and the demonstrations' arrays
    (``"<i>/<key>"``), which the generating process journals: a worker may run on another machine."""
    index, task, cfg = job

    summary = {"index": index, "kept": 0, "tries": 0}
    with tempfile.TemporaryDirectory(prefix="libero-task-") as folder:
        problem = Path(folder) / "task.bddl"
        problem.write_text(problem_text(task, cfg.original))
        env = make_env(problem, render=bool(cfg.cameras or cfg.goal_size))
        episodes: list[dict] = []
        try:
            for attempt in range(cfg.tries):
                if len(episodes) >= cfg.demos_per_task:
                    break
                seed = cfg.seed * 1_000_003 + index * 1009 + attempt
                demo = demonstrate_task(env, task, seed, cfg.demo)
                summary["tries"] += 1
                if not demo.success:
                    continue
                episode = {
                    "action": demo.actions.astype(np.float64),  # exactly what was commanded: the physics is chaotic
                    ABSOLUTE_KEY: absolute_actions(demo.actions, demo.observations["robot0_eef_pos"]),
                    "proprio": demo.observations["robot0_proprio-state"].astype(np.float32),
                    "object_state": demo.observations["object-state"].astype(np.float32),
                    "sim_state": demo.states.astype(np.float64),
                    "seed": np.int64(seed),
                }
                if demo.executed is not None:  # DART noise: the clean actions train, these replay
                    episode["executed_action"] = demo.executed.astype(np.float64)
                # where this reset put the fixtures: not in the simulator state
                summary["fixtures"], episode[FIXTURE_KEY] = fixture_row(env)
                if cfg.goal_size:
                    episode[GOAL_KEY] = render_now(env, CAMERAS["agentview"], cfg.goal_size)  # the final state
                for camera in cfg.cameras:
                    episode[camera] = render_states(env, demo.states, CAMERAS[camera], cfg.image_size)
                episodes.append(episode)
        finally:
            env.close()
    summary["kept"] = len(episodes)
    return summary, {f"{i}/{k}": v for i, ep in enumerate(episodes) for k, v in ep.items()}


def _write_journal(journal: Path, summary: dict, arrays: dict[str, np.ndarray]) -> None:
    with atomic_path(journal / f"task-{summary['index']:04d}.npz") as tmp:
        np.savez(tmp, summary=json.dumps(summary), **arrays)


def _read_journal(path: Path) -> tuple[dict, list[dict]]:
    with np.load(path) as data:
        summary = json.loads(str(data["summary"]))
        episodes: list[dict] = [{} for _ in range(summary["kept"])]
        for name in data.files:
            if name != "summary":
                i, key = name.split("/", 1)
                episodes[int(i)][key] = data[name]
    return summary, episodes


def generate(
    cfg: LiberoDataConfig,
    out: str | Path,
    workers: int | Executor = 0,
    overwrite: bool = False,
    progress: bool = True,
) -> EpisodeStore:
    """Demonstrate `cfg`'s tasks into the store `out`, over `workers` processes (0: one per core) or an
    :class:`~bpp.executor.Executor` (e.g. a Ray cluster), resuming a killed run's finished tasks: this process
    journals every task's demonstrations as they come back, and writes the store from the journal once all are in.
    The generation report (tries and successes per pick and per place, tasks left without a demonstration,
    demonstrations per hour) is printed and kept in the store's ``generation`` attribute."""
    out = Path(out)
    if out.exists() and not overwrite:
        raise StoreError(f"{out} already exists; pass overwrite=True (CLI: --overwrite) to replace it")
    # One generation per destination: another one would discard or delete this one's journal while it writes there.
    with destination_lock(out.with_name(f".{out.name}.journal")):
        return _generate(cfg, out, workers, overwrite, progress)


def _generate(cfg: LiberoDataConfig, out: Path, workers, overwrite: bool, progress: bool) -> EpisodeStore:
    tasks = cfg.tasks()
    journal = journal_folder(out, to_dict(cfg))
    done = {int(p.stem.split("-")[1]) for p in journal.glob("task-*.npz")}
    jobs = [(i, t, cfg) for i, t in tasks if i not in done]
    t0 = time.perf_counter()
    # Interrupted (Ctrl-C, SIGTERM through the CLI), the executor's workers are stopped and the journal keeps every
    # finished task for the next run.
    with contextlib.closing(as_executor(workers).map(_task_job, jobs)) as results:
        bar = tqdm(results, total=len(tasks), initial=len(tasks) - len(jobs), desc=f"demonstrating {out.name}",
                   unit="task", disable=not progress)  # fmt: skip
        made = 0
        for summary, arrays in bar:
            _write_journal(journal, summary, arrays)
            made += summary["kept"]
            bar.set_postfix(demos_per_hour=round(3600 * made / (time.perf_counter() - t0)))
    seconds = time.perf_counter() - t0
    timing = {"seconds_this_run": round(seconds, 1), "demos_per_hour_this_run": round(3600 * made / seconds, 1)}
    report = _write_store(cfg, tasks, journal, out, overwrite, timing)
    store = EpisodeStore(out)
    shutil.rmtree(journal, ignore_errors=True)
    if progress:
        print(describe_report(report))
    return store


def _write_store(cfg: LiberoDataConfig, tasks, journal: Path, out: Path, overwrite: bool, timing: dict) -> dict:
    """The store from the journal's tasks, in the split's order; returns the generation report and its timing."""
    tries, successes, missing, stored = Counter(), Counter(), [], 0
    stats_keys = ("action", ABSOLUTE_KEY, "proprio", "object_state")
    original = cfg.original
    with EpisodeWriter(
        out, benchmark=BENCHMARK, config=to_dict(cfg), overwrite=overwrite, stats_keys=stats_keys
    ) as writer:
        for index, task in tasks:
            summary, episodes = _read_journal(journal / f"task-{index:04d}.npz")
            for family in task.families:
                tries[family] += summary["tries"]
                successes[family] += summary["kept"]
            stored += len(episodes)
            if not episodes:
                missing.append(task.instruction)
                continue
            info = {k: v for k, v in task.describe().items() if k != "instruction"}
            info.update(suite=cfg.suite, split=cfg.split, problem=problem_text(task, original))
            info["fixtures"] = summary["fixtures"]  # the rows of each episode's fixture_pose
            if original:  # rollouts start from LIBERO's own initial states of the task
                info["initial_states"] = "{}/{}.pruned_init".format(*task.libero_source)
            task_index = writer.add_task(task_id(cfg.split, index, task), info, instruction=task.instruction)
            for episode in episodes:
                columns = {"seed": int(episode.pop("seed")), FIXTURE_KEY: episode.pop(FIXTURE_KEY)}
                if GOAL_KEY in episode:
                    columns[GOAL_KEY] = episode.pop(GOAL_KEY)
                writer.add_episode(episode, task_index, **columns)
        report = {
            "tasks": len(tasks),
            "stored": stored,
            "tries": dict(tries),
            "successes": dict(successes),
            "without_demonstrations": missing,
        }
        if not report["stored"]:
            writer.abort()
            raise StoreError(f"no demonstration of {len(tasks)} tasks succeeded; nothing to store")
        writer.root.attrs["generation"] = report
        writer.root.attrs["timing"] = timing  # how fast, not what: left out of the store's fingerprint
    return {**report, **timing}


def describe_report(report: dict) -> str:
    lines = [f"[generate] {report['stored']} demonstrations of {report['tasks']} tasks"]
    for family in sorted(report["tries"]):
        done, tries = report["successes"].get(family, 0), report["tries"][family]
        lines.append(f"  {family:11s} {done}/{tries} tries succeeded")
    if report["without_demonstrations"]:
        lines.append(f"  tasks left without a demonstration: {len(report['without_demonstrations'])}")
    if "demos_per_hour_this_run" in report:
        lines.append(f"  {report['demos_per_hour_this_run']} demonstrations per hour in this run")
    return "\n".join(lines)
