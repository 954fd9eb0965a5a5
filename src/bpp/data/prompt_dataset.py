"""Training batches for behavior prompting: one task, one context demonstration, samples from its other demos.

Batch ``i`` is a pure function of ``(seed, i, rank)``, so data loading is deterministic whatever the number of
loader workers, a resumed run sees exactly the batches it would have seen, and DDP ranks draw different
batches. Each item of this map-style dataset is a *whole batch* (use ``DataLoader(batch_size=None)``).

What a method needs is declared by its model as a :class:`DataSpec`: which keys, and which task context (a
demonstration prompt, the prompt's goal image, or the task's instruction). Every method trains from the same
(task, context demonstration, other demonstrations) draws, so that differences come from the context alone.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from bpp.data.store import EpisodeStore

FrameSource = Callable[..., np.ndarray]
"""``frames(store, episode, key, size, last_only=False)``: (T, size, size, 3) uint8 frames of an episode's
observations from camera `key`; with ``last_only``, just the final observation, (1, size, size, 3)."""

ContextKind = Literal["demo", "goal_image", "instruction"]


class ArrayCache:
    """Arrays by key within a byte budget, the least recently used dropped first (the newest is always kept).
    Pickles empty: each loader worker fills its own."""

    def __init__(self, budget: int):
        self.budget, self.nbytes, self._items = budget, 0, OrderedDict()

    def get(self, key, make: Callable[[], np.ndarray]) -> np.ndarray:
        """The array under `key`, made by `make()` if absent."""
        if key not in self._items:
            self._items[key] = value = make()
            self.nbytes += value.nbytes
            while self.nbytes > self.budget and len(self._items) > 1:
                self.nbytes -= self._items.popitem(last=False)[1].nbytes
        self._items.move_to_end(key)
        return self._items[key]

    def peek(self, key) -> np.ndarray | None:
        """The array under `key` if cached, without making it or counting it as used."""
        return self._items.get(key)

    def __len__(self) -> int:
        return len(self._items)

    def __iter__(self):
        return iter(self._items)

    def __getstate__(self):
        return {"budget": self.budget}

    def __setstate__(self, state):
        self.__init__(state["budget"])


def benchmark_frames(benchmark: str) -> FrameSource | None:
    """How a benchmark's stores provide image observations (DrawAnything renders them from the stored state)."""
    if benchmark == "drawanything":
        from bpp.envs.draw.dataset import render_episode, render_last_observation

        def frames(store: EpisodeStore, episode: int, key: str, size: int, last_only: bool = False) -> np.ndarray:
            if last_only:
                return render_last_observation(store, episode, size)[None]
            return render_episode(store, episode, size)

        return frames
    return None


@dataclass(frozen=True)
class DataSpec:
    """What a method's training batches contain (each model builds one from its config: ``model.data_spec()``)."""

    lowdim_keys: tuple[str, ...]
    """Per-step low-dimensional keys (observation and proprioception), in the batch's ``obs``."""
    image_keys: tuple[str, ...] = ()
    image_size: int = 96
    action_key: str = "action"
    n_obs_steps: int = 2
    horizon: int = 16
    context: ContextKind = "demo"
    """demo: a whole demonstration (the prompt); goal_image: its final frame; instruction: the task's text."""
    context_image_key: str = "image"
    context_image_size: int = 96
    """Goal images: which camera and at what size."""
    samples: Literal["windows", "episodes"] = "windows"
    """windows: (observation history, action chunk) windows; episodes: whole demonstrations, padded (ICRT)."""
    max_prompt_steps: int = 800
    max_episode_steps: int = 400
    """Whole-episode samples are cut to this length."""


def collate_contexts(items: list) -> object:
    """Stack task contexts (each with batch dimension 1) into one batch.

    Arrays are concatenated along the batch axis; arrays whose time axis (axis 1) differs are zero-padded to
    the longest first, so a demonstration's ``valid`` mask pads with False. Lists (e.g. instructions) are joined.
    """
    first = items[0]
    if isinstance(first, Mapping):
        return {k: collate_contexts([item[k] for item in items]) for k in first}
    if isinstance(first, list):
        return [x for item in items for x in item]
    arrays = [np.asarray(a) for a in items]
    if arrays[0].ndim >= 2:
        longest = max(a.shape[1] for a in arrays)
        arrays = [np.pad(a, [(0, 0), (0, longest - a.shape[1])] + [(0, 0)] * (a.ndim - 2)) for a in arrays]
    return np.concatenate(arrays, axis=0)


def index_contexts(context, index):
    """Rows `index` (B,) of a batched context (nested dicts of arrays or tensors along axis 0; lists of strings)."""
    if isinstance(context, Mapping):
        return {k: index_contexts(v, index) for k, v in context.items()}
    if isinstance(context, list):
        return [context[int(i)] for i in index]
    return context[index]


class PromptBatchDataset(torch.utils.data.Dataset):
    """Batches ``{"obs": {k: (B, To, ...)}, "action": (B, T, A), "context": {...}, "context_index": (B,),
    "task": (G,)}`` (numpy).

    Each batch draws G = `tasks_per_batch` distinct tasks uniformly (balanced, among tasks with at least two
    demonstrations); for each, one *context demonstration* and B / G samples from the task's *other*
    demonstrations. Sample i is conditioned on context ``context_index[i]``. The paper draws one task per step
    (G = 1); a larger G shows the model more prompts per optimiser step at the same batch size, which matters
    when steps are few (a CPU). The contexts are (by ``spec.context``)

    * ``demo``: ``{"obs": {k: (G, L, ...)}, "action": (G, L, A), "valid": (G, L)}``, the demonstrations
      themselves, padded to the longest (``valid`` False past a demonstration's end);
    * ``goal_image``: ``{"image": (G, H, W, 3)}``, their final frames;
    * ``instruction``: ``{"text": [str] * G}``, the tasks' instructions.

    With ``spec.samples == "episodes"`` the samples are whole demonstrations instead of windows:
    ``obs`` (B, L, ...), ``action`` (B, L, A) and ``valid`` (B, L), padded to the longest.
    """

    def __init__(
        self,
        store: str | Path | EpisodeStore,
        spec: DataSpec,
        *,
        batch_size: int = 64,
        num_batches: int = 10**9,
        seed: int = 0,
        rank: int = 0,
        tasks: Sequence[int] | None = None,
        tasks_per_batch: int = 1,
        frame_cache_bytes: int = 4 << 30,
        goal_cache_bytes: int = 128 << 20,
    ):
        self.store = store if isinstance(store, EpisodeStore) else EpisodeStore(store)
        self.spec = spec
        missing = [k for k in [*spec.lowdim_keys, spec.action_key] if k not in self.store.keys]
        if missing:
            raise KeyError(f"{self.store.path}: the policy needs keys {missing}, the store has {self.store.keys}")
        needs_frames = bool(spec.image_keys) or spec.context == "goal_image"
        self.frames = benchmark_frames(self.store.benchmark) if needs_frames else None
        if needs_frames and self.frames is None:
            raise ValueError(f"{self.store.path}: benchmark {self.store.benchmark!r} provides no image observations")
        if spec.context == "instruction":
            self.instructions = [str(t.get("instruction") or "") for t in self.store.tasks]
            if not any(self.instructions):
                raise ValueError(
                    f"{self.store.path}: its tasks carry no instructions, so a language policy can't train"
                )
        if tasks_per_batch < 1 or batch_size % tasks_per_batch:
            raise ValueError(
                f"batch_size {batch_size} must be a positive multiple of tasks_per_batch {tasks_per_batch}"
            )
        self.batch_size, self.num_batches, self.tasks_per_batch = batch_size, num_batches, tasks_per_batch
        self.seed, self.rank = seed, rank
        by_task = self.store.task_episodes()
        chosen = range(len(by_task)) if tasks is None else tasks
        self.tasks = [t for t in chosen if len(by_task[t]) >= 2]
        if not self.tasks:
            raise ValueError(f"{self.store.path}: no task has the two demonstrations training needs")
        self.task_episodes = by_task
        self.starts, self.ends = self.store.episode_starts, self.store.episode_ends
        self._arrays: dict[str, np.ndarray] | None = None
        self._frame_cache = ArrayCache(frame_cache_bytes)  # all frames of episodes, by (episode, camera, size)
        self._goal_cache = ArrayCache(goal_cache_bytes)  # final frames alone: the goal images of episodes

    def __len__(self) -> int:
        return self.num_batches

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_arrays"] = None  # each loader worker loads its own copy
        return state

    def _data(self) -> dict[str, np.ndarray]:
        if self._arrays is None:
            self._arrays = {k: self.store.array(k) for k in [*self.spec.lowdim_keys, self.spec.action_key]}
        return self._arrays

    def _episode_frames(self, episode: int, key: str, size: int) -> np.ndarray:
        """All image observations of `episode`, rendered once and kept while they fit the byte budget (rendering
        dominates a training step that observes images otherwise)."""
        return self._frame_cache.get((episode, key, size), lambda: self.frames(self.store, episode, key, size))

    def _goal_frame(self, episode: int, key: str, size: int) -> np.ndarray:
        """(1, size, size, 3): the episode's final observation, from the episode's cached frames if a policy that
        observes images has them, else rendered alone and kept in a cache of final frames."""
        frames = self._frame_cache.peek((episode, key, size))
        if frames is not None:
            return frames[-1:]
        return self._goal_cache.get(episode, lambda: self.frames(self.store, episode, key, size, last_only=True))

    def _gather(self, episodes: np.ndarray, index: np.ndarray) -> dict:
        """Observations of `episodes` (B,) at their step indices `index` (B, N): ``{key: (B, N, ...)}``."""
        data, base = self._data(), self.starts[episodes][:, None]
        obs = {k: data[k][base + index] for k in self.spec.lowdim_keys}
        for key in self.spec.image_keys:
            obs[key] = np.stack(
                [
                    self._episode_frames(int(e), key, self.spec.image_size)[i]
                    for e, i in zip(episodes, index, strict=True)
                ]
            )
        return obs

    def prompt(self, episode: int) -> dict:
        """One stored episode as a prompt (capped at ``max_prompt_steps``), batch dimension 1."""
        length = min(int(self.ends[episode] - self.starts[episode]), self.spec.max_prompt_steps)
        episodes, index = np.array([episode]), np.arange(length)[None]
        action = self._data()[self.spec.action_key][self.starts[episodes][:, None] + index]
        return {"obs": self._gather(episodes, index), "action": action, "valid": np.ones((1, length), dtype=bool)}

    def context(self, task: int, episode: int) -> dict:
        """The task context a method is conditioned on, from context demonstration `episode` of `task`."""
        kind = self.spec.context
        if kind == "demo":
            return self.prompt(episode)
        if kind == "goal_image":
            return {"image": self._goal_frame(episode, self.spec.context_image_key, self.spec.context_image_size)}
        return {"text": [self.instructions[task]]}

    def __getitem__(self, index: int) -> dict:
        rng = np.random.default_rng([self.seed, int(index), self.rank])
        groups, per_group = self.tasks_per_batch, self.batch_size // self.tasks_per_batch
        if groups == 1:  # the draw of earlier versions, so their runs resume onto the same batches
            tasks = [self.tasks[int(rng.integers(len(self.tasks)))]]
        else:  # distinct tasks while there are enough of them
            tasks = rng.choice(self.tasks, size=groups, replace=groups > len(self.tasks)).tolist()
        contexts, chosen = [], []
        for task in tasks:
            episodes = self.task_episodes[task]
            context_episode = int(episodes[rng.integers(len(episodes))])
            others = episodes[episodes != context_episode]
            chosen.append(others[rng.integers(len(others), size=per_group)])
            contexts.append(self.context(task, context_episode))
        chosen = np.concatenate(chosen)
        batch = self._episodes(chosen) if self.spec.samples == "episodes" else self._windows(chosen, rng)
        batch["context"] = collate_contexts(contexts)
        batch["context_index"] = np.repeat(np.arange(groups), per_group)
        batch["task"] = np.asarray(tasks, dtype=np.int64)
        return batch

    def _windows(self, chosen: np.ndarray, rng: np.random.Generator) -> dict:
        To, T = self.spec.n_obs_steps, self.spec.horizon
        lengths = self.ends[chosen] - self.starts[chosen]
        t = (rng.random(len(chosen)) * lengths).astype(np.int64)  # current step within each episode
        obs_idx = np.clip(t[:, None] + np.arange(-To + 1, 1), 0, None)
        act_idx = np.clip(t[:, None] + np.arange(-To + 1, T - To + 1), 0, None)
        act_idx = np.minimum(act_idx, lengths[:, None] - 1)  # pad past the end with the final action
        actions = self._data()[self.spec.action_key][self.starts[chosen][:, None] + act_idx]
        return {"obs": self._gather(chosen, obs_idx), "action": actions}

    def _episodes(self, chosen: np.ndarray) -> dict:
        lengths = np.minimum(self.ends[chosen] - self.starts[chosen], self.spec.max_episode_steps)
        longest = int(lengths.max())
        index = np.minimum(np.arange(longest)[None], lengths[:, None] - 1)  # pad by repeating the last step
        actions = self._data()[self.spec.action_key][self.starts[chosen][:, None] + index]
        return {
            "obs": self._gather(chosen, index),
            "action": actions,
            "valid": np.arange(longest)[None] < lengths[:, None],
        }
