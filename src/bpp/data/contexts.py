"""Task contexts: what a method is conditioned on, built from a stored demonstration the same way for training
and for evaluation (:func:`task_context`), and batched (:func:`batch_context`, :func:`collate_contexts`).

A raw context is what :meth:`PolicyAgent.reset` takes and what ``model.validate_context`` checks:

* ``demo``: ``{"obs": {key: (L, ...)}, "action": (L, A)}``, the whole demonstration (the behavior prompt); with
  ``"valid": (L,)`` all False, no prompt at all (the policy attends to none of its steps; a control);
* ``goal_image``: ``{"image": (H, W, 3) uint8}``, its final observation from one camera;
* ``instruction``: ``{"text": str}``, the task's instruction.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

from bpp.data.spec import DataSpec
from bpp.data.store import EpisodeStore
from bpp.errors import UserError

FrameSource = Callable[..., np.ndarray]
"""``frames(store, episode, key, size, last_only=False, steps=None)``: (T, size, size, 3) uint8 frames of an
episode's observations from camera `key`; with ``last_only``, just the final observation, (1, size, size, 3); with
``steps``, those steps' (k, size, size, 3). Each benchmark provides one (see
:class:`bpp.core.contract.Benchmark`)."""


PROMPT_EDITS = ("shuffled", "first-half", "none")
"""Evaluation's prompt controls that edit a rollout's own demonstration (see :func:`prompt_steps`)."""
CONTROL_CHUNK = 10
"""Steps per chunk that the shuffled control keeps together: the paper's prompt chunk (one second at 10 Hz)."""


def prompt_steps(length: int, edit: str | None, seed: int) -> np.ndarray | None:
    """The steps of a `length`-step demonstration that an `edit` control prompts with, in order (None: all of them,
    unedited). shuffled: its whole chunks of :data:`CONTROL_CHUNK` steps in an order drawn from `seed`, a shorter
    last chunk last; first-half: steps 0 .. ceil(length / 2) - 1; none: no step (no prompt)."""
    if edit is None:
        return None
    if edit == "none":
        return np.zeros(0, dtype=np.int64)
    if edit == "first-half":
        return np.arange(-(-length // 2))
    if edit == "shuffled":
        whole = length // CONTROL_CHUNK
        order = np.random.default_rng([seed, length]).permutation(whole)
        steps = (order[:, None] * CONTROL_CHUNK + np.arange(CONTROL_CHUNK)).reshape(-1)
        return np.concatenate([steps, np.arange(whole * CONTROL_CHUNK, length)])
    raise ValueError(f"unknown prompt edit {edit!r}; known: {', '.join(PROMPT_EDITS)}")


def check_edit_applies(kind: str, edit: str | None) -> None:
    """Raise if prompt control `edit` cannot apply to a method whose context is of `kind`: a goal-image method
    cannot go without its goal."""
    if edit == "none" and kind == "goal_image":
        raise UserError("a goal-image policy cannot run without its goal: --prompts none does not apply")


def task_context(
    store: EpisodeStore,
    episode: int,
    spec: DataSpec,
    frames: FrameSource | None = None,
    max_steps: int | None = None,
    obs_stride: int = 1,
    steps: np.ndarray | None = None,
) -> dict:
    """The raw task context of kind ``spec.context`` from demonstration `episode` of `store`.

    `frames` renders or reads camera frames (needed for image keys and goal images); `max_steps` cuts a
    demonstration prompt (training does, to the model's limit; evaluation passes whole prompts to validation);
    with `obs_stride` k > 1 a demonstration's observations are those of steps 0, k, 2k, ... only, and the context
    says so (``"obs_stride": k``; training's batches, for a method whose ``spec.context_obs_stride`` is k).
    `steps` (episode-relative indices, in the order wanted) edits the demonstration first, as evaluation's prompt
    controls do (:func:`prompt_steps`): a demonstration context is made of those steps, a goal image is the frame
    of the latest of them; an instruction is unaffected. No steps at all is no prompt: a demonstration all of whose
    steps are marked invalid, an empty instruction; a goal-image method cannot go without its goal.
    """
    kind = spec.context
    if kind == "instruction":
        task = int(store.column("task_index")[episode])
        if steps is not None and not len(steps):
            return {"text": ""}
        return {"text": str(store.tasks[task].get("instruction") or "")}
    needs = spec.image_keys if kind == "demo" else (spec.context_image_key,)
    if needs and frames is None:
        raise UserError(f"{store.path}: benchmark {store.benchmark!r} provides no image observations")
    if steps is not None:
        return _edited_context(store, episode, spec, frames, np.asarray(steps, dtype=np.int64))
    if kind == "goal_image":
        return {"image": frames(store, episode, spec.context_image_key, spec.context_image_size, last_only=True)[0]}
    sl = store.episode_slice(episode)
    stop = sl.stop if max_steps is None else min(sl.stop, sl.start + max_steps)
    # Copies of the store's in-memory arrays, which a caller may not edit through its context; frames are the
    # benchmark's own (or, in training, cached ones that batching copies), so they are not copied again.
    obs = {key: store.array(key)[sl.start : stop : obs_stride].copy() for key in spec.lowdim_keys}
    for key in spec.image_keys:
        if obs_stride == 1 and stop == sl.stop:
            obs[key] = frames(store, episode, key, spec.image_size)
        else:
            obs[key] = frames(store, episode, key, spec.image_size, steps=np.arange(0, stop - sl.start, obs_stride))
    context = {"obs": obs, "action": store.array(spec.action_key)[sl.start : stop].copy()}
    if obs_stride > 1:
        context["obs_stride"] = obs_stride
    return context


def _edited_context(store: EpisodeStore, episode: int, spec: DataSpec, frames, steps: np.ndarray) -> dict:
    """:func:`task_context` of demonstration `episode` made of its steps `steps` (a goal image: the latest one's;
    no steps: no prompt, its first step marked invalid)."""
    sl = store.episode_slice(episode)
    if not len(steps):
        check_edit_applies(spec.context, "none")
        context = _edited_context(store, episode, spec, frames, np.zeros(1, dtype=np.int64))
        return {**context, "valid": np.zeros(1, dtype=bool)}
    if steps.min() < 0 or steps.max() >= sl.stop - sl.start:
        raise ValueError(f"prompt steps must be a selection of the episode's {sl.stop - sl.start} steps")
    if spec.context == "goal_image":
        latest = [int(steps.max())]  # a goal has no order: shuffled chunks keep the demonstration's goal
        return {"image": frames(store, episode, spec.context_image_key, spec.context_image_size, steps=latest)[0]}
    obs = {key: store.array(key)[sl.start + steps] for key in spec.lowdim_keys}
    for key in spec.image_keys:
        obs[key] = frames(store, episode, key, spec.image_size, steps=steps)
    return {"obs": obs, "action": store.array(spec.action_key)[sl.start + steps]}


def batch_context(kind: str, context: Mapping) -> dict:
    """A raw context -> the same with batch dimension 1 (a demonstration gains ``valid`` (1, L): its own, if it
    has one, else all True)."""
    if kind == "instruction":
        return {"text": [context["text"]]}
    if kind == "goal_image":
        return {"image": np.asarray(context["image"])[None]}
    actions = np.asarray(context["action"])
    batched = {
        "obs": {k: np.asarray(v)[None] for k, v in context["obs"].items()},
        "action": actions[None],
        "valid": np.asarray(context.get("valid", np.ones(len(actions), dtype=bool)), dtype=bool)[None],
    }
    if context.get("obs_stride", 1) > 1:
        batched["obs_stride"] = np.array([context["obs_stride"]])
    return batched


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


def padded_length(steps: int, multiple: int, limit: int) -> int:
    """`steps` rounded up to a multiple of `multiple` (0: unchanged), but not past `limit` (nor below `steps`)."""
    if multiple <= 0:
        return steps
    return max(steps, min(-(-steps // multiple) * multiple, limit))


def pad_demo_context(context: Mapping, steps: int) -> dict:
    """A batched demonstration context (see :func:`collate_contexts`) padded to `steps` steps: its actions and
    ``valid`` (False past the end) to `steps`, its observations to ``ceil(steps / obs_stride)`` entries, zeros.

    Padding changes no result (what lies past ``valid`` is masked); it gives a batch one of a few fixed shapes,
    which a compiled training step needs (each new shape is compiled again)."""
    stride = int(np.asarray(context["obs_stride"])[0]) if "obs_stride" in context else 1

    def pad(array: np.ndarray, length: int) -> np.ndarray:
        extra = length - array.shape[1]
        assert extra >= 0, f"cannot pad {array.shape[1]} steps to {length}"
        return np.pad(array, [(0, 0), (0, extra)] + [(0, 0)] * (array.ndim - 2)) if extra else array

    padded = dict(context)
    padded["action"], padded["valid"] = pad(context["action"], steps), pad(context["valid"], steps)
    padded["obs"] = {k: pad(v, -(-steps // stride)) for k, v in context["obs"].items()}
    return padded


def index_contexts(context, index):
    """Rows `index` (B,) of a batched context (nested dicts of arrays or tensors along axis 0; lists of strings)."""
    if isinstance(context, Mapping):
        return {k: index_contexts(v, index) for k, v in context.items()}
    if isinstance(context, list):
        return [context[int(i)] for i in index]
    return context[index]
