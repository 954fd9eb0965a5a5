"""A long-running server's freed memory given back to the system (glibc's malloc through ctypes; NumPy's huge pages).
Why and what it changes: docs/studio.md, "Memory"; measured in BENCHMARKS.md, "Studio load"."""

from __future__ import annotations

import ctypes
import ctypes.util

try:
    from numpy._core.multiarray import _set_madvise_hugepage
except ImportError:  # NumPy 1.x
    try:
        from numpy.core.multiarray import _set_madvise_hugepage
    except ImportError:
        _set_madvise_hugepage = None


RELEASE_EVERY_S = 10.0
"""How often the studio gives freed memory back to the system (well under a millisecond of work each time)."""


def release_memory() -> None:
    """Give freed memory back to the system: glibc's malloc keeps what a burst of work freed for the next burst
    otherwise (up to its trim threshold, which grows to 64 MiB after large frees). ``malloc_trim`` releases it all
    from the main arena, but from the other arenas only the free pages below their top chunk: see
    :func:`make_memory_releasable`."""
    if _LIBC is not None:
        _LIBC.malloc_trim(0)


M_ARENA_MAX = -8
"""glibc's ``mallopt`` parameter: the most malloc arenas a process makes."""


def make_memory_releasable() -> None:
    """Set up this process so that :func:`release_memory` reaches all the memory it freed. Call it first thing, before
    threads allocate (an arena a thread already has stays).

    - One malloc arena for every thread (glibc ``M_ARENA_MAX`` 1): by default threads get up to 8 arenas per core, and
      ``malloc_trim`` leaves each arena's top chunk resident (measured after abuse on 2 cores: 30-55 MiB in 14 idle
      arenas). The studio's threads hold the GIL for most of their work, so sharing one arena costs them nothing
      measurable.
    - No transparent huge pages for NumPy's arrays: NumPy marks the memory of an array of 4 MiB or more for huge
      pages, and the kernel's khugepaged then fills the freed, released 2 MiB ranges of that memory back in (up to 8
      MiB at a time, seen every 10 s) until the next release."""
    if _LIBC is not None and hasattr(_LIBC, "mallopt"):
        _LIBC.mallopt(ctypes.c_int(M_ARENA_MAX), ctypes.c_int(1))
    if _set_madvise_hugepage is not None:
        _set_madvise_hugepage(False)


def _load_libc():
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        return libc if libc is not None and hasattr(libc, "malloc_trim") else None
    except OSError:
        return None


_LIBC = _load_libc()
