"""A small text encoder trained from scratch: a UTF-8 byte tokenizer and a pre-norm transformer.

Bytes need no vocabulary to learn or to store: any text tokenizes, and a checkpoint (weights + config) is all that
rebuilding the encoder takes. No pretrained weights can be downloaded here, so the encoder learns with the policy.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn


class ByteTokenizer:
    """Text -> token ids: [BOS] + the text's UTF-8 bytes (+3) + [EOS], padded with [PAD] to the longest."""

    PAD, BOS, EOS = 0, 1, 2
    OFFSET = 3
    vocab_size = 256 + OFFSET

    @staticmethod
    def num_tokens(text: str) -> int:
        return len(text.encode("utf-8")) + 2

    def __call__(self, texts: Sequence[str], max_tokens: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Token ids (B, L) long and their valid mask (B, L) bool, L = the longest text's tokens."""
        encoded = [[self.BOS, *(b + self.OFFSET for b in t.encode("utf-8")), self.EOS] for t in texts]
        longest = max(len(e) for e in encoded)
        if longest > max_tokens:
            raise ValueError(f"a text of {longest} tokens (UTF-8 bytes + 2) exceeds the encoder's {max_tokens}")
        ids = torch.full((len(encoded), longest), self.PAD, dtype=torch.long)
        for i, e in enumerate(encoded):
            ids[i, : len(e)] = torch.tensor(e)
        return ids, ids != self.PAD


class TextTransformer(nn.Module):
    """Token ids (B, L) + valid mask (B, L) -> one text embedding (B, D): the mean of the valid output tokens."""

    def __init__(self, vocab_size: int, dim: int, layers: int, heads: int, mlp_dim: int, max_tokens: int, dropout=0.0):
        super().__init__()
        self.embed = nn.Embedding(vocab_size, dim)
        self.pos = nn.Parameter(torch.randn(max_tokens, dim) * 0.02)
        layer = nn.TransformerEncoderLayer(
            dim, heads, mlp_dim, dropout, activation="gelu", batch_first=True, norm_first=True
        )
        self.encoder = nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(dim)

    def forward(self, ids: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        x = self.embed(ids) + self.pos[: ids.shape[1]]
        x = self.norm(self.encoder(x, src_key_padding_mask=~valid))
        weights = valid.unsqueeze(-1).to(x.dtype)
        return (x * weights).sum(1) / weights.sum(1).clamp_min(1.0)
