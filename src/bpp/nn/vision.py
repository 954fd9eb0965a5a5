"""A ResNet-style image encoder with GroupNorm, trained from scratch (no weights can be downloaded)."""

from __future__ import annotations

import torch
from torch import nn

from bpp.nn.norm import GroupNorm


def _group_norm(channels: int) -> GroupNorm:
    return GroupNorm(max(1, channels // 16), channels)


class BasicBlock(nn.Module):
    def __init__(self, c_in: int, c_out: int, stride: int):
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False),
            _group_norm(c_out),
            nn.ReLU(inplace=True),
            nn.Conv2d(c_out, c_out, 3, 1, 1, bias=False),
            _group_norm(c_out),
        )
        # The projection shortcut is a 1x1 convolution with the block's stride, taken as every stride-th pixel
        # followed by a 1x1 convolution (the same numbers): PyTorch's multi-threaded CPU backward of a *strided* 1x1
        # convolution on channels-last input corrupts memory at some batch sizes (torch 2.11 and 2.15; the crash
        # first seen on the GPU machine's 16 cores; BENCHMARKS.md).
        self.stride = stride
        self.skip = (
            nn.Identity()
            if stride == 1 and c_in == c_out
            else nn.Sequential(nn.Conv2d(c_in, c_out, 1, bias=False), _group_norm(c_out))
        )
        self.act = nn.ReLU(inplace=True)

    def forward(self, x):
        return self.act(self.body(x) + self.skip(x[:, :, :: self.stride, :: self.stride]))


class ResNetGN(nn.Module):
    """(B, 3, H, W) uint8-range or [0, 1] float images -> (B, out_dim) features.

    ``widths=(64, 128, 256, 512), blocks=(2, 2, 2, 2), stem="resnet"`` is ResNet-18 with GroupNorm (the
    paper-sized encoder); the CPU presets use narrower, shallower versions. The last feature map is average-pooled
    into a ``pool_grid`` x ``pool_grid`` grid, flattened and projected: 1 is ResNet's global pool, which keeps what
    the image holds but not where; a larger grid keeps where, one cell per region (a grid finer than the last map
    repeats its values).

    The stem: ``"resnet"`` is ResNet's (a 7x7 stride-2 convolution, then a 3x3 stride-2 max-pool: the first stage
    runs at a quarter of the image size); ``"conv5"`` one 5x5 stride-2 convolution, which keeps twice the resolution
    for small images (the CPU presets' 64x64 cameras) and costs 4x the first stages' compute at 224x224.
    """

    def __init__(
        self, out_dim: int, widths=(64, 128, 256, 512), blocks=(2, 2, 2, 2), stem: str = "conv5", pool_grid: int = 1
    ):
        super().__init__()
        if pool_grid < 1:
            raise ValueError(f"image pool grid must be >= 1, got {pool_grid}")
        if stem == "resnet":
            first = [nn.Conv2d(3, widths[0], 7, 2, 3, bias=False), _group_norm(widths[0]), nn.ReLU(inplace=True)]
            self.stem = nn.Sequential(*first, nn.MaxPool2d(3, 2, 1))
        elif stem == "conv5":
            self.stem = nn.Sequential(
                nn.Conv2d(3, widths[0], 5, 2, 2, bias=False), _group_norm(widths[0]), nn.ReLU(inplace=True)
            )
        else:
            raise ValueError(f"image stem must be 'resnet' or 'conv5', got {stem!r}")
        layers, c = [], widths[0]
        for i, (w, n) in enumerate(zip(widths, blocks, strict=True)):
            for j in range(n):
                layers.append(BasicBlock(c, w, 2 if (j == 0 and i > 0) else 1))
                c = w
        self.layers = nn.Sequential(*layers)
        self.pool = nn.AdaptiveAvgPool2d(pool_grid)
        self.proj = nn.Linear(c * pool_grid * pool_grid, out_dim)
        self.register_buffer("mean", torch.tensor([0.5, 0.5, 0.5]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor([0.25, 0.25, 0.25]).view(1, 3, 1, 1), persistent=False)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        if not self.stem[0].weight.is_contiguous():  # a channels-last encoder (GPU training): dense NHWC input
            images = images.contiguous(memory_format=torch.channels_last)
        # Otherwise frames stay as they come, channels-last strided (an (H, W, 3) image permuted): on a CPU that
        # trains the encoder 1.3x faster than copying them to channels-first.
        x = images.float() / 255.0 if images.dtype == torch.uint8 else images.float()
        x = (x - self.mean) / self.std
        x = self.layers(self.stem(x))
        return self.proj(self.pool(x).flatten(1))
