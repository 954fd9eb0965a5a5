"""LIBERO-Gen (in progress, issue 16): procedural task suites on LIBERO. So far: the task layer (suites.py)."""
