"""Camera frames a store holds (recorded or rendered when it was made), as a benchmark's frame source gives them."""

from __future__ import annotations

import numpy as np

from bpp.data.store import EpisodeStore
from bpp.media import resize_frames


def stored_frames(store: EpisodeStore, episode: int, key: str, size: int, last_only: bool = False, steps=None):
    """Camera `key`'s frames of a stored episode as the contract's ``frames`` gives them (all, the last, or `steps`),
    resized if another size is asked for: for benchmarks whose stores hold their camera frames."""
    sl = store.episode_slice(episode)
    if last_only:
        rows = store[key][sl.stop - 1 : sl.stop]
    elif steps is not None:
        rows = store[key].oindex[sl.start + np.asarray(steps, dtype=np.int64)]
    else:
        rows = store[key][sl]
    return resize_frames(np.asarray(rows), size)
