"""ICRT (In-Context Robot Transformer): the prompt demonstration and the rollout in one causal transformer."""

from bpp.policies.icrt.config import PRESETS, ICRTConfig
from bpp.policies.icrt.model import ICRTModel

Config, Model = ICRTConfig, ICRTModel

__all__ = ["PRESETS", "Config", "ICRTConfig", "ICRTModel", "Model"]
