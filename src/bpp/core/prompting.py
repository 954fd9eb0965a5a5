"""Prompted rollouts: steps 2 and 3 of the evaluation protocol (:mod:`bpp.core.contract`), shared by the
evaluator and the commands that run a single rollout."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from bpp.core.contract import Benchmark, RolloutResult
from bpp.data.contexts import prompt_steps, task_context
from bpp.data.store import EpisodeStore


def run_prompted(
    agent, benchmark: Benchmark, store: EpisodeStore, plan: Sequence[Mapping], max_steps: int, record_frames
) -> tuple[list[RolloutResult], list[np.ndarray] | None]:
    """Run `plan`'s rollouts in lockstep: each prompted with the task context of its ``prompt_episode`` (built by
    :func:`~bpp.data.contexts.task_context`, as in training) and seeded by its ``seed``; the benchmark scores each
    against its ``target_episode``. Returns the results and, if the agent records attention, each rollout's
    attention over its inference calls ((calls, C) arrays; else None)."""
    contexts = []
    for p in plan:
        episode = int(p["prompt_episode"])
        sl = store.episode_slice(episode)
        steps = prompt_steps(sl.stop - sl.start, p.get("prompt_edit"), int(p["seed"]))
        contexts.append(task_context(store, episode, agent.data_spec, benchmark.frames, steps=steps))
    agent.reset_batch(contexts, [int(p["seed"]) for p in plan])
    results = benchmark.run_rollouts(agent, store, plan, max_steps, record_frames)
    if not agent.attention_log:
        return results, None
    attention = np.stack(agent.attention_log, axis=1)  # (B, calls, C)
    return results, [attention[i, : -(-r.steps // agent.n_action_steps)] for i, r in enumerate(results)]
