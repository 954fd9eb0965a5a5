"""Language baseline: the BPP action decoder conditioned on the observations and the task's instruction."""

from bpp.policies.language.config import PRESETS, LanguageConfig

Config = LanguageConfig
MODEL = "bpp.policies.language.model:LanguageModel"
"""The model's ``module:class``, imported only where a model is built (it imports torch)."""

__all__ = ["MODEL", "PRESETS", "Config", "LanguageConfig"]
