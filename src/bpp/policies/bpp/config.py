"""BPP configuration and its named presets."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from bpp.errors import UserError
from bpp.policies.config import (
    CPU_OBS,
    DEBUG_DIFFUSION,
    DEBUG_OBS,
    PAPER_DIFFUSION,
    PAPER_OBS,
    ContextDiffusionConfig,
    transformer_rules,
)
from bpp.utils import check_fields


@dataclass(frozen=True)
class PromptConfig:
    """How a demonstration becomes prompt tokens."""

    chunk_len: int = 10
    """Δt: one observation + proprio step and the Δt actions up to the next chunk form one chunk."""
    use_obs: bool = True
    """Include the observation entries (cameras and low-dimensional state) in each chunk."""
    use_proprio: bool = True
    use_action: bool = True
    action_fourier_octaves: int = 0
    """0: a chunk's actions enter its token through one linear layer (normalised values); k > 0: Fourier
    features over k octaves per action, then an MLP (the state-only presets: see bpp.nn.lowdim for why)."""
    pooling: Literal["all", "obs", "none"] = "all"
    """all: attention-pool every modality of a chunk into one token (the paper's BPP); obs: pool observation
    modalities, keep the action token separate; none: one token per modality (no pooling)."""
    num_sinks: int = 4
    """Learned attention-sink tokens at the start of the prompt."""
    max_steps: int = 800
    """Longest prompt (steps) accepted; sets the number of learned chunk positions."""
    rollout_memory: int = 0
    """K > 0: the policy also reads its own rollout's observations at the last K chunk boundaries (Δt, 2Δt, ...
    KΔt steps ago), which attend to the prompt beside the current ones; 0: the paper's BPP, which reads only its
    To-step history. A state-only stand-in for what a camera shows of the rollout so far."""

    def __post_init__(self):
        check_fields(
            self,
            ("chunk_len", self.chunk_len >= 1, ">= 1"),
            ("action_fourier_octaves", 0 <= self.action_fourier_octaves <= 16, "in [0, 16]"),
            ("num_sinks", self.num_sinks >= 0, ">= 0"),
            ("max_steps", self.max_steps >= 1, ">= 1"),
            ("rollout_memory", 0 <= self.rollout_memory <= 64, "in [0, 64]"),
        )
        if not (self.use_obs or self.use_proprio or self.use_action):
            raise UserError("the prompt must use at least one of obs, proprio, action")
        if self.pooling not in ("all", "obs", "none"):
            raise UserError(f"pooling must be all, obs or none, got {self.pooling!r}")

    @property
    def max_chunks(self) -> int:
        return -(-self.max_steps // self.chunk_len)

    @property
    def memory_offsets(self) -> tuple[int, ...]:
        """The rollout memory's step offsets from the current step, oldest first."""
        return tuple(-k * self.chunk_len for k in range(self.rollout_memory, 0, -1))


@dataclass(frozen=True)
class BPPConfig(ContextDiffusionConfig):
    """Everything that defines a BPP model (saved as JSON in every checkpoint): the shared fields
    (:class:`~bpp.policies.config.ContextDiffusionConfig`), the prompt and the prompt encoder."""

    prompt: PromptConfig = field(default_factory=PromptConfig)
    dim: int = 128
    """D: token width of the prompt encoder."""
    layers: int = 2
    heads: int = 4
    mlp_dim: int = 512
    dropout: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        check_fields(self, *transformer_rules(self))


PRESETS: dict[str, BPPConfig] = {
    # Tiny, for tests: seconds on a CPU.
    "debug": BPPConfig(
        obs=DEBUG_OBS,
        dim=32,
        layers=1,
        heads=2,
        mlp_dim=64,
        prompt=PromptConfig(num_sinks=2),
        diffusion=DEBUG_DIFFUSION,
    ),
    # A 2-core CPU: Fourier features for state inputs and prompt actions (see bpp.nn.lowdim), a small image encoder.
    "cpu": BPPConfig(obs=CPU_OBS, prompt=PromptConfig(action_fourier_octaves=6)),
    # The paper's sizes: prompt encoder 6 layers, D=768, MLP 3072, 8 heads; U-Net [256, 512, 1024], kernel 5,
    # step embedding 128; ResNet-18 (GroupNorm) for cameras.
    "paper": BPPConfig(obs=PAPER_OBS, dim=768, layers=6, heads=8, mlp_dim=3072, dropout=0.1, diffusion=PAPER_DIFFUSION),
}
"""Size presets; combine one with a benchmark's observation preset (bpp.policies.registry.Method.config)."""
