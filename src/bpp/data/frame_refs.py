"""Camera frames as references, rendered on the training device (``bpp train --frames-on device``).

With references, a training batch carries, wherever it would carry frames ``(..., H, W, 3)`` uint8, an int64 array
``(..., 2)`` of (episode + 1, step within the episode) instead; ``(0, 0)`` stands for an all-zero frame, so the
zero padding of :func:`bpp.data.contexts.collate_contexts` and :func:`~bpp.data.contexts.pad_demo_context` pads
with blank frames, as it does with frames. :func:`render_batch` then replaces them by the frames, on the device,
with a benchmark's :class:`DeviceFrames` (its ``device_frames(store, device)``), before the model sees the batch.
The loader sends 16 bytes a frame instead of ``3 H W``, and renders nothing.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol, runtime_checkable

import numpy as np
import torch

from bpp.data.spec import DataSpec
from bpp.data.store import EpisodeStore
from bpp.errors import UserError


@runtime_checkable
class DeviceFrames(Protocol):
    """A benchmark's renderer of a store's frames on a device (what its ``device_frames(store, device)`` returns).
    It may name the cameras it draws in a ``cameras`` attribute; a model that needs another is then refused."""

    def render(self, refs: torch.Tensor, size: int) -> torch.Tensor:
        """(N, 2) int64 references -> (N, size, size, 3) uint8 frames, exactly the benchmark's ``frames(...)``."""
        ...


def frame_refs(
    store: EpisodeStore, episode: int, key: str, size: int, last_only: bool = False, steps=None
) -> np.ndarray:
    """A :data:`~bpp.data.contexts.FrameSource` that returns references, (T, 2), (1, 2) or (k, 2) int64."""
    sl = store.episode_slice(episode)
    length = sl.stop - sl.start
    if last_only:
        steps = [length - 1]
    elif steps is None:
        steps = np.arange(length)
    steps = np.asarray(steps, dtype=np.int64).reshape(-1)
    return np.stack([np.full(len(steps), episode + 1, dtype=np.int64), steps], axis=1)


def window_refs(episodes: np.ndarray, index: np.ndarray) -> np.ndarray:
    """References of `episodes` (B,) at step indices `index` (B, N): (B, N, 2) int64."""
    episodes = np.broadcast_to(np.asarray(episodes, dtype=np.int64)[:, None] + 1, index.shape)
    return np.stack([episodes, np.asarray(index, dtype=np.int64)], axis=-1)


def render_batch(batch: Mapping, spec: DataSpec, renderer: DeviceFrames) -> dict:
    """A batch of :class:`~bpp.data.prompt_dataset.PromptBatchDataset` built with ``frame_refs=True``, on the host
    (numpy arrays or tensors, as a loader gives it), with its frames rendered on the renderer's device in place of the
    references: the batch one built with frames would be, its frames already on the device."""
    drawn = getattr(renderer, "cameras", None)  # the cameras the renderer draws, if it says
    wanted = [*spec.image_keys, *([spec.context_image_key] if spec.context == "goal_image" else [])]
    if drawn is not None and set(wanted) - set(drawn):
        raise UserError(
            f"frames rendered on the device (--frames-on device) are drawn for the cameras {', '.join(drawn)} only; "
            f"this model needs {', '.join(sorted(set(wanted) - set(drawn)))}: train with --frames-on loader"
        )
    batch = dict(batch)
    places = []  # (the dict holding it, its key, the frame size) of every reference array
    obs = batch["obs"] = dict(batch["obs"])
    for key in spec.image_keys:
        places.append((obs, key, spec.image_size))
    if spec.context == "demo" and spec.image_keys:
        context = batch["context"] = dict(batch["context"])
        context_obs = context["obs"] = dict(context["obs"])
        for key in spec.image_keys:
            places.append((context_obs, key, spec.image_size))
    elif spec.context == "goal_image":
        context = batch["context"] = dict(batch["context"])
        places.append((context, "image", spec.context_image_size))
    for size in sorted({size for _, _, size in places}):  # one call per size: boards and ink measured once
        group = [(holder, key) for holder, key, s in places if s == size]
        refs = [torch.as_tensor(holder[key]) for holder, key in group]
        for ref in refs:
            if ref.dtype != torch.int64 or ref.shape[-1] != 2:
                raise TypeError(f"expected frame references (..., 2) int64, got {tuple(ref.shape)} {ref.dtype}")
        frames = renderer.render(torch.cat([r.reshape(-1, 2) for r in refs]), size)
        for (holder, key), ref, part in zip(group, refs, frames.split([r[..., 0].numel() for r in refs]), strict=True):
            holder[key] = part.view(*ref.shape[:-1], size, size, 3)
    return batch
