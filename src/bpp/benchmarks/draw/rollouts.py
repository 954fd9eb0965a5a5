"""DrawAnything rollouts: a policy, already given each rollout's task context, draws on boards at new angles.

Many rollouts run in lockstep through one batched agent, so a task's 32 rollouts cost about as many network calls
as one. A rollout scores the best Chamfer distance to its target drawing reached during the episode (the paper's
protocol).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from bpp.benchmarks.draw.dataset import episode_paths
from bpp.benchmarks.draw.env import ACTION_FRAMES, DrawEnv
from bpp.core.contract import RolloutResult, frames_to_record
from bpp.data.store import EpisodeStore
from bpp.drawing.geometry import canvas_to_upright
from bpp.errors import UserError


def prompt_target(store: EpisodeStore, episode: int) -> list[np.ndarray]:
    """The demonstration's own ink, upright: the target a rollout is scored against (as in the paper)."""
    angle = float(store.column("board_angle")[episode])
    return [canvas_to_upright(p, angle) for p in episode_paths(store, episode)]


def run_rollouts(
    agent,
    store: EpisodeStore,
    rollouts: Sequence[Mapping],
    max_steps: int = 400,
    record_frames: Sequence[bool | str] | None = None,
    render_size: int = 256,
) -> list[RolloutResult]:
    """Rollout i draws on a board at ``rollouts[i]["board_angle"]``, seeded by ``rollouts[i]["seed"]`` (cursor
    start), and is scored against the drawing of ``rollouts[i]["target_episode"]``. `agent` must already be reset
    with the rollouts' contexts; all rollouts step together and a finished one stops stepping."""
    spec = agent.data_spec
    n = len(rollouts)
    record = [frames_to_record(r) for r in (record_frames if record_frames is not None else [False] * n)]
    frame = ACTION_FRAMES.get(spec.action_key)
    if frame is None:
        raise UserError(f"DrawAnything has no action frame for {spec.action_key!r}; known: {sorted(ACTION_FRAMES)}")
    envs, obs = [], []
    for row, rec in zip(rollouts, record, strict=True):
        env = DrawEnv(
            image_size=spec.image_size if spec.image_keys else None,
            cameras=tuple(spec.image_keys),
            max_episode_steps=max_steps,
            render_mode="rgb_array" if rec else None,
            render_size=render_size,
            action_frame=frame,
            score_every_step=False,
        )
        target = prompt_target(store, int(row["target_episode"]))
        o, _ = env.reset(seed=int(row["seed"]), options={"board_angle": float(row["board_angle"]), "target": target})
        envs.append(env)
        obs.append(o)
    frames = [[env.render()] if rec == "all" else [] for env, rec in zip(envs, record, strict=True)]
    done = np.zeros(n, dtype=bool)
    infos: list[dict] = [{"best_chamfer": env.best_chamfer, "chamfer": env.chamfer} for env in envs]
    while not done.all():
        actions = agent.act_batch({k: np.stack([o[k] for o in obs]) for k in agent.obs_keys})
        for i in np.flatnonzero(~done):
            obs[i], _, terminated, truncated, infos[i] = envs[i].step(actions[i])
            done[i] = terminated or truncated
            if record[i] == "all" or (record[i] == "last" and done[i]):
                frames[i].append(envs[i].render())
    return [
        RolloutResult(
            float(infos[i]["best_chamfer"]), envs[i].steps, {"final_chamfer": float(infos[i]["chamfer"])}, frames[i]
        )
        for i in range(n)
    ]
