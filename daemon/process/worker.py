"""A thread that runs until told to stop: the shape of every capture thread."""

from __future__ import annotations

import threading


class Worker:
    """Runs `self._run` on a daemon thread; `_run` returns once `self._stop` is set."""

    def __init__(self, name: str) -> None:
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name=name, daemon=True)

    def _run(self) -> None:
        raise NotImplementedError

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout: float = 1.0) -> None:
        self.thread.join(timeout)
