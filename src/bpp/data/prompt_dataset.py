"""Training batches for behavior prompting: one task, one prompt demonstration, windows from its other demos.

Batch ``i`` is a pure function of ``(seed, i, rank)``, so data loading is deterministic whatever the number of
loader workers, a resumed run sees exactly the batches it would have seen, and DDP ranks draw different
batches. Each item of this map-style dataset is a *whole batch* (use ``DataLoader(batch_size=None)``).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from bpp.data.store import EpisodeStore

FrameSource = Callable[[EpisodeStore, int, str, int], np.ndarray]
"""(store, episode, image key, size) -> (T, size, size, 3) uint8 frames of that episode."""


def benchmark_frames(benchmark: str) -> FrameSource | None:
    """How a benchmark's stores provide image observations (DrawAnything renders them from the stored state)."""
    if benchmark == "drawanything":
        from bpp.envs.draw.dataset import render_episode

        return lambda store, episode, key, size: render_episode(store, episode, size)
    return None


class PromptBatchDataset(torch.utils.data.Dataset):
    """Batches of ``{"obs": {k: (B, To, ...)}, "action": (B, T, A), "prompt": {...}, "task": ()}`` (numpy).

    The prompt is ``{"obs": {k: (1, L, ...)}, "action": (1, L, A), "valid": (1, L)}``: one demonstration of the
    batch's task, and every window comes from a *different* demonstration of the same task. Tasks are drawn
    uniformly (balanced), among tasks with at least two demonstrations.
    """

    def __init__(
        self,
        store: str | Path | EpisodeStore,
        *,
        lowdim_keys: Sequence[str],
        image_keys: Sequence[str] = (),
        image_size: int = 96,
        action_key: str = "action",
        n_obs_steps: int = 2,
        horizon: int = 16,
        batch_size: int = 64,
        num_batches: int = 10**9,
        seed: int = 0,
        rank: int = 0,
        max_prompt_steps: int = 800,
        tasks: Sequence[int] | None = None,
        frame_cache_episodes: int = 256,
    ):
        self.store = store if isinstance(store, EpisodeStore) else EpisodeStore(store)
        missing = [k for k in [*lowdim_keys, action_key] if k not in self.store.keys]
        if missing:
            raise KeyError(f"{self.store.path}: the policy needs keys {missing}, the store has {self.store.keys}")
        self.lowdim_keys = list(lowdim_keys)
        self.image_keys = list(image_keys)
        self.image_size = image_size
        self.frames = benchmark_frames(self.store.benchmark) if image_keys else None
        if image_keys and self.frames is None:
            raise ValueError(f"{self.store.path}: benchmark {self.store.benchmark!r} provides no image observations")
        self.action_key = action_key
        self.n_obs_steps, self.horizon = n_obs_steps, horizon
        self.batch_size, self.num_batches = batch_size, num_batches
        self.seed, self.rank = seed, rank
        self.max_prompt_steps = max_prompt_steps
        by_task = self.store.task_episodes()
        chosen = range(len(by_task)) if tasks is None else tasks
        self.tasks = [t for t in chosen if len(by_task[t]) >= 2]
        if not self.tasks:
            raise ValueError(f"{self.store.path}: no task has the two demonstrations BPP training needs")
        self.task_episodes = by_task
        self.starts, self.ends = self.store.episode_starts, self.store.episode_ends
        self._arrays: dict[str, np.ndarray] | None = None
        self._frame_cache: OrderedDict = OrderedDict()
        self._frame_cache_episodes = frame_cache_episodes

    def __len__(self) -> int:
        return self.num_batches

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_arrays"] = None  # each loader worker loads its own copy
        state["_frame_cache"] = OrderedDict()
        return state

    def _data(self) -> dict[str, np.ndarray]:
        if self._arrays is None:
            self._arrays = {k: self.store.array(k) for k in [*self.lowdim_keys, self.action_key]}
        return self._arrays

    def _episode_frames(self, episode: int, key: str) -> np.ndarray:
        cache_key = (episode, key)
        if cache_key not in self._frame_cache:
            self._frame_cache[cache_key] = self.frames(self.store, episode, key, self.image_size)
            if len(self._frame_cache) > self._frame_cache_episodes:
                self._frame_cache.popitem(last=False)
        self._frame_cache.move_to_end(cache_key)
        return self._frame_cache[cache_key]

    def prompt(self, episode: int) -> dict:
        """One stored episode as a prompt (capped at ``max_prompt_steps``), batch dimension 1."""
        data = self._data()
        start = int(self.starts[episode])
        length = min(int(self.ends[episode]) - start, self.max_prompt_steps)
        sl = slice(start, start + length)
        obs = {k: data[k][sl][None] for k in self.lowdim_keys}
        for key in self.image_keys:
            obs[key] = self._episode_frames(episode, key)[:length][None]
        return {"obs": obs, "action": data[self.action_key][sl][None], "valid": np.ones((1, length), dtype=bool)}

    def __getitem__(self, index: int) -> dict:
        rng = np.random.default_rng([self.seed, int(index), self.rank])
        task = self.tasks[int(rng.integers(len(self.tasks)))]
        episodes = self.task_episodes[task]
        prompt_episode = int(episodes[rng.integers(len(episodes))])
        others = episodes[episodes != prompt_episode]
        chosen = others[rng.integers(len(others), size=self.batch_size)]
        lengths = self.ends[chosen] - self.starts[chosen]
        t = (rng.random(self.batch_size) * lengths).astype(np.int64)  # current step within each episode
        obs_idx = np.clip(t[:, None] + np.arange(-self.n_obs_steps + 1, 1), 0, None)
        act_idx = np.clip(t[:, None] + np.arange(-self.n_obs_steps + 1, self.horizon - self.n_obs_steps + 1), 0, None)
        act_idx = np.minimum(act_idx, lengths[:, None] - 1)  # pad past the end with the final action
        data = self._data()
        base = self.starts[chosen][:, None]
        obs = {k: data[k][base + obs_idx] for k in self.lowdim_keys}
        for key in self.image_keys:
            obs[key] = np.stack([self._episode_frames(int(e), key)[i] for e, i in zip(chosen, obs_idx, strict=True)])
        return {
            "obs": obs,
            "action": data[self.action_key][base + act_idx],
            "prompt": self.prompt(prompt_episode),
            "task": np.int64(task),
        }
