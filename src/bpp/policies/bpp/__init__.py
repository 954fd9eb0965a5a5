"""Behavior Prompting Policy: a demonstration as the prompt, a cross-attention prompt encoder, a diffusion decoder."""

from bpp.policies.bpp.config import PRESETS, BPPConfig

Config = BPPConfig
MODEL = "bpp.policies.bpp.model:BPPModel"
"""The model's ``module:class``, imported only where a model is built (it imports torch)."""

__all__ = ["MODEL", "PRESETS", "Config", "BPPConfig"]
