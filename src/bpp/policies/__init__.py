"""Policies: one folder per method (BPP, Goal-Image, Language, ICRT) plus shared parts.

Every method's model implements the contract described in :mod:`bpp.policies.registry` (the diffusion-decoder
methods by subclassing :class:`bpp.policies.model.ContextDiffusionPolicy`), so one training loop and one
inference agent serve them all.
"""
