"""Datasets: the on-disk episode store shared by every benchmark, and loaders built on it."""
