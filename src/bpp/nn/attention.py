"""Attention blocks: attention pooling and a transformer decoder that can report its cross-attention."""

from __future__ import annotations

import torch
from torch import nn


class AttentionPooling(nn.Module):
    """Merge a set of tokens into one with a learned query: (B, N, D) [+ (B, N) valid mask] -> (B, D)."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.query = nn.Parameter(torch.randn(1, 1, dim) * 0.02)
        self.attn = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.norm = nn.LayerNorm(dim)

    def forward(self, tokens: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        query = self.query.expand(tokens.shape[0], -1, -1)
        pad = None if valid is None else ~valid
        out, _ = self.attn(query, tokens, tokens, key_padding_mask=pad, need_weights=False)
        return self.norm(out[:, 0])


class DecoderLayer(nn.Module):
    """Pre-norm transformer decoder layer: self-attention, cross-attention to a memory, MLP."""

    def __init__(self, dim: int, heads: int, mlp_dim: int, dropout: float = 0.0):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.self_attn = nn.MultiheadAttention(dim, heads, dropout=dropout, batch_first=True)
        self.norm2 = nn.LayerNorm(dim)
        self.cross_attn = nn.MultiheadAttention(dim, heads, dropout=dropout, batch_first=True)
        self.norm3 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(
            nn.Linear(dim, mlp_dim), nn.GELU(), nn.Dropout(dropout), nn.Linear(mlp_dim, dim), nn.Dropout(dropout)
        )

    def forward(self, x: torch.Tensor, memory: torch.Tensor, memory_pad: torch.Tensor | None, want_attn: bool):
        h = self.norm1(x)
        x = x + self.self_attn(h, h, h, need_weights=False)[0]
        h = self.norm2(x)
        out, attn = self.cross_attn(
            h, memory, memory, key_padding_mask=memory_pad, need_weights=want_attn, average_attn_weights=True
        )
        x = x + out
        return x + self.mlp(self.norm3(x)), attn


class CrossAttentionDecoder(nn.Module):
    """A stack of :class:`DecoderLayer`: queries (B, Q, D) attend to memory (B, M, D) with a (B, M) valid mask.

    Returns the outputs (B, Q, D) and, if asked, each layer's cross-attention weights (B, Q, M), head-averaged.
    """

    def __init__(self, dim: int, layers: int, heads: int, mlp_dim: int, dropout: float = 0.0):
        super().__init__()
        self.layers = nn.ModuleList([DecoderLayer(dim, heads, mlp_dim, dropout) for _ in range(layers)])
        self.norm = nn.LayerNorm(dim)

    def forward(self, queries, memory, memory_valid=None, return_attention: bool = False):
        pad = None if memory_valid is None else ~memory_valid
        attentions = []
        x = queries
        for layer in self.layers:
            x, attn = layer(x, memory, pad, return_attention)
            if return_attention:
                attentions.append(attn)
        return self.norm(x), attentions
