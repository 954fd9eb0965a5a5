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
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from bpp.data.contexts import (
    FrameSource,
    batch_context,
    collate_contexts,
    index_contexts,
    pad_demo_context,
    padded_length,
    task_context,
)
from bpp.data.frame_refs import frame_refs as reference_source
from bpp.data.frame_refs import window_refs
from bpp.data.spec import ContextKind, DataSpec
from bpp.data.store import EpisodeStore
from bpp.errors import UserError

__all__ = ["ArrayCache", "ContextKind", "DataSpec", "FrameSource", "PromptBatchDataset", "index_contexts"]


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


def trainable_tasks(store: EpisodeStore, tasks: Sequence[int] | None = None) -> list[int]:
    """The tasks of `store` (of `tasks`, default all) that training can use: those with at least two
    demonstrations, one to prompt with and another to imitate. Raises :class:`UserError` when there are none, so that
    a command can refuse a store before it builds or loads anything."""
    by_task = store.task_episodes()
    chosen = range(len(by_task)) if tasks is None else tasks
    usable = [t for t in chosen if len(by_task[t]) >= 2]
    if not usable:
        most = max((len(by_task[t]) for t in chosen), default=0)
        raise UserError(
            f"{store.path}: no task has the two demonstrations training needs (one is the prompt, another is "
            f"imitated; the most any task has is {most}): generate at least 2 per task (--demos-per-task 2)"
        )
    return usable


def stored_keys(store: EpisodeStore, keys: Sequence[str]) -> None:
    """Refuse a store without one of the per-step `keys` a policy observes or acts with (cameras may be rendered
    from stored states, so callers leave them out), naming what it lacks, so that a command can refuse it before it
    builds or loads anything."""
    missing = [k for k in keys if k not in store.keys]
    if missing:
        raise UserError(
            f"{store.path}: the policy observes or acts with {missing}, which the store lacks (it has "
            f"{', '.join(store.keys)}); a store generated before a key was added lacks it: generate it again, or "
            "choose another --obs"
        )


def finite_statistics(store: EpisodeStore) -> None:
    """Refuse a store whose normalisation statistics hold a NaN or an infinity (a store written before stores
    refused non-finite values): training on it would end with NaN weights."""
    for key, stats in store.stats.items():
        for name, values in stats.items():
            if not np.isfinite(np.asarray(values, dtype=np.float64)).all():
                raise UserError(
                    f"{store.path}: the {name} of {key!r} is not finite ({values}): the store holds a NaN or an "
                    "infinity; write it again from its source, whose bad values are then named"
                )


class PromptBatchDataset(torch.utils.data.Dataset):
    """Batches ``{"obs": {k: (B, To, ...)}, "action": (B, T, A), "context": {...}, "context_index": (B,),
    "task": (G,)}`` (numpy).

    Each batch draws G = `tasks_per_batch` distinct tasks uniformly (balanced, among tasks with at least two
    demonstrations); for each, one *context demonstration* and B / G samples from the task's *other*
    demonstrations. Sample i is conditioned on context ``context_index[i]``. The paper draws one task per step
    (G = 1); a larger G shows the model more prompts per optimiser step at the same batch size, which matters
    when steps are few (a CPU). The contexts are (by ``spec.context``)

    * ``demo``: ``{"obs": {k: (G, L, ...)}, "action": (G, L, A), "valid": (G, L)}``, the demonstrations
      themselves, padded to the longest (``valid`` False past a demonstration's end); with
      ``spec.context_obs_stride`` k > 1 the observations are every k-th step's, (G, ceil(L / k), ...), and the
      context says so (``"obs_stride": (G,)``);
    * ``goal_image``: ``{"image": (G, H, W, 3)}``, their final frames;
    * ``instruction``: ``{"text": [str] * G}``, the tasks' instructions.

    With ``spec.samples == "episodes"`` the samples are whole demonstrations instead of windows:
    ``obs`` (B, L, ...), ``action`` (B, L, A) and ``valid`` (B, L), padded to the longest.

    With `pad_to_multiple` k > 0, these padded time axes (a demonstration context's L, whole-episode samples' L)
    are padded further, to a multiple of k steps (at most the spec's limit), so that batches come in a few shapes.

    Camera frames come from `frames`, the frame source of the store's benchmark (its
    :meth:`~bpp.core.contract.Benchmark.frames`), which a spec that observes cameras or a goal image needs.

    With `frame_refs`, every camera frame is a reference instead, (..., 2) int64 where the frame would be
    (..., H, W, 3) uint8 (see :mod:`bpp.data.frame_refs`): nothing is rendered, and the training process renders
    them on its device (:func:`bpp.data.frame_refs.render_batch`).
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
        frames: FrameSource | None = None,
        frame_cache_bytes: int = 4 << 30,
        goal_cache_bytes: int = 128 << 20,
        pad_to_multiple: int = 0,
        frame_refs: bool = False,
    ):
        self.store = store if isinstance(store, EpisodeStore) else EpisodeStore(store)
        self.spec = spec
        stored_keys(self.store, [*spec.lowdim_keys, spec.action_key])
        self.frame_refs = frame_refs
        if frame_refs:
            frames = reference_source
        if frames is None and (spec.image_keys or spec.context == "goal_image"):
            raise ValueError(
                f"the policy observes camera frames ({', '.join(spec.image_keys) or 'a goal image'}): pass `frames`, "
                f"the frame source of the store's benchmark ({self.store.benchmark}), e.g. its Benchmark.frames"
            )
        self.frames = frames
        if spec.context == "instruction" and not any(str(t.get("instruction") or "") for t in self.store.tasks):
            raise UserError(f"{self.store.path}: its tasks carry no instructions, so a language policy can't train")
        if tasks_per_batch < 1 or batch_size % tasks_per_batch:
            raise UserError(f"batch_size {batch_size} must be a positive multiple of tasks_per_batch {tasks_per_batch}")
        self.batch_size, self.num_batches, self.tasks_per_batch = batch_size, num_batches, tasks_per_batch
        self.seed, self.rank = seed, rank
        if pad_to_multiple < 0:
            raise UserError(f"pad_to_multiple must be >= 0 (0: pad to the longest only), got {pad_to_multiple}")
        self.pad_to_multiple = pad_to_multiple
        self.tasks = trainable_tasks(self.store, tasks)
        self.task_episodes = self.store.task_episodes()
        self.starts, self.ends = self.store.episode_starts, self.store.episode_ends
        self._arrays: dict[str, np.ndarray] | None = None
        self._frame_cache = ArrayCache(frame_cache_bytes)  # all frames of episodes, by (episode, camera, size)
        self._goal_cache = ArrayCache(goal_cache_bytes)  # final frames alone: the goal images of episodes
        # Whether every frame the method observes fits the cache: then each episode is rendered whole, once, and
        # kept; if not, keeping a few episodes would rarely help a random draw, so each batch renders just the
        # frames it uses (a 224x224 dataset of 2000 x 5 demonstrations would need hundreds of GB).
        frame_bytes = len(spec.image_keys) * spec.image_size**2 * 3
        fits = int((self.ends - self.starts).sum()) * frame_bytes <= frame_cache_bytes
        self.whole_episodes = fits and not frame_refs

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

    def _cached_frames(
        self, store: EpisodeStore, episode: int, key: str, size: int, last_only: bool = False, steps=None
    ) -> np.ndarray:
        """The benchmark's frames (a :data:`FrameSource`) through the caches. A final frame alone (a goal image)
        comes from the episode's cached frames if a policy that observes images has them, else is rendered alone
        and kept. (References are made, not cached.)"""
        if self.frame_refs:
            return self.frames(store, episode, key, size, last_only=last_only, steps=steps)
        if last_only:
            frames = self._frame_cache.peek((episode, key, size))
            if frames is not None:
                return frames[-1:]
            return self._goal_cache.get(episode, lambda: self.frames(store, episode, key, size, last_only=True))
        if not self.whole_episodes:
            return self.frames(store, episode, key, size, steps=steps)
        frames = self._episode_frames(episode, key, size)
        return frames if steps is None else frames[steps]

    def _gather(self, episodes: np.ndarray, index: np.ndarray) -> dict:
        """Observations of `episodes` (B,) at their step indices `index` (B, N): ``{key: (B, N, ...)}``."""
        data, base = self._data(), self.starts[episodes][:, None]
        obs = {k: data[k][base + index] for k in self.spec.lowdim_keys}
        size = self.spec.image_size
        for key in self.spec.image_keys:
            if self.frame_refs:
                obs[key] = window_refs(episodes, index)
                continue
            frames = obs[key] = np.empty((*index.shape, size, size, 3), dtype=np.uint8)
            for episode in np.unique(episodes):  # each episode's frames made once per batch
                rows = episodes == episode
                steps, inverse = np.unique(index[rows], return_inverse=True)
                made = self._cached_frames(self.store, int(episode), key, size, steps=steps)
                frames[rows] = made[inverse.reshape(-1)].reshape(frames[rows].shape)
        return obs

    def context(self, episode: int) -> dict:
        """The task context the method is conditioned on, from context demonstration `episode`, batch dimension 1
        (the same :func:`~bpp.data.contexts.task_context` evaluation uses; prompts cut to ``max_prompt_steps``)."""
        raw = task_context(
            self.store,
            episode,
            self.spec,
            self._cached_frames,
            self.spec.max_prompt_steps,
            obs_stride=self.spec.context_obs_stride,
        )
        return batch_context(self.spec.context, raw)

    def __getitem__(self, index: int) -> dict:
        rng = np.random.default_rng([self.seed, int(index), self.rank])
        groups, per_group = self.tasks_per_batch, self.batch_size // self.tasks_per_batch
        if groups == 1:  # an index drawn as rng.integers: the draw BENCHMARKS.md's one-task runs reproduce with
            tasks = [self.tasks[int(rng.integers(len(self.tasks)))]]
        else:  # distinct tasks while there are enough of them
            tasks = rng.choice(self.tasks, size=groups, replace=groups > len(self.tasks)).tolist()
        contexts, chosen = [], []
        for task in tasks:
            episodes = self.task_episodes[task]
            context_episode = int(episodes[rng.integers(len(episodes))])
            others = episodes[episodes != context_episode]
            chosen.append(others[rng.integers(len(others), size=per_group)])
            contexts.append(self.context(context_episode))
        chosen = np.concatenate(chosen)
        batch = self._episodes(chosen) if self.spec.samples == "episodes" else self._windows(chosen, rng)
        batch["context"] = collate_contexts(contexts)
        if self.spec.context == "demo" and self.pad_to_multiple:
            longest = batch["context"]["valid"].shape[1]
            steps = padded_length(longest, self.pad_to_multiple, self.spec.max_prompt_steps)
            batch["context"] = pad_demo_context(batch["context"], steps)
        batch["context_index"] = np.repeat(np.arange(groups), per_group)
        batch["task"] = np.asarray(tasks, dtype=np.int64)
        return batch

    def _windows(self, chosen: np.ndarray, rng: np.random.Generator) -> dict:
        To, T = self.spec.n_obs_steps, self.spec.horizon
        lengths = self.ends[chosen] - self.starts[chosen]
        t = (rng.random(len(chosen)) * lengths).astype(np.int64)  # current step within each episode
        obs_idx = np.clip(t[:, None] + np.asarray(self.spec.obs_offsets), 0, None)  # To steps after any memory
        act_idx = np.clip(t[:, None] + np.arange(-To + 1, T - To + 1), 0, None)
        act_idx = np.minimum(act_idx, lengths[:, None] - 1)  # pad past the end with the final action
        actions = self._data()[self.spec.action_key][self.starts[chosen][:, None] + act_idx]
        return {"obs": self._gather(chosen, obs_idx), "action": actions}

    def _episodes(self, chosen: np.ndarray) -> dict:
        lengths = np.minimum(self.ends[chosen] - self.starts[chosen], self.spec.max_episode_steps)
        longest = padded_length(int(lengths.max()), self.pad_to_multiple, self.spec.max_episode_steps)
        index = np.minimum(np.arange(longest)[None], lengths[:, None] - 1)  # pad by repeating the last step
        actions = self._data()[self.spec.action_key][self.starts[chosen][:, None] + index]
        return {
            "obs": self._gather(chosen, index),
            "action": actions,
            "valid": np.arange(longest)[None] < lengths[:, None],
        }
