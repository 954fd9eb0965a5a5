"""Goal-Image configuration and its named presets."""

from __future__ import annotations

from dataclasses import dataclass

from bpp.errors import UserError
from bpp.policies.config import (
    CPU_OBS,
    DEBUG_DIFFUSION,
    DEBUG_OBS,
    IMAGE_WIDTHS_RULE,
    PAPER_DIFFUSION,
    PAPER_OBS,
    ContextDiffusionConfig,
    ObsConfig,
    group_normable,
)
from bpp.utils import check_fields


@dataclass(frozen=True)
class GoalImageConfig(ContextDiffusionConfig):
    """Everything that defines a Goal-Image model (saved as JSON in every checkpoint): the shared fields
    (:class:`~bpp.policies.config.ContextDiffusionConfig`) and the goal image's.

    The goal is the final frame of the prompt demonstration from camera ``goal_camera``. With image observations
    it goes through that camera's own encoder (shared weights, as in the paper); with state-only observations
    through an encoder of its own, a ResNetGN of ``goal_widths`` x ``goal_blocks``.
    """

    goal_camera: str = "image"
    goal_image_size: int = 96
    """Goal images are (goal_image_size, goal_image_size, 3) uint8; with image observations, obs.image_size."""
    goal_features: int = 256
    """Width of the goal encoding (own encoder only; a shared camera encoder gives obs.image_features)."""
    goal_widths: tuple[int, ...] = (32, 64, 128, 256)
    goal_blocks: tuple[int, ...] = (1, 1, 1, 1)

    def __post_init__(self):
        super().__post_init__()
        widths, blocks = self.goal_widths, self.goal_blocks
        check_fields(
            self,
            ("goal_image_size", 8 <= self.goal_image_size <= 1024, "in [8, 1024] px"),
            ("goal_features", self.goal_features >= 1, ">= 1"),
            ("goal_widths", len(widths) >= 1 and all(group_normable(w) for w in widths), IMAGE_WIDTHS_RULE),
            ("goal_blocks", len(blocks) == len(widths) and all(b >= 1 for b in blocks), "one count >= 1 per width"),
        )
        if self.obs.image_keys:
            if self.goal_camera not in self.obs.image_keys:
                raise UserError(
                    f"goal_camera {self.goal_camera!r} is not among the observed cameras {self.obs.image_keys}; "
                    "the goal image shares that camera's encoder"
                )
            if self.goal_image_size != self.obs.image_size:
                raise UserError(
                    f"goal_image_size {self.goal_image_size} must equal obs.image_size {self.obs.image_size}: "
                    "with image observations the goal image goes through the camera's own encoder"
                )

    def observation_overrides(self, obs: ObsConfig, preset) -> dict:
        """The benchmark's goal camera; observed, the goal is its frame at its size (it shares the camera's encoder)."""
        if not obs.image_keys:
            return {"goal_camera": preset.goal_camera}
        camera = preset.goal_camera if preset.goal_camera in obs.image_keys else obs.image_keys[0]
        return {"goal_camera": camera, "goal_image_size": obs.image_size}

    @property
    def shares_camera_encoder(self) -> bool:
        return bool(self.obs.image_keys)


PRESETS: dict[str, GoalImageConfig] = {
    # Tiny, for tests: seconds on a CPU.
    "debug": GoalImageConfig(
        obs=DEBUG_OBS,
        goal_image_size=32,
        goal_features=16,
        goal_widths=(8, 16),
        goal_blocks=(1, 1),
        diffusion=DEBUG_DIFFUSION,
    ),
    # A 2-core CPU (encoders as BPP's cpu preset); a 96x96 goal image through its own encoder when the policy
    # observes no camera.
    "cpu": GoalImageConfig(obs=CPU_OBS),
    # The paper's sizes: ResNet-18 (GroupNorm), one encoder for the camera and the goal; U-Net [256, 512, 1024],
    # kernel 5, step embedding 128.
    "paper": GoalImageConfig(obs=PAPER_OBS, goal_image_size=224, diffusion=PAPER_DIFFUSION),
}
"""Size presets; combine one with a benchmark's observation preset (bpp.policies.registry.Method.config)."""
