"""Language configuration and its named presets."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from bpp.policies.common import (
    CPU_OBS,
    DEBUG_DIFFUSION,
    PAPER_DIFFUSION,
    PAPER_OBS,
    DiffusionConfig,
    Horizons,
    ObsConfig,
)


@dataclass(frozen=True)
class TextEncoderConfig:
    """The instruction encoder: a pre-norm transformer over UTF-8 bytes, trained with the policy."""

    dim: int = 128
    """Width of the tokens and of the instruction embedding."""
    layers: int = 2
    heads: int = 4
    mlp_dim: int = 512
    max_tokens: int = 256
    """Longest instruction accepted, in UTF-8 bytes + 2."""
    dropout: float = 0.0

    def __post_init__(self):
        if self.dim % self.heads:
            raise ValueError(f"text dim {self.dim} must be divisible by heads {self.heads}")
        if self.max_tokens < 3:
            raise ValueError(f"text max_tokens must be >= 3, got {self.max_tokens}")


@dataclass(frozen=True)
class LanguageConfig:
    """Everything that defines a Language model (saved as JSON in every checkpoint)."""

    obs: ObsConfig = field(default_factory=ObsConfig)
    horizons: Horizons = field(default_factory=Horizons)
    diffusion: DiffusionConfig = field(default_factory=DiffusionConfig)
    action_key: str = "action"
    action_relative_to: str = ""
    """"": absolute actions (the paper). An observed position key (e.g. ``cursor_on_board``, in the frame of the
    actions' first dims): actions are learned and predicted as offsets from its value at the current step (see
    :meth:`bpp.policies.common.PolicyModel.normalize_actions`; on DrawAnything it did not help: BENCHMARKS.md)."""
    text_encoder: Literal["scratch"] = "scratch"
    """scratch: a byte-level transformer trained from scratch with the policy (the paper fine-tunes CLIP's text
    encoder; no pretrained text encoder can be downloaded here, and none ships in a package we can use)."""
    text: TextEncoderConfig = field(default_factory=TextEncoderConfig)

    def __post_init__(self):
        if self.text_encoder != "scratch":
            raise ValueError(f"text_encoder must be 'scratch', got {self.text_encoder!r}")


PRESETS: dict[str, LanguageConfig] = {
    # Tiny, for tests: seconds on a CPU.
    "debug": LanguageConfig(text=TextEncoderConfig(dim=32, layers=1, heads=2, mlp_dim=64), diffusion=DEBUG_DIFFUSION),
    # State-only DrawAnything on a 2-core CPU (observations as BPP's cpu preset).
    "cpu": LanguageConfig(obs=CPU_OBS),
    # The paper's sizes: 224x224 images through ResNet-18 (GroupNorm); U-Net [256, 512, 1024]; a text encoder of
    # CLIP ViT-B's text-tower size (12 layers, width 512, 8 heads), here trained from scratch.
    "paper": LanguageConfig(
        obs=PAPER_OBS, text=TextEncoderConfig(dim=512, layers=12, heads=8, mlp_dim=2048), diffusion=PAPER_DIFFUSION
    ),
}
