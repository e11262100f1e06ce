"""Kernels compile even where numba cannot write its cache (a read-only install)."""

from __future__ import annotations

import numba
import numpy as np

from calibkit.core import jit as jit_module


def test_jit_falls_back_to_memory_when_no_cache_can_be_written(monkeypatch) -> None:
    real = numba.njit
    calls = []

    def njit(*args, **options):  # numba itself calls njit too: pass those through
        if not args:
            calls.append(options)
            if options.get("cache"):
                raise RuntimeError("cannot cache function: no locator available")
        return real(*args, **options)

    monkeypatch.setattr(jit_module.numba, "njit", njit)

    @jit_module.jit
    def total(a):
        s = 0.0
        for x in a:
            s += x
        return s

    assert total(np.arange(5.0)) == 10.0
    assert calls[0]["cache"] is True and "cache" not in calls[1]
