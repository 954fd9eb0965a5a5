"""The behavior prompts a policy server offers: the demonstrations of an episode store, named by id, demonstrations
that clients upload, named by the handle the server returns, and for the Language method any instruction text.

Every method is driven the same way: a client names a demonstration, and the library turns it into the served
method's task context exactly as evaluation does (:func:`bpp.data.contexts.task_context`): the whole demonstration
for BPP and ICRT, its final frame for Goal-Image, its task's instruction for Language.

Uploads are held by connections: an upload lives while the connection that uploaded it is open (each keeps its
newest few), while an episode runs it, and while it is the newest upload of all (so that a person can upload a
prompt, disconnect, and have robots that name it, or ``upload:latest``, run it). Their total size is bounded.
"""

from __future__ import annotations

import hashlib
import re
import threading
from collections import OrderedDict
from collections.abc import Hashable, Mapping
from dataclasses import dataclass

import numpy as np

from bpp.data.arrays import check_array
from bpp.data.contexts import task_context
from bpp.data.spec import DataSpec
from bpp.data.store import EpisodeStore
from bpp.errors import UserError

UPLOAD_PREFIX = "upload:"
LATEST_UPLOAD = "upload:latest"
"""The newest upload, whichever it is: a client that names it follows new uploads (its next request after one starts
a new episode with it), so a person can re-prompt a running robot by uploading a demonstration."""
UPLOAD_FIELDS = ("obs", "action", "instruction")
MAX_PROMPT_CHARS = 2000
"""The longest prompt a request may name (an id, or an instruction for the Language method) or an upload may carry
as its instruction."""
NO_LIBRARY = "this server has no prompt library; upload a demonstration instead"
ID_FORMS = "'episode:<i>' (or the integer i), '<task id>', '<task id>#<k>' or an upload handle"

_EPISODE_ID = re.compile(r"episode:(-?[0-9]{1,12})")
_DEMO_INDEX = re.compile(r"[0-9]{1,9}")
_PROMPTED_BY = {"demo": "a demonstration", "goal_image": "a goal image (a demonstration's final frame)"}


class PromptLookupError(UserError):
    """A prompt id or upload that the library cannot turn into a task context."""


@dataclass(frozen=True)
class PromptEntry:
    """One prompt: its canonical id and the raw task context the served method takes."""

    id: str
    context: Mapping


@dataclass(frozen=True)
class _Upload:
    context: Mapping
    nbytes: int


class PromptLibrary:
    """Prompts by id for one served model.

    Ids: ``"episode:<i>"`` (or the integer i) for episode i of the store; ``"<task id>"`` for the task's first
    demonstration and ``"<task id>#<k>"`` for its k-th (from 0); ``"upload:<hex>"`` for an uploaded demonstration.
    A Language model also takes any other text as its instruction (openpi's servers read their ``prompt`` so).

    Args:
        spec: the served model's :class:`DataSpec` (what its context holds).
        validate: the model's ``validate_context``; every prompt is checked by it before it is accepted.
        store: the episode store whose demonstrations are offered (None: uploads only).
        frames: the store's benchmark's frame source (cameras and goal images).
        max_uploads_per_client: uploads one connection holds; its oldest is let go when it uploads more.
        max_upload_bytes: the size of all uploads held at once; an upload beyond it is refused.
        cache: contexts built from the store kept in memory (building one may render frames).
    """

    def __init__(
        self,
        spec: DataSpec,
        validate,
        store: EpisodeStore | None,
        frames=None,
        max_uploads_per_client: int = 4,
        max_upload_bytes: int = 2**30,
        cache: int = 32,
    ):
        self.spec, self.validate, self.store, self.frames = spec, validate, store, frames
        self.max_uploads_per_client, self.max_upload_bytes = max_uploads_per_client, max_upload_bytes
        self.cache_size = cache
        self._cache: OrderedDict[int, Mapping] = OrderedDict()
        self._task_ids: dict[str, int] = {}
        if store is not None:
            self._task_ids = {str(t["id"]): i for i, t in enumerate(store.tasks)}
            self._task_episodes = store.task_episodes()
        # Uploads and who holds them: read and changed from the model's thread (get, upload) and the server's
        # (run, release), so under the lock.
        self._lock = threading.Lock()
        self._uploads: dict[str, _Upload] = {}
        self._uploaded: dict[Hashable, list[str]] = {}
        """Each connection's own uploads, oldest first."""
        self._running: dict[Hashable, str] = {}
        """The upload each connection's episode runs."""
        self._latest: str | None = None

    # ------------------------------------------------------------------ listing
    def describe(self, limit: int = 500) -> dict:
        """What a client may ask for: the store (by name), and its tasks with their demonstration counts (first
        `limit`)."""
        if self.store is None:
            return {"store": None, "episodes": 0, "tasks": [], "uploads": True}
        tasks = [
            {"id": str(t["id"]), "instruction": str(t.get("instruction") or ""), "demos": len(self._task_episodes[i])}
            for i, t in enumerate(self.store.tasks[:limit])
        ]
        return {
            "store": self.store.path.name,
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
        episode = self._parse_id(prompt)
        if episode is None:
            raise PromptLookupError(self._not_an_id(prompt))
        return episode

    def get(self, prompt: int | str) -> PromptEntry:
        """The validated raw context of prompt `prompt`: an id, or instruction text for a Language model."""
        if isinstance(prompt, str) and prompt.startswith(UPLOAD_PREFIX):
            return self._get_upload(prompt)
        episode = self._parse_id(prompt)
        if episode is None:
            if self.spec.context != "instruction":
                raise PromptLookupError(self._not_an_id(prompt))
            context = {"text": prompt}
            self.validate(context)
            return PromptEntry(prompt, context)
        if episode not in self._cache:
            context = task_context(self.store, episode, self.spec, self.frames)
            self.validate(context)
            self._cache[episode] = context
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        self._cache.move_to_end(episode)
        return PromptEntry(f"episode:{episode}", self._cache[episode])

    def _parse_id(self, prompt: int | str) -> int | None:
        """The store episode that `prompt` names; None if it is not a store id (a string in none of the forms);
        PromptLookupError if it is one but names nothing."""
        if isinstance(prompt, bool) or not isinstance(prompt, int | np.integer | str):
            raise PromptLookupError(f"prompt must be a string id or an episode number, got {type(prompt).__name__}")
        if isinstance(prompt, str) and len(prompt) > MAX_PROMPT_CHARS:
            raise PromptLookupError(f"prompt {_quote(prompt)} has over {MAX_PROMPT_CHARS} characters")
        if isinstance(prompt, str) and prompt.startswith("episode:") and self.store is not None:
            number = _EPISODE_ID.fullmatch(prompt)
            if number is None:
                raise PromptLookupError(
                    f"prompt {_quote(prompt)}: 'episode:' takes an episode number, "
                    f"0..{self.store.num_episodes - 1} in digits 0-9"
                )
            prompt = int(number.group(1))
        if isinstance(prompt, str):
            task_id, _, k = (prompt, "", "0") if prompt in self._task_ids else prompt.rpartition("#")
            if task_id not in self._task_ids:
                return None
            demos = self._task_episodes[self._task_ids[task_id]]
            if not _DEMO_INDEX.fullmatch(k) or int(k) >= len(demos):
                raise PromptLookupError(
                    f"prompt {_quote(prompt)}: task {task_id!r} has demonstrations #0..#{len(demos) - 1}"
                )
            return int(demos[int(k)])
        if self.store is None:
            raise PromptLookupError(NO_LIBRARY)
        if not 0 <= prompt < self.store.num_episodes:
            raise PromptLookupError(f"prompt {prompt}: the store has episodes 0..{self.store.num_episodes - 1}")
        return int(prompt)

    def _not_an_id(self, prompt: str) -> str:
        """Why string `prompt`, in none of the id forms, names no prompt: what bpp's 'prompt' is, and openpi's."""
        where = f"no such task in {self.store.path.name}" if self.store is not None else NO_LIBRARY
        return (
            f"prompt {_quote(prompt)}: {where}. bpp reads 'prompt' as the id of a demonstration, {ID_FORMS} (the "
            "metadata's 'prompts' lists the tasks); openpi's servers read it as instruction text, which only a "
            f"Language policy takes, and this one is prompted by {_PROMPTED_BY[self.spec.context]}"
        )

    # ------------------------------------------------------------------ uploads
    def upload(self, demo: Mapping, holder: Hashable = None) -> str:
        """Accept an uploaded demonstration ``{"obs": {key: (L, ...)}, "action": (L, A), "instruction": str}``
        (instruction optional, needed by the Language method), held by `holder` (a connection) until
        :meth:`release`, and return its handle."""
        context = self._context_from_demo(demo)
        digest = hashlib.sha256()
        _hash_into(digest, context)
        handle = UPLOAD_PREFIX + digest.hexdigest()[:20]
        with self._lock:
            mine = [h for h in self._uploaded.get(holder, []) if h != handle] + [handle]
            uploaded = {**self._uploaded, holder: mine[-self.max_uploads_per_client :]}
            uploads = {**self._uploads, handle: self._uploads.get(handle) or _Upload(context, _nbytes(context))}
            live = _live(uploaded, self._running, handle)
            total = sum(uploads[h].nbytes for h in live)
            if total > self.max_upload_bytes:
                raise PromptLookupError(
                    f"this upload ({_mib(uploads[handle].nbytes)}) would take the uploaded prompts the server holds "
                    f"to {_mib(total)}, over its limit of {_mib(self.max_upload_bytes)}; uploads are let go as the "
                    "connections that made them close"
                )
            self._uploads = {h: uploads[h] for h in live}
            self._uploaded, self._latest = uploaded, handle
        return handle

    def run(self, holder: Hashable, prompt_id: str) -> None:
        """`holder`'s episode now runs prompt `prompt_id` (an upload stays while an episode runs it)."""
        with self._lock:
            if prompt_id in self._uploads:
                self._running[holder] = prompt_id
            else:
                self._running.pop(holder, None)
            self._drop_unheld()

    def release(self, holder: Hashable) -> None:
        """`holder` (a connection) closed: let go of its uploads and of the one its episode ran."""
        with self._lock:
            self._uploaded.pop(holder, None)
            self._running.pop(holder, None)
            self._drop_unheld()

    @property
    def upload_bytes(self) -> int:
        """The size of the uploads held now."""
        with self._lock:
            return sum(u.nbytes for u in self._uploads.values())

    def _drop_unheld(self) -> None:
        live = _live(self._uploaded, self._running, self._latest)
        self._uploads = {h: u for h, u in self._uploads.items() if h in live}

    def _get_upload(self, prompt: str) -> PromptEntry:
        with self._lock:
            if prompt == LATEST_UPLOAD:
                if self._latest is None:
                    raise PromptLookupError(f"prompt {LATEST_UPLOAD!r}: nothing has been uploaded yet")
                prompt = self._latest
            if prompt not in self._uploads:
                raise PromptLookupError(
                    f"prompt {_quote(prompt)}: no such upload (an upload is kept while the connection that made it "
                    "is open, while an episode runs it, and while it is the newest; upload it again)"
                )
            return PromptEntry(prompt, self._uploads[prompt].context)

    def _context_from_demo(self, demo: Mapping) -> dict:
        """An uploaded demonstration as the served method's validated raw context (see the module docstring), its
        arrays copied out of the message."""
        if not isinstance(demo, Mapping):
            raise PromptLookupError("upload must be a demonstration: {'obs': {key: (L, ...)}, 'action': (L, A)}")
        unknown = sorted(map(str, set(demo) - set(UPLOAD_FIELDS)))
        if unknown:
            raise PromptLookupError(f"upload fields {unknown} are unknown; an upload holds {list(UPLOAD_FIELDS)}")
        kind = self.spec.context
        if kind == "instruction":
            text = demo.get("instruction")
            if not isinstance(text, str) or not text.strip():
                raise PromptLookupError("this server's method (Language) needs the upload's 'instruction' text")
            if len(text) > MAX_PROMPT_CHARS:
                raise PromptLookupError(f"upload 'instruction' has {len(text)} characters, over {MAX_PROMPT_CHARS}")
            context = {"text": text}
            self.validate(context)
            return context
        obs = demo.get("obs")
        if not isinstance(obs, Mapping):
            raise PromptLookupError("upload lacks 'obs', a dict of per-step arrays")
        if kind == "goal_image":
            key, size = self.spec.context_image_key, self.spec.context_image_size
            if key not in obs:
                raise PromptLookupError(f"upload obs lacks {key!r}, whose final frame is this method's goal image")
            frames = check_array(
                f"upload obs {key!r}", obs[key], (None, size, size, 3), np.uint8, error=PromptLookupError
            )
            if not len(frames):
                raise PromptLookupError(f"upload obs {key!r} holds no frames")
            context = {"image": frames[-1].copy()}
            self.validate(context)
            return context
        if "action" not in demo:
            raise PromptLookupError("upload lacks 'action', (steps, action dim)")
        keys = (*self.spec.lowdim_keys, *self.spec.image_keys)
        missing = [k for k in keys if k not in obs]
        if missing:
            raise PromptLookupError(f"upload obs lacks {missing}; this method's prompt needs {list(keys)}")
        # floating-point measurements only (the model's check also takes a store's integers), then the model's
        size = self.spec.image_size
        arrays = {
            k: check_array(f"upload obs {k!r}", obs[k], (None, size, size, 3), np.uint8, error=PromptLookupError)
            if k in self.spec.image_keys
            else check_array(
                f"upload obs {k!r}",
                obs[k],
                (None, None),
                np.float32,
                expected="(steps, width)",
                error=PromptLookupError,
            )
            for k in keys
        }
        action = check_array(
            "upload 'action'",
            demo["action"],
            (None, None),
            np.float32,
            expected="(steps, width)",
            error=PromptLookupError,
        )
        batch = self.validate({"obs": arrays, "action": action})
        # copies: arrays decoded from a message are views of all of it
        return {"obs": {k: np.array(v[0]) for k, v in batch["obs"].items()}, "action": np.array(batch["action"][0])}


def _live(uploaded: Mapping[Hashable, list[str]], running: Mapping[Hashable, str], latest: str | None) -> set[str]:
    """The uploads someone holds: a connection's own, those episodes run, and the newest."""
    return {h for mine in uploaded.values() for h in mine} | set(running.values()) | ({latest} if latest else set())


def _nbytes(value) -> int:
    if isinstance(value, Mapping):
        return sum(_nbytes(v) for v in value.values())
    if isinstance(value, str):
        return len(value.encode())
    return np.asarray(value).nbytes


def _mib(count: int) -> str:
    return f"{count / 2**20:.1f} MiB"


def _quote(text: str, limit: int = 80) -> str:
    """`text` quoted for a message, cut to `limit` characters (a prompt may be long; the reply need not be)."""
    return repr(text) if len(text) <= limit else repr(text[:limit]) + f"... ({len(text)} characters)"


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
