"""DrawAnything rollouts: give a policy the context of one stored demonstration and let it draw at a new board angle.

Many rollouts run in lockstep through one batched :class:`~bpp.policies.agent.PolicyAgent`, so a task's 32
rollouts cost about as many network calls as one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from bpp.data.store import EpisodeStore
from bpp.envs.draw.dataset import episode_paths, render_episode, render_last_observation
from bpp.envs.draw.env import ACTION_FRAMES, DrawEnv
from bpp.envs.draw.geometry import canvas_to_upright


def prompt_from_store(store: EpisodeStore, episode: int, keys, image_keys=(), image_size: int = 96) -> dict:
    """A stored demonstration as a raw prompt ``{"obs": {key: (L, ...)}, "action": (L, A)}`` (canvas actions)."""
    return demo_context(store, episode, keys, image_keys, image_size, "action")


def demo_context(store: EpisodeStore, episode: int, keys, image_keys, image_size: int, action_key: str) -> dict:
    ep = store.episode(episode, [k for k in keys if k not in image_keys] + [action_key])
    obs = {k: ep[k] for k in keys if k not in image_keys}
    for key in image_keys:
        obs[key] = render_episode(store, episode, image_size)
    return {"obs": obs, "action": ep[action_key]}


def context_for(model, store: EpisodeStore, episode: int) -> dict:
    """The raw task context `model` expects (its ``context_kind``), taken from demonstration `episode` of `store`."""
    spec = model.data_spec()
    kind = model.context_kind
    if kind == "demo":
        return demo_context(store, episode, model.obs_keys(), spec.image_keys, spec.image_size, spec.action_key)
    if kind == "goal_image":
        return {"image": render_last_observation(store, episode, spec.context_image_size)}
    if kind == "instruction":
        task = int(store.column("task_index")[episode])
        return {"text": str(store.tasks[task].get("instruction") or "")}
    raise ValueError(f"unknown context kind {kind!r}")


def prompt_target(store: EpisodeStore, episode: int) -> list[np.ndarray]:
    """The prompt's own ink, upright: the target a rollout is scored against (as in the paper)."""
    angle = float(store.column("board_angle")[episode])
    return [canvas_to_upright(p, angle) for p in episode_paths(store, episode)]


@dataclass
class DrawRollout:
    best_chamfer: float
    final_chamfer: float
    steps: int
    board_angle: float
    paths: list = field(repr=False)  # canvas polylines the rollout inked
    frames: list = field(repr=False)  # rgb frames if recorded
    attention: np.ndarray | None = field(default=None, repr=False)  # (calls, n_chunks + 1) prompt attention


def rollout_batch(
    agent,
    store: EpisodeStore,
    episodes: Sequence[int],
    angles: Sequence[float],
    seeds: Sequence[int],
    max_steps: int = 400,
    record_frames: Sequence[bool] | None = None,
    render_size: int = 256,
    prompt_episodes: Sequence[int] | None = None,
) -> list[DrawRollout]:
    """Rollout i is prompted with demonstration `episodes[i]` and draws on a board at `angles[i]`, seeded by
    `seeds[i]` (cursor start and policy noise). All rollouts step together; a finished one stops stepping.
    It is scored against `episodes[i]`'s drawing; `prompt_episodes` prompts it with other demonstrations instead
    (a control: :class:`bpp.evaluation.evaluate.Protocol`'s ``prompts="other-task"``).
    """
    model = agent.model
    spec = model.data_spec()
    n = len(episodes)
    record_frames = list(record_frames) if record_frames is not None else [False] * n
    frame = ACTION_FRAMES.get(spec.action_key)
    if frame is None:
        raise ValueError(f"DrawAnything has no action frame for {spec.action_key!r}; known: {sorted(ACTION_FRAMES)}")
    envs, obs = [], []
    for ep, angle, seed, rec in zip(episodes, angles, seeds, record_frames, strict=True):
        env = DrawEnv(
            image_size=spec.image_size if spec.image_keys else None,
            max_episode_steps=max_steps,
            render_mode="rgb_array" if rec else None,
            render_size=render_size,
            action_frame=frame,
        )
        o, _ = env.reset(seed=int(seed), options={"board_angle": float(angle), "target": prompt_target(store, ep)})
        envs.append(env)
        obs.append(o)
    prompts = episodes if prompt_episodes is None else prompt_episodes
    if len(prompts) != n:
        raise ValueError(f"{len(prompts)} prompt episodes for {n} rollouts")
    agent.reset_batch([context_for(model, store, ep) for ep in prompts], seeds)
    frames = [[env.render()] if rec else [] for env, rec in zip(envs, record_frames, strict=True)]
    done = np.zeros(n, dtype=bool)
    infos: list[dict] = [{"best_chamfer": env.best_chamfer, "chamfer": env.chamfer} for env in envs]
    while not done.all():
        actions = agent.act_batch({k: np.stack([o[k] for o in obs]) for k in agent.obs_keys})
        for i in np.flatnonzero(~done):
            obs[i], _, terminated, truncated, infos[i] = envs[i].step(actions[i])
            done[i] = terminated or truncated
            if record_frames[i]:
                frames[i].append(envs[i].render())
    attention = np.stack(agent.attention_log, axis=1) if agent.attention_log else None  # (B, calls, C)
    return [
        DrawRollout(
            float(infos[i]["best_chamfer"]),
            float(infos[i]["chamfer"]),
            envs[i].steps,
            float(angles[i]),
            envs[i].paths,
            frames[i],
            None if attention is None else attention[i, : -(-envs[i].steps // agent.n_action_steps)],
        )
        for i in range(n)
    ]


def rollout(
    agent,
    store: EpisodeStore,
    prompt_episode: int,
    board_angle: float,
    seed: int = 0,
    max_steps: int = 400,
    record_frames: bool = False,
) -> DrawRollout:
    """One episode: `agent` is prompted with `prompt_episode` of `store` and draws on a board at `board_angle`."""
    return rollout_batch(agent, store, [prompt_episode], [board_angle], [seed], max_steps, [record_frames])[0]
