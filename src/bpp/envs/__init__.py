"""Benchmarks and their environments (one folder each; see :mod:`bpp.envs.benchmark` for the contract).

Importing this package registers the environments with Gymnasium."""

from bpp.envs.registry import register_gym_envs

register_gym_envs()
