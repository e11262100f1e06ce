"""Compiling numba kernels: cached on disk where possible, in memory otherwise.

numba raises at decoration time when `cache=True` finds no writable cache directory (a
read-only install without NUMBA_CACHE_DIR); a service must still start, so it then compiles
in memory (a few seconds on each start instead of once).
"""

from __future__ import annotations

import numba


def jit(fn=None, **options):
    """numba.njit(cache=True, nogil=True, **options), falling back to no disk cache.

    Use as @jit or @jit(inline="always")."""
    def wrap(f):
        try:
            return numba.njit(cache=True, nogil=True, **options)(f)
        except RuntimeError:  # no writable cache directory
            return numba.njit(nogil=True, **options)(f)

    return wrap(fn) if fn is not None else wrap
