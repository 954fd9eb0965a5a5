"""The 1D-convolution U-Net with FiLM conditioning used as the action decoder (after Diffusion Policy).

Actions (B, T, A) are treated as an A-channel signal over T steps. Every residual block is modulated by a
feature-wise affine transform (scale and shift per channel, "FiLM") predicted from the conditioning vector:
the diffusion-step embedding concatenated with the task/observation features.

Every block's FiLM projection reads the same vector, so the network computes them all as one linear layer
(:attr:`ConditionalUnet1D.film`) and hands each block its slice: one matrix product instead of one per block, and
the conditioning's Mish once. Checkpoints written with a projection per block load into it unchanged
(:meth:`ConditionalUnet1D._join_block_films`).
"""

from __future__ import annotations

import math

import torch
from einops import rearrange
from torch import nn
from torch.nn import functional as F

from bpp.nn.norm import GroupNorm


class SinusoidalEmbedding(nn.Module):
    """(B,) diffusion steps -> (B, dim) sinusoidal features."""

    def __init__(self, dim: int):
        super().__init__()
        assert dim % 2 == 0, "embedding dim must be even"
        self.dim = dim

    def forward(self, steps: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=steps.device) / (half - 1))
        angles = steps.float()[:, None] * freqs[None]
        return torch.cat([angles.sin(), angles.cos()], dim=-1)


class _CpuMish(torch.autograd.Function):
    """Mish with its derivative, each from a handful of vectorised operations: ``tanh(softplus(x))`` written as
    ``n / (n + 2)`` with ``n = e^x (e^x + 2)``. On a CPU, torch's own ``mish`` and its backward run slower than these
    few vectorised passes at the decoder's sizes; the values agree to within float32 rounding. On a GPU, and inside
    ``torch.compile``, which fuses it, torch's own is used."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        e = torch.exp(x.clamp(max=20.0))  # beyond 20, n / (n + 2) is 1 in float32
        n = e * (e + 2)
        tanh_softplus = n / (n + 2)
        ctx.save_for_backward(x, tanh_softplus)
        return x * tanh_softplus

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        x, t = ctx.saved_tensors
        return grad * (t + x * (1 - t * t) * torch.sigmoid(x))


def mish(x: torch.Tensor) -> torch.Tensor:
    """``x * tanh(softplus(x))`` (torch's ``mish``), computed the faster way for `x`'s device."""
    if x.device.type == "cpu" and x.dtype == torch.float32 and not torch.compiler.is_compiling():
        return _CpuMish.apply(x)
    return F.mish(x)


class Mish(nn.Module):
    """:func:`mish` as a module (``nn.Mish``'s drop-in, same checkpoints: it has no parameters)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return mish(x)


class ConvNormAct(nn.Sequential):
    def __init__(self, c_in: int, c_out: int, kernel: int, groups: int):
        super().__init__(nn.Conv1d(c_in, c_out, kernel, padding=kernel // 2), GroupNorm(groups, c_out), Mish())


class FiLMResBlock(nn.Module):
    """Two conv blocks; the first one's output is scaled and shifted per channel by its FiLM parameters."""

    def __init__(self, c_in: int, c_out: int, kernel: int, groups: int):
        super().__init__()
        self.film_width = 2 * c_out
        """Width of this block's FiLM parameters (a scale and a shift per output channel)."""
        self.conv1 = ConvNormAct(c_in, c_out, kernel, groups)
        self.conv2 = ConvNormAct(c_out, c_out, kernel, groups)
        self.skip = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: torch.Tensor, film: torch.Tensor) -> torch.Tensor:
        """x: (B, C_in, T), film: (B, 2 C_out), the scales then the shifts -> (B, C_out, T)."""
        scale, shift = rearrange(film, "b (two c) -> two b c 1", two=2)
        h = self.conv1(x) * scale + shift
        return self.conv2(h) + self.skip(x)


class ConditionalUnet1D(nn.Module):
    """Noise-prediction network: (noisy actions (B, T, A), steps (B,), cond (B, C)) -> (B, T, A).

    Args:
        action_dim: A.
        cond_dim: size of the global conditioning vector (observation + task features).
        down_dims: channels at each resolution; T is halved between levels (T must be divisible by
            2 ** (len(down_dims) - 1)).
        kernel_size: temporal kernel of every convolution.
        step_embed_dim: size of the diffusion-step embedding.
        groups: GroupNorm groups.
    """

    def __init__(
        self,
        action_dim: int,
        cond_dim: int,
        down_dims: tuple[int, ...] = (256, 512, 1024),
        kernel_size: int = 5,
        step_embed_dim: int = 128,
        groups: int = 8,
    ):
        super().__init__()
        self.down_factor = 2 ** (len(down_dims) - 1)
        self.step_embed = nn.Sequential(
            SinusoidalEmbedding(step_embed_dim),
            nn.Linear(step_embed_dim, 4 * step_embed_dim),
            Mish(),
            nn.Linear(4 * step_embed_dim, step_embed_dim),
        )
        channels = [action_dim, *down_dims]
        self.down = nn.ModuleList()
        for i, (c_in, c_out) in enumerate(zip(channels[:-1], channels[1:], strict=True)):
            last = i == len(down_dims) - 1
            self.down.append(
                nn.ModuleList(
                    [
                        FiLMResBlock(c_in, c_out, kernel_size, groups),
                        FiLMResBlock(c_out, c_out, kernel_size, groups),
                        nn.Identity() if last else nn.Conv1d(c_out, c_out, 3, stride=2, padding=1),
                    ]
                )
            )
        mid = down_dims[-1]
        self.mid = nn.ModuleList(
            [
                FiLMResBlock(mid, mid, kernel_size, groups),
                FiLMResBlock(mid, mid, kernel_size, groups),
            ]
        )
        self.up = nn.ModuleList()
        for c_out, c_skip in zip(reversed(down_dims[:-1]), reversed(down_dims[1:]), strict=True):
            self.up.append(
                nn.ModuleList(
                    [
                        FiLMResBlock(2 * c_skip, c_out, kernel_size, groups),
                        FiLMResBlock(c_out, c_out, kernel_size, groups),
                        nn.ConvTranspose1d(c_out, c_out, 4, stride=2, padding=1),
                    ]
                )
            )
        self.head = nn.Sequential(
            ConvNormAct(down_dims[0], down_dims[0], kernel_size, groups), nn.Conv1d(down_dims[0], action_dim, 1)
        )
        self.film_widths = [block.film_width for block in self.blocks()]
        """Each block's share of :attr:`film`'s outputs, in :meth:`blocks` order."""
        self.film = nn.Linear(step_embed_dim + cond_dim, sum(self.film_widths))
        """Every block's FiLM projection of the conditioning (after a Mish), as one layer."""
        self._register_load_state_dict_pre_hook(self._join_block_films)

    def blocks(self) -> list[FiLMResBlock]:
        """The residual blocks in the order their FiLM parameters are laid out: down, middle, up."""
        return [
            *(block for level in self.down for block in level[:2]),
            *self.mid,
            *(block for level in self.up for block in level[:2]),
        ]

    def _join_block_films(self, state: dict, prefix: str, *args) -> None:
        """A state dict with a FiLM projection per block (``down.0.0.film.1.weight``, ...: the layout before they
        were joined) -> the joined :attr:`film`, the blocks' rows stacked in :meth:`blocks` order. Their products
        with the conditioning are the same; only the order of the sums may differ by rounding."""
        names = [
            *(f"down.{i}.{j}" for i in range(len(self.down)) for j in range(2)),
            *(f"mid.{i}" for i in range(len(self.mid))),
            *(f"up.{i}.{j}" for i in range(len(self.up)) for j in range(2)),
        ]
        for kind in ("weight", "bias"):
            old = [f"{prefix}{name}.film.1.{kind}" for name in names]
            if all(key in state for key in old):
                state[f"{prefix}film.{kind}"] = torch.cat([state.pop(key) for key in old])

    def forward(self, actions: torch.Tensor, steps: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        if actions.shape[1] % self.down_factor:
            raise ValueError(f"horizon {actions.shape[1]} must be divisible by {self.down_factor}")
        cond = torch.cat([self.step_embed(steps.expand(actions.shape[0])), cond], dim=-1)
        films = iter(self.film(mish(cond)).split(self.film_widths, dim=-1))
        x = rearrange(actions, "b t a -> b a t")
        skips = []
        for block1, block2, downsample in self.down:
            x = block2(block1(x, next(films)), next(films))
            skips.append(x)
            x = downsample(x)
        for block in self.mid:
            x = block(x, next(films))
        for block1, block2, upsample in self.up:
            x = torch.cat([x, skips.pop()], dim=1)
            x = upsample(block2(block1(x, next(films)), next(films)))
        return rearrange(self.head(x), "b a t -> b t a")
