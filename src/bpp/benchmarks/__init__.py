"""Benchmarks and their environments (one folder each; see :mod:`bpp.benchmarks.contract` for the contract).

Importing this package registers the environments with Gymnasium."""

from bpp.benchmarks.registry import register_gym_envs

register_gym_envs()
