"""Evaluation without a simulator: open-loop replay of recorded episodes, scored by the action error.

A rollout of task t replays a recorded episode of t that is not its prompt (the one after the rollout's target
episode among t's episodes, in store order): at every step the policy observes that episode's recorded
observations, and its action is compared with the recorded action. Under the other-task prompt control the same
episodes are replayed, so the two numbers differ only by the prompt.

The score of a rollout is the mean, over the replayed steps and the action's dimensions, of
``|policy action - recorded action|``, each dimension divided by half its range (max - min) in the evaluated store: 0
is a perfect copy, 1 an error of half the range. The raw mean absolute error and the mean L2 error (the store's
units) are recorded beside it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np

from bpp.core.contract import RolloutResult, frames_to_record
from bpp.data.store import EpisodeStore
from bpp.errors import UserError
from bpp.media import pyplot

CHART_SIZE = 256


def replayed_episode(store: EpisodeStore, target: int, prompt: int) -> int:
    """The episode a rollout replays: the first episode of the target's task after the target (cyclically) that is
    not the prompt."""
    task = int(store.column("task_index")[target])
    episodes = [int(e) for e in store.task_episodes()[task]]
    start = episodes.index(target)
    for episode in episodes[start + 1 :] + episodes[: start + 1]:
        if episode != prompt:
            return episode
    raise UserError(
        f"{store.path}: task {store.tasks[task]['id']!r} has one episode; open-loop evaluation replays an episode of "
        "the task other than its prompt, so each task needs at least two (import with a larger --holdout-episodes, "
        "or evaluate on a store whose tasks have several episodes)"
    )


def half_ranges(store: EpisodeStore, key: str) -> np.ndarray:
    """Half of each action dimension's range in `store` (1 where a dimension is constant)."""
    stats = store.stats.get(key)
    if stats is None:
        raise UserError(f"{store.path}: no statistics for {key!r}, so its action error cannot be normalised")
    half = (np.asarray(stats["max"], dtype=np.float64) - np.asarray(stats["min"], dtype=np.float64)) / 2
    return np.where(half > 0, half, 1.0)


def run_rollouts(
    agent,
    store: EpisodeStore,
    rollouts: Sequence[Mapping],
    max_steps: int,
    record_frames: Sequence[bool | str],
    frames: Callable[..., np.ndarray],
) -> list[RolloutResult]:
    """Replay each rollout's episode (see the module docstring) through ``agent.act_batch`` in lockstep, at most
    `max_steps` steps each; `frames` is the benchmark's camera source."""
    spec = agent.data_spec
    action_key, keys = spec.action_key, list(agent.obs_keys)
    images = set(spec.image_keys)
    half = half_ranges(store, action_key)
    episodes = [replayed_episode(store, int(r["target_episode"]), int(r["prompt_episode"])) for r in rollouts]
    observed, recorded = [], []
    for episode in episodes:
        lowdim = store.episode(episode, [k for k in keys if k not in images] + [action_key])
        obs = {k: (frames(store, episode, k, spec.image_size) if k in images else lowdim[k]) for k in keys}
        observed.append(obs)
        recorded.append(lowdim[action_key].astype(np.float64))
    lengths = [min(len(r), max_steps) for r in recorded]
    predicted = [np.zeros((n, r.shape[1])) for n, r in zip(lengths, recorded, strict=True)]
    for t in range(max(lengths)):
        batch = {k: np.stack([obs[k][min(t, n - 1)] for obs, n in zip(observed, lengths, strict=True)]) for k in keys}
        actions = np.asarray(agent.act_batch(batch), dtype=np.float64)
        for i, n in enumerate(lengths):
            if t < n:
                predicted[i][t] = actions[i]
    results = []
    for i, (episode, n) in enumerate(zip(episodes, lengths, strict=True)):
        error = predicted[i] - recorded[i][:n]
        extra = {
            "replayed_episode": episode,
            "action_mae_raw": float(np.abs(error).mean()),
            "action_l2_raw": float(np.linalg.norm(error, axis=1).mean()),
        }
        charted = frames_to_record(record_frames[i])  # one picture, whichever frames were asked for
        chart = [action_chart(recorded[i][:n], predicted[i], f"episode {episode}")] if charted else []
        results.append(RolloutResult(float((np.abs(error) / half).mean()), n, extra, chart))
    return results


def action_chart(recorded: np.ndarray, predicted: np.ndarray | None = None, title: str = "", size: int = CHART_SIZE):
    """A (size, size, 3) uint8 picture of an episode's actions over time, one colour per dimension (the first 8):
    recorded solid, predicted dashed."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(size / 100, size / 100), dpi=100)
    colours = plt.get_cmap("tab10").colors
    for d in range(min(recorded.shape[1], 8)):
        ax.plot(recorded[:, d], color=colours[d], linewidth=1)
        if predicted is not None:
            ax.plot(predicted[:, d], color=colours[d], linewidth=1, linestyle="--")
    ax.set_title(title, fontsize=7)
    ax.tick_params(labelsize=5)
    fig.tight_layout(pad=0.3)
    fig.canvas.draw()
    picture = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return picture
