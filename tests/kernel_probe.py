"""Run one mocapd or calibkit command line in this process, then write what numba did as JSON.

Used by tests/test_kernels_cache.py in a child process with its own NUMBA_CACHE_DIR:
    python tests/kernel_probe.py OUT.json mocapd|calibkit ARGS...
OUT.json holds the command's exit code, every numba compile seen through numba's own
"numba:compile" event (any dispatcher, made through calibkit.core.jit or not), and per
kernel made through calibkit.core.jit its cache loads and compiles (numba's counters).
"""

from __future__ import annotations

import importlib
import json
import sys

from numba.core import event


class _Compiles(event.Listener):
    def __init__(self) -> None:
        self.names: list[str] = []

    def on_start(self, ev) -> None:
        func = getattr(ev.data.get("dispatcher"), "py_func", None)
        self.names.append(f"{getattr(func, '__module__', '?')}."
                          f"{getattr(func, '__qualname__', '?')}")

    def on_end(self, ev) -> None:
        pass


def main() -> None:
    out, prog, args = sys.argv[1], sys.argv[2], sys.argv[3:]
    compiles = _Compiles()
    event.register("numba:compile", compiles)
    from calibkit.clitools import run_app

    app = importlib.import_module({"mocapd": "daemon.cli", "calibkit": "calibkit.cli"}[prog]).app
    sys.argv = [prog, *args]
    code = 0
    try:
        run_app(app, prog)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    from calibkit.core.jit import cache_counts, kernel_name, kernels

    per_kernel = {kernel_name(k): cache_counts(k) for k in kernels()}
    with open(out, "w", encoding="utf-8") as handle:
        json.dump({"code": code, "compiled": compiles.names,
                   "kernels": {n: {"loaded": h, "compiled": m}
                               for n, (h, m) in per_kernel.items()}}, handle)


if __name__ == "__main__":
    main()
