"""Compiling numba kernels: cached on disk where possible, in memory otherwise; said if so.

numba raises at decoration time when `cache=True` finds no writable cache directory (a
read-only install without NUMBA_CACHE_DIR); a service must still start, so it then compiles
in memory (a few seconds on each start instead of once).

A kernel missing from the cache compiles the first time it runs: seconds to minutes on a
small machine, with nothing else to show for it. numba announces each real compile (never a
cache load) as a "numba:compile" event, so a listener here prints one line on stderr the
first time a module's kernels compile in a process: a user waiting learns why, and that
`mocapd build-kernels` does it ahead. Every kernel made through `jit` is also listed
(`kernels()`) with numba's own cache counters, so a test can prove a command compiled
nothing.
"""

from __future__ import annotations

import sys
import threading

import numba
from numba.core import event

_KERNELS: list = []  # every dispatcher made through jit(), in definition order
_LOCK = threading.Lock()
_ANNOUNCED: set[str] = set()  # modules whose compiling has been said in this process
_NOTICE = {"on": True, "stream": None}  # the compile notice: said or not, where (stderr)


def jit(fn=None, **options):
    """numba.njit(cache=True, nogil=True, **options), falling back to no disk cache.

    Use as @jit or @jit(inline="always")."""
    def wrap(f):
        try:
            kernel = numba.njit(cache=True, nogil=True, **options)(f)
        except RuntimeError:  # no writable cache directory
            kernel = numba.njit(nogil=True, **options)(f)
        _KERNELS.append(kernel)
        return kernel

    return wrap(fn) if fn is not None else wrap


def kernels() -> list:
    """Every kernel made through jit() in the modules imported so far."""
    return list(_KERNELS)


def kernel_name(kernel) -> str:
    return f"{kernel.py_func.__module__}.{kernel.py_func.__qualname__}"


def cache_counts(kernel) -> tuple[int, int]:
    """(signatures loaded from the disk cache, signatures compiled) for this kernel in
    this process: numba's own counters, bumped only by a real load or compile."""
    stats = kernel.stats
    return sum(stats.cache_hits.values()), sum(stats.cache_misses.values())


def is_cached(kernel) -> bool | None:
    """Whether the disk cache holds compiled code of this kernel's current source, for
    some argument types (None: it cannot tell, e.g. a kernel cached in memory only). Reads
    numba's small index file, which numba itself empties when the source changes."""
    try:
        return bool(kernel._cache._cache_file._load_index())
    except (AttributeError, OSError, EOFError):  # numba's internals moved, or no cache
        return None


def set_compile_notice(on: bool, stream=None) -> None:
    """Say (on stderr, or `stream`) or do not say that kernels compile: off while
    `mocapd build-kernels` compiles on purpose and says so itself."""
    _NOTICE["on"], _NOTICE["stream"] = on, stream


class _CompileNotice(event.Listener):
    """One stderr line per module, the first time one of its kernels really compiles."""

    def on_start(self, ev) -> None:
        dispatcher = ev.data.get("dispatcher") if isinstance(ev.data, dict) else None
        func = getattr(dispatcher, "py_func", None)
        module = getattr(func, "__module__", None)
        if module is None or not module.startswith(("calibkit", "daemon", "projector")):
            return  # numba's own internals compile through the same event
        stream = _NOTICE["stream"] or sys.stderr
        with _LOCK:
            if not _NOTICE["on"] or module in _ANNOUNCED:
                return
            _ANNOUNCED.add(module)
        try:
            stream.write(f"compiling the {module} kernels, once (`mocapd build-kernels` "
                         "does this ahead) ...\n")
            stream.flush()
        except (OSError, ValueError):  # a closed stream must not stop the compile
            pass

    def on_end(self, ev) -> None:
        pass


event.register("numba:compile", _CompileNotice())
