"""Policies: one folder per method (BPP, and later Goal-Image, Language, ICRT) plus shared parts.

Every method's model implements the :class:`bpp.policies.base.PolicyModel` contract, so one training loop and
one inference agent serve them all.
"""
