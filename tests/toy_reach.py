"""A second, tiny benchmark that proves the benchmark contract (bpp.core.contract): 2-D point reaching.

A task is 2-4 waypoints in the unit square; a demonstration moves a point through them in order from a random start.
The policy observes the point's position (state only) and outputs the next target position; the point moves toward
it by at most ``MAX_STEP`` per step. A rollout scores the mean distance from each waypoint to the closest point of
its trajectory (lower is better). It generates, trains, evaluates and reports through the same commands as
DrawAnything, in seconds.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from bpp.core.contract import Metric, RolloutResult, TaskSet
from bpp.data.spec import ObservationPreset
from bpp.data.store import EpisodeStore, EpisodeWriter

MAX_STEP = 0.05
SIZE = 48  # pixels of the pictures


@dataclass(frozen=True)
class ReachDataConfig:
    num_tasks: int = 6
    demos_per_task: int = 3
    seed: int = 0

    def __post_init__(self):
        if self.num_tasks < 1 or self.demos_per_task < 1:
            raise ValueError("num_tasks and demos_per_task must be >= 1")


def step(pos: np.ndarray, target: np.ndarray) -> np.ndarray:
    move = np.asarray(target, dtype=np.float64) - pos
    norm = np.linalg.norm(move)
    return pos + (move if norm <= MAX_STEP else move * MAX_STEP / norm)


def demonstrate(waypoints: np.ndarray, start: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray]:
    pos, positions, actions = np.asarray(start, dtype=np.float64), [], []
    for waypoint in waypoints:
        while np.linalg.norm(waypoint - pos) > 0.02:
            target = waypoint + rng.normal(0, 0.005, 2)
            positions.append(pos)
            actions.append(target)
            pos = step(pos, target)
    positions.append(pos)
    actions.append(pos)  # stay
    return {"pos": np.asarray(positions, np.float32), "action": np.asarray(actions, np.float32)}


def score(waypoints: np.ndarray, trajectory: np.ndarray) -> float:
    gaps = np.linalg.norm(waypoints[:, None] - trajectory[None], axis=-1)
    return float(gaps.min(axis=1).mean())


def picture(waypoints: np.ndarray, trajectory: np.ndarray) -> np.ndarray:
    image = np.full((SIZE, SIZE, 3), 255, np.uint8)
    for x, y in np.clip((trajectory * (SIZE - 1)).round().astype(int), 0, SIZE - 1):
        image[SIZE - 1 - y, x] = (40, 40, 200)
    for x, y in np.clip((waypoints * (SIZE - 1)).round().astype(int), 0, SIZE - 1):
        image[max(0, SIZE - 2 - y) : SIZE - y, x : x + 2] = (220, 30, 30)
    return image


class Reach:
    name = "reach"
    command = "reach"
    description = "2-D point reaching through waypoints (a test benchmark)"
    data_config = ReachDataConfig
    data_presets = {"debug": ReachDataConfig()}
    default_data_dir = Path("data/reach")
    derived_keys: Mapping[str, tuple[str, tuple[int, ...]]] = {}
    observations: Mapping[str, ObservationPreset] = {"state": ObservationPreset(proprio_keys=("pos",))}
    metric = Metric("waypoint miss", lower_is_better=True, good_threshold=0.05, description="mean waypoint miss")
    max_steps = 100
    task_sets: Mapping[str, str] = {}
    command_table = ""

    def default_observation(self, size: str) -> str:
        return "state"

    def generate(self, cfg, out, *, workers=0, overwrite=False, progress=True) -> EpisodeStore:
        rng = np.random.default_rng(cfg.seed)
        with EpisodeWriter(out, benchmark=self.name, config=asdict(cfg), overwrite=overwrite) as writer:
            for t in range(cfg.num_tasks):
                waypoints = [rng.uniform(0.1, 0.9, 2)]
                while len(waypoints) < int(rng.integers(2, 5)) + 1:  # legs of at least 0.4: demos of 16+ steps
                    candidate = rng.uniform(0.1, 0.9, 2)
                    if np.linalg.norm(candidate - waypoints[-1]) >= 0.4:
                        waypoints.append(candidate)
                waypoints = np.asarray(waypoints[1:])
                task = writer.add_task(f"reach-{t}", {"waypoints": len(waypoints)}, waypoints=waypoints)
                for _ in range(cfg.demos_per_task):
                    writer.add_episode(demonstrate(waypoints, rng.uniform(0.1, 0.9, 2), rng), task)
        return EpisodeStore(out)

    def frames(self, store, episode, key, size, last_only=False):
        raise ValueError("reach has no cameras")

    def task_set(self, name: str, data_dir: Path, workers: int = 0) -> TaskSet:
        raise ValueError(f"reach has no named task set {name!r}")

    def task_set_from_files(self, files: Sequence[Path], data_dir: Path, workers: int = 0) -> TaskSet:
        raise ValueError("reach takes no task files")

    def rollout_conditions(self, rng: np.random.Generator) -> dict:
        return {"start": rng.uniform(0.1, 0.9, 2).tolist()}

    def _waypoints(self, store: EpisodeStore, episode: int) -> np.ndarray:
        return store.task_array("waypoints", int(store.column("task_index")[episode]))

    def run_rollouts(self, agent, store, rollouts, max_steps, record_frames) -> list[RolloutResult]:
        key = agent.data_spec.action_key
        assert key == "action", key
        positions = np.array([row["start"] for row in rollouts], dtype=np.float64)
        trajectories = [[p.copy()] for p in positions]
        for _ in range(max_steps):
            actions = agent.act_batch({"pos": positions.astype(np.float32)})
            positions = np.stack([step(p, a) for p, a in zip(positions, actions, strict=True)])
            for trajectory, p in zip(trajectories, positions, strict=True):
                trajectory.append(p.copy())
        results = []
        for row, trajectory, record in zip(rollouts, trajectories, record_frames, strict=True):
            waypoints, trajectory = self._waypoints(store, int(row["target_episode"])), np.asarray(trajectory)
            frames = [picture(waypoints, trajectory[: i + 1]) for i in range(len(trajectory))] if record else []
            results.append(RolloutResult(score(waypoints, trajectory), max_steps, {}, frames))
        return results

    def prompt_picture(self, store: EpisodeStore, episode: int, size: int = 256) -> np.ndarray:
        return picture(self._waypoints(store, episode), store.episode(episode, ["pos"])["pos"])

    def describe_rollout(self, row: Mapping) -> str:
        return f"start ({row['start'][0]:.2f}, {row['start'][1]:.2f})"


BENCHMARK = Reach()
