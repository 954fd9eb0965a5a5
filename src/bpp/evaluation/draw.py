"""DrawAnything rollouts: prompt a policy with one stored demonstration and let it draw at a new board angle."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bpp.data.store import EpisodeStore
from bpp.envs.draw.dataset import episode_paths, render_episode
from bpp.envs.draw.env import DrawEnv
from bpp.envs.draw.geometry import canvas_to_upright


def prompt_from_store(store: EpisodeStore, episode: int, keys, image_keys=(), image_size: int = 96) -> dict:
    """A stored demonstration as a raw prompt ``{"obs": {key: (L, ...)}, "action": (L, A)}``."""
    ep = store.episode(episode, [k for k in keys if k not in image_keys] + ["action"])
    obs = {k: ep[k] for k in keys if k not in image_keys}
    for key in image_keys:
        obs[key] = render_episode(store, episode, image_size)
    return {"obs": obs, "action": ep["action"]}


def prompt_target(store: EpisodeStore, episode: int) -> list[np.ndarray]:
    """The prompt's own ink, upright: the target a rollout is scored against (as in the paper)."""
    angle = float(store.column("board_angle")[episode])
    return [canvas_to_upright(p, angle) for p in episode_paths(store, episode)]


@dataclass
class DrawRollout:
    best_chamfer: float
    final_chamfer: float
    steps: int
    paths: list = field(repr=False)  # canvas polylines the rollout inked
    frames: list = field(repr=False)  # rgb frames if recorded
    attention: list = field(repr=False)  # per inference call: (n_chunks + 1,) prompt attention


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
    cfg = agent.model.cfg.obs
    keys = [*cfg.image_keys, *cfg.lowdim_keys, *cfg.proprio_keys]
    prompt = prompt_from_store(store, prompt_episode, keys, cfg.image_keys, cfg.image_size)
    env = DrawEnv(
        image_size=cfg.image_size if cfg.image_keys else None,
        max_episode_steps=max_steps,
        render_mode="rgb_array" if record_frames else None,
        render_size=256,
    )
    obs, info = env.reset(
        seed=seed, options={"board_angle": board_angle, "target": prompt_target(store, prompt_episode)}
    )
    agent.reset(prompt, seed=seed)
    frames = [env.render()] if record_frames else []
    done = False
    while not done:
        obs, _, terminated, truncated, info = env.step(agent.act(obs))
        done = terminated or truncated
        if record_frames:
            frames.append(env.render())
    return DrawRollout(info["best_chamfer"], info["chamfer"], env.steps, env.paths, frames, agent.attention_log)
