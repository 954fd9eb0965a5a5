"""Checks of raw task contexts: the errors a model raises for a context it cannot use, and the check of a
demonstration prompt shared by the methods that take one."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from bpp.errors import UserError
from bpp.policies.config import ObsConfig
from bpp.policies.normalizer import Normalizer


class ContextError(UserError):
    """A task context (demonstration prompt, goal image or instruction) that a model cannot use.

    Raised by ``validate_context``; the message names the input and what was expected.
    """


class PromptError(ContextError):
    """A demonstration prompt that a model cannot use; the message says what was expected."""


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
    """
    if not isinstance(prompt, Mapping) or "obs" not in prompt or "action" not in prompt:
        raise PromptError("a prompt must be a dict with 'obs' (a dict of per-step arrays) and 'action'")
    action_dim = normalizer.width(action_key)
    actions = np.asarray(prompt["action"], dtype=np.float32)
    if actions.ndim != 2 or actions.shape[1] != action_dim:
        raise PromptError(f"prompt actions must have shape (steps, {action_dim}) as in training, got {actions.shape}")
    steps = len(actions)
    if steps < chunk_len:
        raise PromptError(f"prompt has {steps} steps; at least one chunk of {chunk_len} steps is needed")
    if steps > max_steps:
        raise PromptError(f"prompt has {steps} steps; this model accepts at most {max_steps}{limit_note}")
    if not np.all(np.isfinite(actions)):
        raise PromptError("prompt actions contain NaN or infinite values")
    obs = {}
    for key in obs_cfg.entries:
        if key not in prompt["obs"]:
            raise PromptError(f"prompt obs lacks {key!r}; expected keys {obs_cfg.entries}")
        value = np.asarray(prompt["obs"][key])
        if len(value) != steps:
            raise PromptError(f"prompt obs {key!r} has {len(value)} steps, actions have {steps}")
        if key in obs_cfg.image_keys:
            size = obs_cfg.image_size
            if value.shape[1:] != (size, size, 3):
                raise PromptError(f"prompt images {key!r} must be (steps, {size}, {size}, 3), got {value.shape}")
        else:
            width = normalizer.width(key)
            if value.ndim != 2 or value.shape[1] != width:
                raise PromptError(f"prompt obs {key!r} must be (steps, {width}), got {value.shape}")
            if not np.all(np.isfinite(value)):
                raise PromptError(f"prompt obs {key!r} contains NaN or infinite values")
        obs[key] = value[None]
    return {"obs": obs, "action": actions[None], "valid": np.ones((1, steps), dtype=bool)}
