"""Language configuration and its named presets."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
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
    (:class:`~bpp.policies.config.ContextDiffusionConfig`) and the instruction encoder's.

    The default, and the ``debug`` and ``cpu`` presets, encode instructions with a transformer trained from scratch
    over UTF-8 bytes: it needs no vocabulary, no weights and no extra package, so it trains offline anywhere. No
    maker of a pretrained text encoder (OpenAI's CLIP, the sentence-transformers authors' MiniLM) publishes its
    weights on a package registry, so none can be a dependency of bpp, and nothing is downloaded at run time. The
    ``paper`` preset fine-tunes a pretrained encoder as the paper does (CLIP's text tower), from a local Hugging Face
    folder the user supplies (``pretrained_text_model``); without one it stops before reading any data, saying what
    to pass.
    """

    text_encoder: Literal["scratch", "pretrained"] = "scratch"
    """scratch: a transformer sized by ``text``, trained from scratch with the policy. pretrained: the encoder in the
    folder ``pretrained_text_model``, fine-tuned with the policy (the ``paper`` preset; the paper fine-tunes CLIP's
    text tower). A CLIP folder loads only its text tower, pooled at the end-of-text token as CLIP pools; any other
    Hugging Face text encoder is mean-pooled over its valid tokens (:class:`bpp.nn.text.PretrainedTextEncoder`)."""
    tokenizer: Literal["bytes", "pretrained"] = "bytes"
    """bytes: UTF-8 bytes, no vocabulary and no extra package, only with the scratch encoder (the default, and the
    ``debug`` and ``cpu`` presets'). pretrained: the tokenizer in the folder ``pretrained_text_model`` (CLIP's
    byte-level BPE, BERT's WordPiece, ...; needs the ``language`` extra): required by a pretrained encoder, possible
    with the scratch one."""
    pretrained_text_model: str = ""
    """A local Hugging Face model folder (config.json, weights, tokenizer files), read when ``text_encoder`` or
    ``tokenizer`` is pretrained: e.g. a copy of openai/clip-vit-base-patch32 (CLIP, which the paper fine-tunes),
    made once where there is a network (``hf download openai/clip-vit-base-patch32 --local-dir PATH``). Nothing is
    downloaded at run time, and bpp ships no weights. The folder must still be there, with the same weights, when a
    checkpoint of this model is loaded: the architecture and tokenizer are read from it."""
    pretrained_text_sha256: dict[str, str] = field(default_factory=dict)
    """The SHA-256 of each weight file of ``pretrained_text_model`` (model.safetensors or pytorch_model.bin, or their
    shards), by file name: recorded when training starts (:meth:`pinned`), and checked whenever the model is built,
    so that a checkpoint is refused, naming the file and both digests, if the folder's weights changed since. Given
    at the start of training, the folder must already hold those weights."""
    text: TextEncoderConfig = field(default_factory=TextEncoderConfig)

    def __post_init__(self):
        super().__post_init__()
        if self.text_encoder not in ("scratch", "pretrained"):
            raise UserError(f"text_encoder must be 'scratch' or 'pretrained', got {self.text_encoder!r}")
        if self.tokenizer not in ("pretrained", "bytes"):
            raise UserError(f"tokenizer must be 'pretrained' or 'bytes', got {self.tokenizer!r}")
        if self.text_encoder == "pretrained" and self.tokenizer != "pretrained":
            raise UserError("a pretrained text encoder needs its own tokenizer: set tokenizer='pretrained'")
        if self.pretrained_text_sha256 and self.text_encoder != "pretrained":
            raise UserError(
                "pretrained_text_sha256 pins a pretrained text encoder's weights; text_encoder is 'scratch'"
            )

    @property
    def reads_pretrained(self) -> bool:
        """Whether the model reads the folder ``pretrained_text_model`` (its encoder or its tokenizer)."""
        return self.text_encoder == "pretrained" or self.tokenizer == "pretrained"

    def pinned(self, recorded: Mapping | None = None) -> LanguageConfig:
        """This config with the pretrained encoder's weights pinned (``pretrained_text_sha256``), checked before a
        run reads any data: a missing folder is a UserError saying what to pass, and digests already given (or
        `recorded` by the run being resumed, for the same folder) must match the folder's."""
        if not self.reads_pretrained:
            return self
        # bpp.nn.text imports torch; a config is otherwise read without it
        from bpp.nn.text import check_weights, pretrained_text_dir, weights_sha256

        folder = pretrained_text_dir(self.pretrained_text_model)
        if self.text_encoder != "pretrained":
            return self  # the scratch encoder reads only the tokenizer files
        pins = self.pretrained_text_sha256
        if not pins and recorded and recorded.get("pretrained_text_model") == self.pretrained_text_model:
            pins = recorded.get("pretrained_text_sha256") or {}
        if pins:
            check_weights(folder, pins)
            return replace(self, pretrained_text_sha256=dict(pins))
        return replace(self, pretrained_text_sha256=weights_sha256(folder))


PRESETS: dict[str, LanguageConfig] = {
    # Tiny, for tests: seconds on a CPU (a byte tokenizer, so no vocabulary-sized embedding).
    "debug": LanguageConfig(
        obs=DEBUG_OBS, text=TextEncoderConfig(dim=32, layers=1, heads=2, mlp_dim=64), diffusion=DEBUG_DIFFUSION
    ),
    # A 2-core CPU (encoders as BPP's cpu preset); a small scratch encoder over UTF-8 bytes: offline, no extra.
    "cpu": LanguageConfig(obs=CPU_OBS),
    # The paper's sizes: ResNet-18 (GroupNorm) for cameras; U-Net [256, 512, 1024]; a pretrained text encoder
    # fine-tuned with the policy (CLIP's text tower in the paper), from the local folder the user passes as
    # --model.pretrained-text-model (none: training stops at once, saying so).
    "paper": LanguageConfig(
        obs=PAPER_OBS, text_encoder="pretrained", tokenizer="pretrained", diffusion=PAPER_DIFFUSION
    ),
}
"""Size presets; combine one with a benchmark's observation preset (bpp.policies.registry.Method.config)."""
