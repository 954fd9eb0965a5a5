"""The observation encoder: raw observations -> one feature vector per entry (each camera, each low-dimensional
key)."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import nn

from bpp.nn.lowdim import LowDimEncoder
from bpp.nn.vision import ResNetGN
from bpp.policies.config import ObsConfig
from bpp.policies.normalizer import Normalizer


def encode_images(net: nn.Module, images: torch.Tensor) -> torch.Tensor:
    """Channels-last images (..., H, W, 3) (uint8 or [0, 1] floats) through an image encoder -> (..., F)."""
    lead = images.shape[:-3]
    flat = images.reshape(-1, *images.shape[-3:]).permute(0, 3, 1, 2)
    return net(flat).reshape(*lead, -1)


class ObsEncoder(nn.Module):
    """Raw observations -> one feature vector per entry (each camera and each low-dimensional key).

    Input: a dict of (..., dim) tensors (images (..., H, W, 3) uint8); output: a list of (..., F_e) tensors in
    :attr:`ObsConfig.entries` order. Leading dims are arbitrary (e.g. (B, To) or (B, L)).
    """

    def __init__(self, cfg: ObsConfig, normalizer: Normalizer):
        super().__init__()
        self.cfg = cfg
        self.normalizer = normalizer
        self.cameras = nn.ModuleDict(
            {
                k: ResNetGN(cfg.image_features, cfg.image_widths, cfg.image_blocks, cfg.image_stem, cfg.image_pool_grid)
                for k in cfg.image_keys
            }
        )
        lowdim = (*cfg.lowdim_keys, *cfg.proprio_keys)
        self.lowdim = nn.ModuleDict(
            {
                k: LowDimEncoder(normalizer.width(k), cfg.lowdim_features, cfg.lowdim_fourier_octaves)
                for k in (lowdim if cfg.lowdim_fourier_octaves > 0 else ())
            }
        )
        self.dims = [cfg.image_features] * len(cfg.image_keys)
        self.dims += [cfg.lowdim_features if k in self.lowdim else normalizer.width(k) for k in lowdim]

    def forward(self, obs: Mapping[str, torch.Tensor]) -> list[torch.Tensor]:
        out = []
        for key, net in self.cameras.items():
            out.append(encode_images(net, obs[key]))
        for key in (*self.cfg.lowdim_keys, *self.cfg.proprio_keys):
            x = self.normalizer.normalize(key, obs[key])
            out.append(self.lowdim[key](x) if key in self.lowdim else x)
        return out
