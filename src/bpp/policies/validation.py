"""Checks of raw task contexts: the errors a model raises for a context it cannot use, the check of a
demonstration prompt shared by the methods that take one, and the values a feature may take
(:func:`feature_bounds`), which every array from outside is checked against (:func:`bpp.data.arrays.check_array`)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from bpp.data.arrays import Bounds, check_array
from bpp.errors import UserError
from bpp.policies.config import ObsConfig
from bpp.policies.normalizer import Normalizer


class ContextError(UserError):
    """A task context (demonstration prompt, goal image or instruction) that a model cannot use.

    Raised by ``validate_context``; the message names the input and what was expected.
    """


class PromptError(ContextError):
    """A demonstration prompt that a model cannot use; the message says what was expected."""


MAX_NORMALIZED = 1000.0
"""How far a feature may lie outside its training range, in the normalized units where that range is [-1, 1]: much
further than any sensor or demonstration worth acting on, and close enough that the networks' float32 arithmetic
stays finite (3e38 in a position makes every action NaN)."""


def feature_bounds(normalizer: Normalizer, key: str) -> Bounds:
    """The raw values that feature `key` may take, (width,) each: :data:`MAX_NORMALIZED` either side."""
    scale = normalizer.scale(key).double().cpu().numpy()
    offset = getattr(normalizer, f"{key}__offset").double().cpu().numpy()
    low, high = (-MAX_NORMALIZED - offset) / scale, (MAX_NORMALIZED - offset) / scale
    return Bounds(low, high, f"its training range widened {MAX_NORMALIZED:g}-fold")


def validate_demo_context(
    prompt: Mapping,
    obs_cfg: ObsConfig,
    normalizer: Normalizer,
    action_key: str,
    chunk_len: int,
    max_steps: int,
    limit_note: str = "",
) -> dict:
    """Check a raw demonstration prompt ``{"obs": {key: (L, ...)}, "action": (L, A)}`` and batch it.

    Every observation entry of `obs_cfg` must be present with L steps (images (L, H, W, 3) at the model's size,
    low-dimensional keys at their statistics' width, finite), actions (L, A) finite, and L between one chunk
    (`chunk_len`) and `max_steps` (`limit_note` may say why that limit). Returns the prompt with batch dimension 1
    and ``valid`` (1, L) all True; raises :class:`PromptError` naming the input and what was expected.

    A prompt may instead carry ``"valid": (L,)`` all False: no prompt (its steps, at least one, are padding that
    the model attends to none of; the no-prompt control of :func:`bpp.data.contexts.prompt_steps`).
    """
    if not isinstance(prompt, Mapping) or "obs" not in prompt or "action" not in prompt:
        raise PromptError("a prompt must be a dict with 'obs' (a dict of per-step arrays) and 'action'")
    if not isinstance(prompt["obs"], Mapping):
        raise PromptError(f"a prompt's 'obs' must be a dict of per-step arrays, got {type(prompt['obs']).__name__}")
    action_dim = normalizer.width(action_key)
    actions = check_array(
        "prompt actions",
        prompt["action"],
        (None, action_dim),
        np.float32,
        kinds="fiub",
        bounds=feature_bounds(normalizer, action_key),
        expected=f"(steps, {action_dim}) as in training",
        error=PromptError,
    )
    steps = len(actions)
    blank = _blank_prompt(prompt, steps)
    if steps < (1 if blank else chunk_len):
        raise PromptError(f"prompt has {steps} steps; at least one chunk of {chunk_len} steps is needed")
    if steps > max_steps:
        raise PromptError(f"prompt has {steps} steps; this model accepts at most {max_steps}{limit_note}")
    obs = {}
    for key in obs_cfg.entries:
        if key not in prompt["obs"]:
            raise PromptError(f"prompt obs lacks {key!r}; expected keys {obs_cfg.entries}")
        name = f"prompt obs {key!r}"
        if key in obs_cfg.image_keys:
            size = obs_cfg.image_size
            value = check_array(name, prompt["obs"][key], (None, size, size, 3), np.uint8, error=PromptError)
        else:
            bounds = feature_bounds(normalizer, key)
            value = check_array(
                name, prompt["obs"][key], (None, normalizer.width(key)), np.float32, kinds="fiub", bounds=bounds,
                error=PromptError,
            )  # fmt: skip
        if len(value) != steps:
            raise PromptError(f"prompt obs {key!r} has {len(value)} steps, actions have {steps}")
        obs[key] = value[None]
    return {"obs": obs, "action": actions[None], "valid": np.full((1, steps), not blank)}


def _blank_prompt(prompt: Mapping, steps: int) -> bool:
    """Whether `prompt` is marked as no prompt (``"valid"`` all False); raises for any other ``"valid"``."""
    if "valid" not in prompt:
        return False
    valid = np.asarray(prompt["valid"])
    if valid.dtype != bool or valid.shape != (steps,) or valid.any():
        raise PromptError(
            f"a prompt's 'valid' may only mark all of its {steps} steps False (no prompt), got "
            f"{valid.dtype} {valid.shape} with {int(np.count_nonzero(valid))} True"
        )
    return True
