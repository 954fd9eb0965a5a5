"""Attention blocks: attention pooling and a transformer decoder that can report its cross-attention."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from einops import rearrange
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

    def forward(
        self,
        x: torch.Tensor,
        memory: torch.Tensor,
        memory_pad: torch.Tensor | None,
        want_attn: bool,
        memory_index: torch.Tensor | None = None,
    ):
        """x (B, Q, D) attends to memory (B, M, D), or with `memory_index` (B,) to memory (G, M, D) of which query
        row i reads row ``memory_index[i]``; memory_pad (B or G, M) is True where the memory is padding."""
        h = self.norm1(x)
        x = x + self.self_attn(h, h, h, need_weights=False)[0]
        out, attn = self._cross_attend(self.norm2(x), memory, memory_pad, memory_index, want_attn)
        x = x + out
        return x + self.mlp(self.norm3(x)), attn

    def _cross_attend(self, h, memory, pad, index, want_attn: bool):
        """``self.cross_attn(h, memory, memory)`` (its weights, its arithmetic up to rounding) with the keys and
        values projected once per memory row before `index` hands them to the queries: when G prompts serve B
        samples (training), the projection and its layout copies cost G rows instead of B."""
        attn = self.cross_attn
        dim, heads = attn.embed_dim, attn.num_heads
        q = F.linear(h, attn.in_proj_weight[:dim], attn.in_proj_bias[:dim])
        kv = F.linear(memory, attn.in_proj_weight[dim:], attn.in_proj_bias[dim:])
        if index is not None:
            kv = kv[index]
            pad = None if pad is None else pad[index]
        q = rearrange(q, "b n (h d) -> b h n d", h=heads)
        k, v = rearrange(kv, "b m (two h d) -> two b h m d", two=2, h=heads)
        keep = None if pad is None else ~pad[:, None, None, :]
        dropout = attn.dropout if self.training else 0.0
        if not want_attn:
            out, weights = F.scaled_dot_product_attention(q, k, v, attn_mask=keep, dropout_p=dropout), None
        else:  # the weights are wanted (inference): the same product, written out
            scores = (q @ k.transpose(-2, -1)) / math.sqrt(q.shape[-1])
            if keep is not None:
                scores = scores.masked_fill(~keep, float("-inf"))
            weights = scores.softmax(dim=-1)
            out = F.dropout(weights, dropout, self.training) @ v
            weights = weights.mean(dim=1)  # averaged over heads, as nn.MultiheadAttention averages them
        return attn.out_proj(rearrange(out, "b h n d -> b n (h d)")), weights


class CrossAttentionDecoder(nn.Module):
    """A stack of :class:`DecoderLayer`: queries (B, Q, D) attend to memory (B, M, D) with a (B, M) valid mask, or to
    G memories (G, M, D) shared by the B query rows through an index.

    Returns the outputs (B, Q, D) and, if asked, each layer's cross-attention weights (B, Q, M), head-averaged.
    """

    def __init__(self, dim: int, layers: int, heads: int, mlp_dim: int, dropout: float = 0.0):
        super().__init__()
        self.layers = nn.ModuleList([DecoderLayer(dim, heads, mlp_dim, dropout) for _ in range(layers)])
        self.norm = nn.LayerNorm(dim)

    def forward(self, queries, memory, memory_valid=None, return_attention: bool = False, memory_index=None):
        """With `memory_index` (B,), memory (G, M, D) and its valid mask (G, M) hold G memories, query row i
        attending to ``memory[memory_index[i]]`` (as if memory were ``memory[memory_index]``, without copying it)."""
        pad = None if memory_valid is None else ~memory_valid
        attentions = []
        x = queries
        for layer in self.layers:
            x, attn = layer(x, memory, pad, return_attention, memory_index)
            if return_attention:
                attentions.append(attn)
        return self.norm(x), attentions
