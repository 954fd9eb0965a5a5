"""Environments. Importing this package registers them with Gymnasium."""

import gymnasium as gym

DRAW_ENV_ID = "bpp/DrawAnything-v0"

if DRAW_ENV_ID not in gym.registry:
    gym.register(DRAW_ENV_ID, entry_point="bpp.envs.draw.env:DrawEnv")
