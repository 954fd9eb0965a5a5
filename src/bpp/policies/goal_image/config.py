"""Goal-Image configuration and its named presets."""

from __future__ import annotations

from dataclasses import dataclass, field

from bpp.policies.common import (
    BOARD_OBS,
    CPU_IMAGE_OBS,
    CPU_OBS,
    DEBUG_DIFFUSION,
    PAPER_DIFFUSION,
    PAPER_OBS,
    DiffusionConfig,
    Horizons,
    ObsConfig,
)


@dataclass(frozen=True)
class GoalImageConfig:
    """Everything that defines a Goal-Image model (saved as JSON in every checkpoint).

    The goal is the final frame of the prompt demonstration from camera ``goal_camera``. With image observations
    it goes through that camera's own encoder (shared weights, as in the paper); with state-only observations
    through an encoder of its own, a ResNetGN of ``goal_widths`` x ``goal_blocks``.
    """

    obs: ObsConfig = field(default_factory=ObsConfig)
    horizons: Horizons = field(default_factory=Horizons)
    diffusion: DiffusionConfig = field(default_factory=DiffusionConfig)
    action_key: str = "action"
    action_relative_to: str = ""
    """"": absolute actions (the paper). An observed position key (e.g. ``cursor_on_board``, in the frame of the
    actions' first dims): actions are learned and predicted as offsets from its value at the current step (see
    :meth:`bpp.policies.common.PolicyModel.normalize_actions`; on DrawAnything it did not help: BENCHMARKS.md)."""
    goal_camera: str = "image"
    goal_image_size: int = 96
    """Goal images are (goal_image_size, goal_image_size, 3) uint8; with image observations, obs.image_size."""
    goal_features: int = 256
    """Width of the goal encoding (own encoder only; a shared camera encoder gives obs.image_features)."""
    goal_widths: tuple[int, ...] = (32, 64, 128, 256)
    goal_blocks: tuple[int, ...] = (1, 1, 1, 1)

    def __post_init__(self):
        if self.goal_image_size < 8:
            raise ValueError(f"goal_image_size must be >= 8, got {self.goal_image_size}")
        if len(self.goal_widths) != len(self.goal_blocks):
            raise ValueError(f"goal_widths {self.goal_widths} and goal_blocks {self.goal_blocks} differ in length")
        if self.obs.image_keys:
            if self.goal_camera not in self.obs.image_keys:
                raise ValueError(
                    f"goal_camera {self.goal_camera!r} is not among the observed cameras {self.obs.image_keys}; "
                    "the goal image shares that camera's encoder"
                )
            if self.goal_image_size != self.obs.image_size:
                raise ValueError(
                    f"goal_image_size {self.goal_image_size} must equal obs.image_size {self.obs.image_size}: "
                    "with image observations the goal image goes through the camera's own encoder"
                )

    @property
    def shares_camera_encoder(self) -> bool:
        return bool(self.obs.image_keys)


PRESETS: dict[str, GoalImageConfig] = {
    # Tiny, for tests: seconds on a CPU.
    "debug": GoalImageConfig(
        goal_image_size=32, goal_features=16, goal_widths=(8, 16), goal_blocks=(1, 1), diffusion=DEBUG_DIFFUSION
    ),
    # State-only DrawAnything on a 2-core CPU (observations as BPP's cpu preset) + a 96x96 goal image.
    "cpu": GoalImageConfig(obs=CPU_OBS),
    # As BPP's cpu-board preset: state and actions in the board's frame (not the paper's setting).
    "cpu-board": GoalImageConfig(obs=BOARD_OBS, action_key="action_on_board"),
    # As BPP's cpu-image preset: a 64x64 camera + proprioception; the goal frame goes through the camera's encoder.
    "cpu-image": GoalImageConfig(obs=CPU_IMAGE_OBS, goal_image_size=CPU_IMAGE_OBS.image_size),
    # The paper's sizes: 224x224 images through ResNet-18 (GroupNorm), one encoder for the camera and the goal;
    # U-Net [256, 512, 1024], kernel 5, step embedding 128.
    "paper": GoalImageConfig(obs=PAPER_OBS, goal_image_size=224, diffusion=PAPER_DIFFUSION),
}
