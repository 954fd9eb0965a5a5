"""Language baseline: the BPP action decoder conditioned on the observations and the task's instruction."""

from bpp.policies.language.config import PRESETS, LanguageConfig
from bpp.policies.language.model import LanguageModel

Config, Model = LanguageConfig, LanguageModel

__all__ = ["PRESETS", "LanguageConfig", "LanguageModel", "Config", "Model"]
