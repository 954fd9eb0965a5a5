"""Goal-Image baseline: the BPP action decoder conditioned on the observations and the prompt's final frame."""

from bpp.policies.goal_image.config import PRESETS, GoalImageConfig
from bpp.policies.goal_image.model import GoalImageModel

Config, Model = GoalImageConfig, GoalImageModel

__all__ = ["PRESETS", "GoalImageConfig", "GoalImageModel", "Config", "Model"]
