"""Behavior Prompting Policy: a demonstration as the prompt, a cross-attention prompt encoder, a diffusion decoder."""

from bpp.policies.bpp.config import PRESETS, BPPConfig
from bpp.policies.bpp.model import BPPModel

Config, Model = BPPConfig, BPPModel

__all__ = ["PRESETS", "BPPConfig", "BPPModel", "Config", "Model"]
