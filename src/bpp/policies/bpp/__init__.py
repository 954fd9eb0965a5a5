"""Behavior Prompting Policy: a demonstration as the prompt, a cross-attention prompt encoder, a diffusion decoder."""

from bpp.policies.bpp.config import BPPConfig
from bpp.policies.bpp.model import BPPModel

__all__ = ["BPPConfig", "BPPModel"]
