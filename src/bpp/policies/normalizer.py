"""Per-key range normalisation whose statistics travel with the model (buffers, so checkpoints keep them)."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import nn

from bpp.errors import UserError


class NormalizationError(UserError):
    """Statistics and data disagree (a missing key or a different width): never silently passed through."""


class Normalizer(nn.Module):
    """Range-normalises each key to [-1, 1] from dataset min/max; stored as buffers, so it travels in checkpoints.

    Features with (almost) no range are only centred, so a constant feature maps to 0. For the keys a model
    predicts (`outputs`, e.g. the actions), :meth:`unnormalize` gives such a feature its constant back whatever the
    model produced: a dimension the data never moves (LIBERO-Gen's scripted demonstrations never roll or pitch the
    hand) is not the model's to move. Otherwise a sampler clipped to [-1, 1] could command anything in that range,
    full-speed rotations included.
    """

    def __init__(self, stats: Mapping[str, Mapping[str, list[float]]], keys: list[str], outputs: tuple[str, ...] = ()):
        super().__init__()
        self.keys = list(keys)
        for key in self.keys:
            if key not in stats:
                raise NormalizationError(f"no normalisation statistics for {key!r}; the dataset has {sorted(stats)}")
            lo = torch.tensor(stats[key]["min"], dtype=torch.float32)
            hi = torch.tensor(stats[key]["max"], dtype=torch.float32)
            span = hi - lo
            scale = torch.where(span > 1e-6, 2.0 / span.clamp_min(1e-6), torch.ones_like(span))
            offset = -(lo + hi) / 2 * scale
            self.register_buffer(f"{key}__scale", scale)
            self.register_buffer(f"{key}__offset", offset)
            if key in outputs:  # derived from the statistics, which checkpoints keep: not saved with the weights
                self.register_buffer(f"{key}__constant", span <= 1e-6, persistent=False)
                self.register_buffer(f"{key}__value", (lo + hi) / 2, persistent=False)

    def width(self, key: str) -> int:
        return getattr(self, f"{key}__scale").numel()

    def scale(self, key: str) -> torch.Tensor:
        """Normalised units per raw unit of `key`, (width,)."""
        return getattr(self, f"{key}__scale")

    def _params(self, key: str, x: torch.Tensor):
        if key not in self.keys:
            raise NormalizationError(f"no normalisation statistics for {key!r}; known keys: {self.keys}")
        scale, offset = getattr(self, f"{key}__scale"), getattr(self, f"{key}__offset")
        if x.shape[-1] != scale.numel():
            raise NormalizationError(f"{key!r} has width {x.shape[-1]}, statistics have width {scale.numel()}")
        return scale, offset

    def normalize(self, key: str, x: torch.Tensor) -> torch.Tensor:
        scale, offset = self._params(key, x)
        return x.float() * scale + offset

    def unnormalize(self, key: str, x: torch.Tensor) -> torch.Tensor:
        scale, offset = self._params(key, x)
        raw = (x - offset) / scale
        constant = getattr(self, f"{key}__constant", None)
        return raw if constant is None else torch.where(constant, getattr(self, f"{key}__value"), raw)
