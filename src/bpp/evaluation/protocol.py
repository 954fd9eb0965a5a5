"""The evaluation protocol's plan and numbers, without the model: which rollouts each task gets
(:class:`Protocol`), one task's results (:class:`TaskResult`) and their summary. Importing it needs no torch, so that
a robot-side client (:mod:`bpp.serve.robot`) runs the same protocol against a policy server.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, get_args

import numpy as np

from bpp.core.contract import Benchmark, Metric, RolloutResult
from bpp.data.contexts import PROMPT_EDITS
from bpp.data.store import EpisodeStore
from bpp.errors import UserError
from bpp.utils import check_fields

PromptChoice = Literal["own", "other-task", "shuffled", "first-half", "none"]
PROMPT_CHOICES: tuple[str, ...] = get_args(PromptChoice)


@dataclass(frozen=True)
class Protocol:
    """Which rollouts are run for each task (identical for every method and checkpoint)."""

    rollouts: int = 32
    """Rollouts per task; prompts cycle through the task's demonstrations."""
    seed: int = 0
    max_steps: int = 0
    """Rollout length limit (0: the benchmark's own)."""
    prompts: PromptChoice = "own"
    """own: the paper's protocol. The controls, each scored against the task's own drawing or goal as usual:
    other-task: rollout r of task t (of n) is prompted with demonstration r mod (its demos) of task
    (t + 1 + r mod (n - 1)) mod n, never t itself; shuffled: with its own demonstration whose whole chunks of
    :data:`~bpp.data.contexts.CONTROL_CHUNK` steps are put in a random order (a shorter last chunk stays last);
    first-half: with the first half of its own demonstration's steps; none: with no prompt (a demonstration whose
    steps the policy attends to none of). A method whose context is not a demonstration (an instruction) gets its
    usual context under shuffled and first-half, an empty one under none; a goal image is the frame of the edited
    demonstration's latest step (under shuffled, its usual goal), and a goal-image method has no run without one."""
    n_action_steps: int = 0
    """Actions executed per inference (0: the checkpoint's Ta)."""
    inference_steps: int = 0
    """Denoising steps per inference of a diffusion decoder (0: the checkpoint's own)."""
    noise_scale: float | None = None
    """A diffusion decoder's initial noise times this (None: the checkpoint's own)."""
    tasks_per_batch: int = 1
    """Tasks whose rollouts step together as one batch through the policy, in the order of the evaluated task list
    (the batches depend on that list, never on the workers). More is faster on a CPU, whose kernels do more per call
    on larger batches; a task's scores then depend in their last bits on the tasks batched with it. A benchmark that
    keeps a simulator per rollout keeps that many more in memory."""

    def __post_init__(self):
        check_fields(
            self,
            ("rollouts", self.rollouts >= 1, ">= 1"),
            ("seed", self.seed >= 0, ">= 0"),
            ("max_steps", self.max_steps >= 0, ">= 0 (0: the benchmark's)"),
            ("prompts", self.prompts in PROMPT_CHOICES, f"one of {', '.join(PROMPT_CHOICES)}"),
            ("n_action_steps", self.n_action_steps >= 0, ">= 0 (0: the checkpoint's)"),
            ("inference_steps", self.inference_steps >= 0, ">= 0 (0: the checkpoint's)"),
            ("tasks_per_batch", self.tasks_per_batch >= 1, ">= 1"),
            ("noise_scale", self.noise_scale is None or 0 <= self.noise_scale <= 2, "in [0, 2] (None: the model's)"),
        )

    def agent_options(self) -> dict:
        """The :class:`~bpp.policies.agent.PolicyAgent` overrides this protocol asks for."""
        return {
            "n_action_steps": self.n_action_steps or None,
            "num_inference_steps": self.inference_steps or None,
            "noise_scale": self.noise_scale,
        }

    def plan(self, store: EpisodeStore, task: int, benchmark: Benchmark) -> list[dict]:
        """The rollouts of `task`: target episode (whose task scores it), prompt episode, the benchmark's conditions
        and a seed."""
        episodes = store.task_episodes()
        if self.prompts == "other-task" and len(episodes) < 2:
            raise UserError("an other-task prompt control needs a store with at least 2 tasks")
        demos = episodes[task]
        plan = []
        for r in range(self.rollouts):
            rng = np.random.default_rng([self.seed, task, r])
            target = int(demos[r % len(demos)])
            prompt = target
            if self.prompts == "other-task":
                other = episodes[(task + 1 + r % (len(episodes) - 1)) % len(episodes)]
                prompt = int(other[r % len(other)])
            conditions = benchmark.rollout_conditions(rng)
            clash = set(conditions) & {"rollout", "target_episode", "prompt_episode", "seed"}
            assert not clash, f"{benchmark.name}: rollout conditions {sorted(clash)} shadow the protocol's own fields"
            row = {"rollout": r, "target_episode": target, "prompt_episode": prompt, **conditions}
            row["seed"] = int(rng.integers(2**31))
            if self.prompts in PROMPT_EDITS:
                row["prompt_edit"] = self.prompts
            plan.append(row)
        return plan


@dataclass
class TaskResult:
    task: int
    task_id: str
    rollouts: list[dict]
    last_frame: np.ndarray | None = field(default=None, repr=False)  # rollout 0's outcome
    frames: list | None = field(default=None, repr=False)  # rollout 0's video frames, if asked for
    attention: np.ndarray | None = field(default=None, repr=False)  # rollout 0: (calls, n_chunks + 1)

    @property
    def mean(self) -> float:
        return float(np.mean([r["score"] for r in self.rollouts]))


def rollout_rows(benchmark: Benchmark, plan: list[dict], results: list[RolloutResult]) -> list[dict]:
    """One JSON row per rollout: its plan (conditions, prompt, seed), its score and steps, and the benchmark's
    extras."""
    clash = {*plan[0], "score", "steps"} & set(results[0].extra)
    assert not clash, f"{benchmark.name}: rollout extras {sorted(clash)} shadow the protocol's own fields"
    return [{**p, "score": r.score, "steps": r.steps, **r.extra} for p, r in zip(plan, results, strict=True)]


def summarize(results: list[TaskResult], metric: Metric) -> dict:
    """Mean over tasks of the per-task mean score, with the spread over tasks."""
    means = np.array([r.mean for r in results])
    scores = np.array([row["score"] for r in results for row in r.rollouts])
    return {
        "score_mean": float(means.mean()),
        "score_std_over_tasks": float(means.std()),
        "score_sem_over_tasks": float(means.std(ddof=1) / np.sqrt(len(means))) if len(means) > 1 else 0.0,
        "score_median_rollout": float(np.median(scores)),
        "good_rollouts": float(np.mean(metric.good(scores))),
        "tasks": len(results),
        "rollouts": int(scores.size),
    }


def results_json(results: list[TaskResult], meta: dict, metric: Metric) -> dict:
    return {
        **meta,
        "summary": summarize(results, metric),
        "tasks": [{"task": r.task, "task_id": r.task_id, "score_mean": r.mean} for r in results],
        "rollouts": [{"task": r.task, "task_id": r.task_id, **row} for r in results for row in r.rollouts],
    }
