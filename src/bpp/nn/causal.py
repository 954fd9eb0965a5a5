"""A causal (decoder-only) transformer that can append tokens to a key/value cache.

Sequences may contain padding: every token has a ``valid`` flag, and no token attends to an invalid one (except
itself, which keeps the attention rows of padding tokens finite: their keys and values are then finite too, so
masking them out never multiplies a zero weight by NaN). Positions are the caller's business: add them to the
tokens before calling, so that a padded sequence can carry per-sample positions.

Running a sequence in one call or in several calls that extend a :class:`KVCache` gives the same outputs (up to
float rounding), which is what makes incremental inference possible.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from einops import rearrange
from torch import nn
from torch.nn import functional as F


@dataclass
class KVCache:
    """Keys and values of every layer for the S tokens seen so far, and which of them may be attended."""

    keys: list[torch.Tensor]  # per layer (B, H, S, Dh)
    values: list[torch.Tensor]  # per layer (B, H, S, Dh)
    valid: torch.Tensor  # (B, S) bool

    def expand(self, batch: int) -> KVCache:
        """A cache of batch 1 shared by `batch` sequences (views, no copy)."""
        assert self.valid.shape[0] == 1, f"only a cache of batch 1 can be expanded, got {self.valid.shape[0]}"
        return KVCache(
            [k.expand(batch, -1, -1, -1) for k in self.keys],
            [v.expand(batch, -1, -1, -1) for v in self.values],
            self.valid.expand(batch, -1),
        )


class CausalSelfAttention(nn.Module):
    def __init__(self, dim: int, heads: int, dropout: float = 0.0):
        super().__init__()
        self.heads, self.dropout = heads, dropout
        self.qkv = nn.Linear(dim, 3 * dim)
        self.out = nn.Linear(dim, dim)

    def forward(self, x, mask, past_keys=None, past_values=None, attention: list | None = None):
        """x (B, S_new, D); mask (B, 1, S_new, S_past + S_new) bool, True = may attend.

        Returns the output (B, S_new, D) and the keys and values of all S_past + S_new tokens (B, H, S, Dh). Given a
        list `attention`, appends the last new token's attention weights over all S tokens, averaged over heads
        (B, S).
        """
        q, k, v = rearrange(self.qkv(x), "b s (three h d) -> three b h s d", three=3, h=self.heads)
        if past_keys is not None:
            k, v = torch.cat([past_keys, k], dim=2), torch.cat([past_values, v], dim=2)
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=self.dropout if self.training else 0.0)
        if attention is not None:
            scores = (q[:, :, -1:] @ k.transpose(-1, -2)) * q.shape[-1] ** -0.5  # (B, H, 1, S)
            scores = scores.masked_fill(~mask[:, :, -1:], float("-inf"))
            attention.append(scores.softmax(-1).mean(1)[:, 0])
        return self.out(rearrange(y, "b h s d -> b s (h d)")), k, v


class CausalBlock(nn.Module):
    """Pre-norm block: causal self-attention, then an MLP."""

    def __init__(self, dim: int, heads: int, mlp_dim: int, dropout: float = 0.0):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = CausalSelfAttention(dim, heads, dropout)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, mlp_dim), nn.GELU(), nn.Linear(mlp_dim, dim))
        self.drop = nn.Dropout(dropout)

    def forward(self, x, mask, past_keys=None, past_values=None, attention: list | None = None):
        h, k, v = self.attn(self.norm1(x), mask, past_keys, past_values, attention)
        x = x + self.drop(h)
        return x + self.drop(self.mlp(self.norm2(x))), k, v


class CausalTransformer(nn.Module):
    """A stack of :class:`CausalBlock` with a final LayerNorm, run on a whole sequence or appended to a cache."""

    def __init__(self, dim: int, layers: int, heads: int, mlp_dim: int, dropout: float = 0.0):
        super().__init__()
        if dim % heads:
            raise ValueError(f"dim {dim} must be divisible by heads {heads}")
        self.blocks = nn.ModuleList([CausalBlock(dim, heads, mlp_dim, dropout) for _ in range(layers)])
        self.norm = nn.LayerNorm(dim)

    def forward(
        self, x: torch.Tensor, valid: torch.Tensor, cache: KVCache | None = None, attention: list | None = None
    ) -> tuple[torch.Tensor, KVCache]:
        """Run tokens x (B, S_new, D) (positions already added) that follow the cached ones.

        Args:
            x: the new tokens.
            valid: (B, S_new) bool; invalid tokens (padding) are never attended by other tokens.
            cache: keys and values of the tokens before x (None: x is the whole sequence).
            attention: a list to which each layer appends the last token's attention over all cached and new tokens,
                averaged over heads (B, S); None: not computed.

        Returns:
            outputs (B, S_new, D) and the cache extended by x (the given cache is not modified).
        """
        new = valid.shape[1]
        past = 0 if cache is None else cache.valid.shape[1]
        all_valid = valid if cache is None else torch.cat([cache.valid, valid], dim=1)
        query_slot = torch.arange(past, past + new, device=x.device)[:, None]
        key_slot = torch.arange(past + new, device=x.device)[None, :]
        mask = (key_slot <= query_slot) & (all_valid[:, None, :] | (key_slot == query_slot))  # (B, S_new, S)
        mask = mask[:, None]  # one mask for every head
        keys, values = [], []
        for i, block in enumerate(self.blocks):
            past_k = None if cache is None else cache.keys[i]
            past_v = None if cache is None else cache.values[i]
            x, k, v = block(x, mask, past_k, past_v, attention)
            keys.append(k)
            values.append(v)
        return self.norm(x), KVCache(keys, values, all_valid)
