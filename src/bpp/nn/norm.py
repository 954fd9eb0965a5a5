"""GroupNorm that keeps its input's precision under autocast."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


class GroupNorm(nn.GroupNorm):
    """``nn.GroupNorm`` (same parameters, same checkpoints) that, under autocast, normalises in the activations'
    own precision (bf16; the kernels still accumulate the statistics in fp32) instead of autocast's fp32: casting
    every activation to fp32 and back was the largest part of a paper-sized GPU training step (copies). Without
    autocast (a CPU, inference) it is ``nn.GroupNorm`` exactly."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not torch.is_autocast_enabled(x.device.type):
            return super().forward(x)
        with torch.autocast(x.device.type, enabled=False):
            weight = None if self.weight is None else self.weight.to(x.dtype)
            bias = None if self.bias is None else self.bias.to(x.dtype)
            return F.group_norm(x, self.num_groups, weight, bias, self.eps)
