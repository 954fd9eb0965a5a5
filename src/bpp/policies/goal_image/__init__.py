"""Goal-Image baseline: the BPP action decoder conditioned on the observations and the prompt's final frame."""

from bpp.policies.goal_image.config import PRESETS, GoalImageConfig

Config = GoalImageConfig
MODEL = "bpp.policies.goal_image.model:GoalImageModel"
"""The model's ``module:class``, imported only where a model is built (it imports torch)."""

__all__ = ["MODEL", "PRESETS", "Config", "GoalImageConfig"]
