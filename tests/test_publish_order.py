"""Publishers keep frames in order, also when inline sends and the worker thread meet."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

from daemon.publish.base import Publisher


class SlowWorkerPublisher(Publisher):
    """Sends inline from the frame loop; the worker thread's sends are slow."""

    inline = True
    name = "slow"

    def __init__(self) -> None:
        super().__init__()
        self.order: list[int] = []
        self.worker_sending = threading.Event()

    def send(self, result) -> None:
        if threading.current_thread() is self._thread:
            self.worker_sending.set()
            time.sleep(0.05)
        self.order.append(result.frame)


def _frame(i: int):
    return SimpleNamespace(frame=i, arrival_ns=time.monotonic_ns())


def test_a_frame_the_worker_holds_is_not_overtaken_by_an_inline_send() -> None:
    pub = SlowWorkerPublisher()
    pub.start()
    try:
        pub.submit(_frame(1))  # not open yet: queued; the worker opens and sends it slowly
        assert pub.worker_sending.wait(2.0)
        for i in range(2, 6):  # the queue is empty now, but frame 1 is still in flight
            pub.submit(_frame(i))
        deadline = time.monotonic() + 3.0
        while len(pub.order) < 5 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        pub.stop()
    assert pub.order == [1, 2, 3, 4, 5]
