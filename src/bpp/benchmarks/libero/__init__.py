"""LIBERO-Gen: the Combination and Chain task suites on LIBERO, their scripted demonstrations, stores, rollouts and
LIBERO's own suites."""
