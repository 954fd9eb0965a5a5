"""What a freshly started interpreter (multiprocessing's spawn start method, as a data-loader worker may use) reads
of a store. A module of its own, so that the spawned process imports nothing but the store to run it."""

from __future__ import annotations

import sys
from pathlib import Path

from bpp.core.registry import open_store
from bpp.data.store import EpisodeStore


def read_key(source: str | Path | EpisodeStore, key: str) -> tuple[list[str], list[str], object]:
    """(the bpp.benchmarks modules imported before the store is used, the store's keys, per-step key `key`) for a
    store given by its path (opened as its benchmark presents it) or as a pickled copy."""
    before = sorted(m for m in sys.modules if m.startswith("bpp.benchmarks."))
    store = source if isinstance(source, EpisodeStore) else open_store(source)
    return before, store.keys, store.array(key)
