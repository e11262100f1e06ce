"""A thread that runs until told to stop: the shape of every capture thread."""

from __future__ import annotations

import threading

from daemon.process.supervise import Supervised


class Worker:
    """Runs `self._run` on a daemon thread; `_run` returns once `self._stop` is set. An
    exception escaping `_run` restarts it (daemon.process.supervise): a camera's thread must not
    end on a bug while the others go on without it."""

    def __init__(self, name: str) -> None:
        self._stop = threading.Event()
        self.sup = Supervised(name, self._run, stopping=self._stop.is_set)
        self.thread = self.sup.thread
        self.supervised = [self.sup]

    def _run(self) -> None:
        raise NotImplementedError

    def start(self) -> None:
        self.sup.start()

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout: float = 1.0) -> None:
        self.sup.join(timeout)
