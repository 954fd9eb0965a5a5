"""Nonlinear embeddings of low-dimensional inputs (positions, pen state, actions).

Why: attention matches a query to a key by a dot product. If positions enter tokens through a linear layer, the
score is bilinear in the two positions, so a query at x attends to the key that lies furthest along x, not the one
nearest x. Fourier features make the dot product a smooth function of the *difference* of the two inputs
(sin a sin b + cos a cos b = cos(a - b)), so "attend to the prompt chunk near where I am" becomes learnable. The
paper's image encoder gives its tokens this nonlinearity for free; state-only policies need it explicitly.
"""

from __future__ import annotations

import math

import torch
from torch import nn


class FourierFeatures(nn.Module):
    """(..., d) inputs scaled to about [-1, 1] -> (..., d * (1 + 2 * octaves)): x, sin(2^k pi x), cos(2^k pi x)."""

    def __init__(self, octaves: int):
        super().__init__()
        self.octaves = octaves
        self.register_buffer("freqs", math.pi * 2.0 ** torch.arange(octaves), persistent=False)

    def out_dim(self, in_dim: int) -> int:
        return in_dim * (1 + 2 * self.octaves)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        angles = (x[..., None] * self.freqs).flatten(-2)
        return torch.cat([x, angles.sin(), angles.cos()], dim=-1)


class LowDimEncoder(nn.Module):
    """Fourier features followed by a two-layer MLP: (..., in_dim) -> (..., out_dim)."""

    def __init__(self, in_dim: int, out_dim: int, octaves: int = 6):
        super().__init__()
        self.fourier = FourierFeatures(octaves)
        self.mlp = nn.Sequential(
            nn.Linear(self.fourier.out_dim(in_dim), out_dim), nn.GELU(), nn.Linear(out_dim, out_dim)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.mlp(self.fourier(x))
