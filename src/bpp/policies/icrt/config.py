"""ICRT configuration and its named presets."""

from __future__ import annotations

from dataclasses import dataclass

from bpp.errors import UserError
from bpp.policies.config import CPU_OBS, DEBUG_OBS, PAPER_OBS, Horizons, PolicyConfig, transformer_rules
from bpp.utils import check_fields


@dataclass(frozen=True)
class ICRTConfig(PolicyConfig):
    """Everything that defines an ICRT model (saved as JSON in every checkpoint).

    The token sequence is the prompt demonstration then the rollout, two tokens per chunk of N = `chunk_len`
    steps: the observation at the chunk's first step, then the chunk's N actions. So a context of `max_tokens`
    tokens holds ``max_tokens // 2`` chunks in all, prompt and rollout together.
    """

    chunk_len: int = 10
    """N: actions per action token, and steps between observation tokens (BPP's prompt chunk Δt)."""
    max_tokens: int = 256
    """Context limit (tokens; one learned position each). 256 holds an 800-step prompt plus a 400-step rollout
    at N = 10. A longer rollout keeps the prompt and its most recent chunks (see :mod:`bpp.policies.icrt.model`)."""
    min_rollout_chunks: int = 4
    """Rollout chunks that must fit after the prompt: a longer prompt is refused (this sets the prompt limit)."""
    dim: int = 256
    """D: token width."""
    layers: int = 6
    heads: int = 8
    mlp_dim: int = 1024
    dropout: float = 0.0

    def __post_init__(self):
        check_fields(
            self,
            ("chunk_len", self.chunk_len >= 1, ">= 1"),
            ("min_rollout_chunks", self.min_rollout_chunks >= 1, ">= 1"),
            *transformer_rules(self),
        )
        if self.max_tokens < 2 * (1 + self.min_rollout_chunks):
            raise UserError(
                f"max_tokens {self.max_tokens} can't hold a one-chunk prompt and {self.min_rollout_chunks} rollout "
                f"chunks (2 tokens each)"
            )

    @property
    def horizons(self) -> Horizons:
        """One observation in, N actions out, all N executed: the agent calls the model once per chunk."""
        return Horizons(n_obs_steps=1, horizon=self.chunk_len, n_action_steps=self.chunk_len)

    @property
    def max_prompt_steps(self) -> int:
        """The longest prompt that leaves room for `min_rollout_chunks` rollout chunks."""
        return (self.max_tokens // 2 - self.min_rollout_chunks) * self.chunk_len


PRESETS: dict[str, ICRTConfig] = {
    # Tiny, for tests: seconds on a CPU.
    "debug": ICRTConfig(obs=DEBUG_OBS, dim=32, layers=2, heads=2, mlp_dim=64, max_tokens=128),
    # A 2-core CPU (about 5M parameters; BPP's cpu preset has 8M, mostly its U-Net).
    "cpu": ICRTConfig(obs=CPU_OBS),
    # The paper's setting: ResNet-18 (GroupNorm) for cameras, as BPP's paper preset. The ICRT paper's transformer is
    # a Llama-2-style 12-layer, D=768 model (RMSNorm, SwiGLU, rotary positions); this one has the same size with
    # LayerNorm, GELU and learned positions.
    "paper": ICRTConfig(obs=PAPER_OBS, dim=768, layers=12, heads=12, mlp_dim=3072, dropout=0.1),
}
"""Size presets; combine one with a benchmark's observation preset (bpp.policies.registry.Method.config)."""
