"""Ending a `mocapd start` process at once when everything is written: no interpreter teardown.

Why: after SIGTERM the daemon stops its threads, flushes every output and closes its files
and sockets in well under 0.1 s; what came after was the interpreter tearing itself down,
freeing a heap of a few hundred MB object by object (numpy, numba, the scene), 1 to 3 s
after SIGTERM on a loaded 2-core machine (benchmarks/bench_stop.py; freezing the heap out of
the last collection had taken off only part of it). A process whose work is done and flushed
need not do that: `mocapd start` arms this once its figures are written, and the entry point
ends the process with `os._exit` after flushing the log and the standard streams. Only the
entry point does (daemon.cli.main), so an in-process run (the tests) returns normally.
"""

from __future__ import annotations

import logging
import os
import sys

_armed = False


def arm() -> None:
    """Everything is written and closed: the process may end without tearing down."""
    global _armed
    _armed = True


def end_now_if_armed(code) -> None:
    """At the entry point's exit (`code` as SystemExit carries it): when armed, flush the
    log and the standard streams and end the process now; otherwise return."""
    if not _armed:
        return
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more can be said there
            pass
    os._exit(code if isinstance(code, int) else (0 if code is None else 1))
