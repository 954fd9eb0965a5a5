"""The Goal-Image baseline: BPP's diffusion action decoder, conditioned on the observation history and an encoding
of the goal image (the prompt demonstration's final frame) in place of the prompt encoder.

Tensor shapes at the boundaries (B: batch; Bg: goal batch, 1 or B; To, T, A):

* context: ``{"image": (Bg, H, W, 3) uint8}``; encoded: (Bg, F)
* obs: ``{key: (B, To, ...)}`` raw; action: (B, T, A) raw
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from bpp.data.arrays import check_array
from bpp.nn.vision import ResNetGN
from bpp.policies.goal_image.config import GoalImageConfig
from bpp.policies.model import ContextDiffusionPolicy
from bpp.policies.observation import encode_images
from bpp.policies.validation import ContextError


class GoalImageModel(ContextDiffusionPolicy):
    """Goal-Image policy (tensor-only; :class:`bpp.policies.agent.PolicyAgent` wraps it for rollouts)."""

    method = "goal_image"
    context_kind = "goal_image"

    def __init__(self, cfg: GoalImageConfig, stats: Mapping[str, Mapping[str, list[float]]]):
        super().__init__(cfg, stats)
        if cfg.shares_camera_encoder:
            # Not registered a second time: the camera's weights are saved (and updated) once.
            self.goal_encoder = None
            self.build_head(cfg.obs.image_features)
        else:
            self.goal_encoder = ResNetGN(cfg.goal_features, cfg.goal_widths, cfg.goal_blocks)
            self.build_head(cfg.goal_features)

    def goal_network(self) -> ResNetGN:
        """The goal image's encoder: the observed camera's own (shared weights), or the model's own."""
        return self.obs_encoder.cameras[self.cfg.goal_camera] if self.goal_encoder is None else self.goal_encoder

    def context_spec(self) -> dict:
        return {"context_image_key": self.cfg.goal_camera, "context_image_size": self.cfg.goal_image_size}

    def validate_context(self, context: Mapping) -> dict:
        """Check a raw goal ``{"image": (H, W, 3) uint8}`` and batch it; clear errors if bad."""
        size = self.cfg.goal_image_size
        expected = f"{{'image': ({size}, {size}, 3) uint8 RGB array}}"
        if not isinstance(context, Mapping) or "image" not in context:
            raise ContextError(f"a goal-image context must be a dict {expected}")
        shape = (size, size, 3)
        name, expected = "the goal image", f"{shape} as in training"
        image = check_array(name, context["image"], shape, np.uint8, expected=expected, error=ContextError)
        return {"image": image[None]}

    def encode_context(self, context: Mapping) -> torch.Tensor:
        """Goal images ``{"image": (Bg, H, W, 3) uint8}`` -> goal features (Bg, F), once per rollout."""
        return encode_images(self.goal_network(), context["image"])
