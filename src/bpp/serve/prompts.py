"""The behavior prompts a policy server offers: the demonstrations of an episode store, named by id, and
demonstrations that clients upload, named by the handle the server returns.

Every method is driven the same way: a client names a demonstration, and the library turns it into the served
method's task context exactly as evaluation does (:func:`bpp.data.contexts.task_context`): the whole demonstration
for BPP and ICRT, its final frame for Goal-Image, its task's instruction for Language.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from bpp.data.contexts import task_context
from bpp.data.spec import DataSpec
from bpp.data.store import EpisodeStore
from bpp.errors import UserError

UPLOAD_PREFIX = "upload:"
LATEST_UPLOAD = "upload:latest"
"""The newest upload, whichever it is: a client that names it follows new uploads (its next request after one starts
a new episode with it), so a person can re-prompt a running robot by uploading a demonstration."""


class PromptLookupError(UserError):
    """A prompt id or upload that the library cannot turn into a task context."""


@dataclass(frozen=True)
class PromptEntry:
    """One prompt: its canonical id and the raw task context the served method takes."""

    id: str
    context: Mapping


class PromptLibrary:
    """Prompts by id for one served model.

    Ids: ``"episode:<i>"`` (or the integer i) for episode i of the store; ``"<task id>"`` for the task's first
    demonstration and ``"<task id>#<k>"`` for its k-th (from 0); ``"upload:<hex>"`` for an uploaded demonstration.

    Args:
        spec: the served model's :class:`DataSpec` (what its context holds).
        validate: the model's ``validate_context``; every prompt is checked by it before it is accepted.
        store: the episode store whose demonstrations are offered (None: uploads only).
        frames: the store's benchmark's frame source (cameras and goal images).
        max_uploads: uploads kept; the oldest is forgotten when more arrive.
        cache: contexts built from the store kept in memory (building one may render frames).
    """

    def __init__(self, spec: DataSpec, validate, store: EpisodeStore | None, frames=None, max_uploads=64, cache=32):
        self.spec, self.validate, self.store, self.frames = spec, validate, store, frames
        self.max_uploads, self.cache_size = max_uploads, cache
        self._uploads: OrderedDict[str, Mapping] = OrderedDict()
        self._latest: str | None = None
        self._cache: OrderedDict[int, Mapping] = OrderedDict()
        self._task_ids: dict[str, int] = {}
        if store is not None:
            self._task_ids = {str(t["id"]): i for i, t in enumerate(store.tasks)}
            self._task_episodes = store.task_episodes()

    # ------------------------------------------------------------------ listing
    def describe(self, limit: int = 500) -> dict:
        """What a client may ask for: the store, and its tasks with their demonstration counts (first `limit`)."""
        if self.store is None:
            return {"store": None, "episodes": 0, "tasks": [], "uploads": True}
        tasks = [
            {"id": str(t["id"]), "instruction": str(t.get("instruction") or ""), "demos": len(self._task_episodes[i])}
            for i, t in enumerate(self.store.tasks[:limit])
        ]
        return {
            "store": str(self.store.path),
            "benchmark": self.store.benchmark,
            "episodes": self.store.num_episodes,
            "tasks": tasks,
            "tasks_listed": len(tasks),
            "tasks_total": self.store.num_tasks,
            "uploads": True,
        }

    # ------------------------------------------------------------------ lookup
    def episode_of(self, prompt: int | str) -> int:
        """The store episode a prompt id names (PromptLookupError if it names none)."""
        if self.store is None:
            raise PromptLookupError("this server has no prompt library; upload a demonstration instead")
        if isinstance(prompt, int | np.integer) and not isinstance(prompt, bool):
            episode = int(prompt)
        elif isinstance(prompt, str) and prompt.startswith("episode:") and prompt[8:].lstrip("-").isdigit():
            episode = int(prompt[8:])
        elif isinstance(prompt, str):
            task_id, _, k = (prompt, "", "0") if prompt in self._task_ids else prompt.rpartition("#")
            if task_id not in self._task_ids:
                raise PromptLookupError(
                    f"prompt {prompt!r}: no such task in {self.store.path.name} (ids: 'episode:<i>', '<task id>', "
                    f"'<task id>#<k>' or an upload handle; the metadata lists the tasks)"
                )
            demos = self._task_episodes[self._task_ids[task_id]]
            if not k.isdigit() or int(k) >= len(demos):
                raise PromptLookupError(f"prompt {prompt!r}: task {task_id!r} has demonstrations #0..#{len(demos) - 1}")
            return int(demos[int(k)])
        else:
            raise PromptLookupError(f"prompt must be a string id or an episode number, got {type(prompt).__name__}")
        if not 0 <= episode < self.store.num_episodes:
            raise PromptLookupError(f"prompt {prompt!r}: the store has episodes 0..{self.store.num_episodes - 1}")
        return episode

    def get(self, prompt: int | str) -> PromptEntry:
        """The validated raw context of prompt id `prompt`."""
        if prompt == LATEST_UPLOAD:
            if self._latest is None or self._latest not in self._uploads:
                raise PromptLookupError(f"prompt {LATEST_UPLOAD!r}: nothing has been uploaded yet")
            prompt = self._latest
        if isinstance(prompt, str) and prompt.startswith(UPLOAD_PREFIX):
            if prompt not in self._uploads:
                raise PromptLookupError(
                    f"prompt {prompt!r}: no such upload (uploads are kept in memory, the newest "
                    f"{self.max_uploads}; upload it again)"
                )
            self._uploads.move_to_end(prompt)
            return PromptEntry(prompt, self._uploads[prompt])
        episode = self.episode_of(prompt)
        if episode not in self._cache:
            context = task_context(self.store, episode, self.spec, self.frames)
            self.validate(context)
            self._cache[episode] = context
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        self._cache.move_to_end(episode)
        return PromptEntry(f"episode:{episode}", self._cache[episode])

    # ------------------------------------------------------------------ uploads
    def upload(self, demo: Mapping) -> str:
        """Accept an uploaded demonstration ``{"obs": {key: (L, ...)}, "action": (L, A), "instruction": str}``
        (instruction optional, needed by the Language method) and return its handle."""
        if not isinstance(demo, Mapping):
            raise PromptLookupError("upload must be a demonstration: {'obs': {key: (L, ...)}, 'action': (L, A)}")
        context = self._context_from_demo(demo)
        self.validate(context)
        digest = hashlib.sha256()
        _hash_into(digest, context)
        handle = UPLOAD_PREFIX + digest.hexdigest()[:20]
        self._uploads[handle] = context
        self._uploads.move_to_end(handle)
        self._latest = handle
        while len(self._uploads) > self.max_uploads:
            self._uploads.popitem(last=False)
        return handle

    def _context_from_demo(self, demo: Mapping) -> dict:
        """An uploaded demonstration as the served method's raw context (see the module docstring)."""
        kind = self.spec.context
        if kind == "instruction":
            text = demo.get("instruction")
            if not isinstance(text, str) or not text.strip():
                raise PromptLookupError("this server's method (Language) needs the upload's 'instruction' text")
            return {"text": text}
        obs = demo.get("obs")
        if not isinstance(obs, Mapping):
            raise PromptLookupError("upload lacks 'obs', a dict of per-step arrays")
        if kind == "goal_image":
            key = self.spec.context_image_key
            if key not in obs:
                raise PromptLookupError(f"upload obs lacks {key!r}, whose final frame is this method's goal image")
            frames = np.asarray(obs[key])
            size = self.spec.context_image_size
            if frames.ndim != 4 or frames.shape[1:] != (size, size, 3) or frames.dtype != np.uint8 or not len(frames):
                raise PromptLookupError(
                    f"upload obs {key!r} must be (steps, {size}, {size}, 3) uint8, got {frames.shape} {frames.dtype}"
                )
            return {"image": frames[-1].copy()}
        if "action" not in demo:
            raise PromptLookupError("upload lacks 'action', (steps, action dim)")
        keys = (*self.spec.lowdim_keys, *self.spec.image_keys)
        missing = [k for k in keys if k not in obs]
        if missing:
            raise PromptLookupError(f"upload obs lacks {missing}; this method's prompt needs {list(keys)}")
        # copies: arrays decoded from a frame are read-only views of it
        return {"obs": {k: np.array(obs[k]) for k in keys}, "action": np.array(demo["action"])}


def _hash_into(digest, value) -> None:
    """Feed a nested context (dicts, arrays, strings) into `digest` deterministically."""
    if isinstance(value, Mapping):
        for key in sorted(value):
            digest.update(str(key).encode() + b"\0")
            _hash_into(digest, value[key])
    elif isinstance(value, str):
        digest.update(b"s" + value.encode())
    else:
        array = np.ascontiguousarray(value)
        digest.update(f"{array.dtype.str}{array.shape}".encode() + array.tobytes())
