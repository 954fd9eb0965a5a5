"""ICRT (In-Context Robot Transformer): the prompt demonstration and the rollout in one causal transformer."""

from bpp.policies.icrt.config import PRESETS, ICRTConfig

Config = ICRTConfig
MODEL = "bpp.policies.icrt.model:ICRTModel"
"""The model's ``module:class``, imported only where a model is built (it imports torch)."""

__all__ = ["MODEL", "PRESETS", "Config", "ICRTConfig"]
