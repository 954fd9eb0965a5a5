"""The Language baseline: BPP's diffusion action decoder, conditioned on the observation history and an encoding
of the task's instruction (a text encoder trained or fine-tuned with the policy) in place of the prompt encoder.
By default the encoder is trained from scratch over UTF-8 bytes (offline, no extra package); a pretrained one comes
from a local Hugging Face folder the user supplies, pinned by its weights' SHA-256
(:class:`~bpp.policies.language.config.LanguageConfig`).

Tensor shapes at the boundaries (B: batch; Bt: instruction batch, 1 or B; To, T, A):

* context: ``{"text": [str] * Bt}``; encoded: (Bt, D)
* obs: ``{key: (B, To, ...)}`` raw; action: (B, T, A) raw
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from bpp.nn.text import (
    ByteTokenizer,
    PretrainedTextEncoder,
    PretrainedTokenizer,
    TextTransformer,
    check_weights,
    pretrained_text_dir,
)
from bpp.policies.language.config import LanguageConfig
from bpp.policies.model import ContextDiffusionPolicy
from bpp.policies.validation import ContextError


class LanguageModel(ContextDiffusionPolicy):
    """Language-conditioned policy (tensor-only; :class:`bpp.policies.agent.PolicyAgent` wraps it for rollouts)."""

    method = "language"
    context_kind = "instruction"

    def __init__(self, cfg: LanguageConfig, stats: Mapping[str, Mapping[str, list[float]]]):
        # The config ensures a pretrained encoder comes with its own (pretrained) tokenizer. Its folder is checked
        # first: a missing one is refused before the other networks are built.
        folder = pretrained_text_dir(cfg.pretrained_text_model) if cfg.tokenizer == "pretrained" else None
        super().__init__(cfg, stats)
        t = cfg.text
        self.tokenizer = ByteTokenizer() if folder is None else PretrainedTokenizer(folder)
        if cfg.text_encoder == "pretrained":
            if cfg.pretrained_text_sha256:  # recorded when training began (LanguageConfig.pinned)
                check_weights(folder, cfg.pretrained_text_sha256)
            self.text_encoder = PretrainedTextEncoder(folder)
            self.text_encoder.check_tokenizer(self.tokenizer)
        else:
            self.text_encoder = TextTransformer(
                self.tokenizer.vocab_size, t.dim, t.layers, t.heads, t.mlp_dim, t.max_tokens, t.dropout
            )
        self.build_head(self.text_encoder.dim)

    def validate_context(self, context: Mapping) -> dict:
        """Check a raw instruction ``{"text": str}`` and batch it; clear errors if bad."""
        if not isinstance(context, Mapping) or "text" not in context:
            raise ContextError("an instruction context must be a dict {'text': str}")
        text = context["text"]
        if not isinstance(text, str):
            raise ContextError(f"the instruction must be a str, got {type(text).__name__}")
        if not text.strip():
            raise ContextError("this task has no instruction; Language is not offered for it")
        tokens, limit = self.tokenizer.num_tokens(text), self.text_encoder.max_tokens
        if tokens > limit:
            raise ContextError(
                f"the instruction is {tokens} tokens ({self.tokenizer.unit}); this model accepts {limit}"
            )
        return {"text": [text]}

    never_compiled = ("tokenize",)
    """Left to Python by a compiled loss (:func:`bpp.policies.model.keep_eager`): traced, the instructions would be
    constants of the graph, and each new one would be compiled anew."""

    def tokenize(self, texts: list[str], multiple: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        """Instructions -> token ids and valid mask (Bt, longest rounded up to a `multiple`), on the model's
        device."""
        ids, valid = self.tokenizer(texts, self.text_encoder.max_tokens, multiple)
        device = next(self.text_encoder.parameters()).device
        return ids.to(device), valid.to(device)

    compiled_token_multiple = 16
    """A compiled loss pads token ids to a multiple of this: the padding is masked, and fewer lengths are fewer
    graphs (under ``--compile reduce-overhead`` each length is a CUDA graph recorded anew). Eager, no padding."""

    def encode_context(self, context: Mapping) -> torch.Tensor:
        """Instructions ``{"text": [str] * Bt}`` -> instruction embeddings (Bt, D), once per rollout."""
        multiple = self.compiled_token_multiple if torch.compiler.is_compiling() else 1
        return self.text_encoder(*self.tokenize(context["text"], multiple))
