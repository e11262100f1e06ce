"""The one publisher interface: each output has its own bounded queue and worker thread.

Why a thread and queue per output: tracking must never wait for a consumer. A serial port
unplugged, a pty nobody reads, an unreachable address: the frame loop only appends to a
queue (dropping the oldest frame when it is full, since a pose consumer wants the newest),
and the worker logs the failure and retries opening the output, at most once a second.

A protocol is one file with one subclass that implements `open`, `send(result)` and
`close`; `rate_hz` throttles what it is handed. An output whose send can never block (UDP
on a non-blocking socket) may set `inline`: while it is open and its queue empty, frames
are sent on the frame loop itself, saving a thread hand-off of latency; any failure goes
to the queue and the worker, as for every other output. NatNet, VRPN and friends plug in
the same way.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

from daemon.process.supervise import Supervised, threads_status

log = logging.getLogger("mocapd.publish")


class Publisher:
    """Base class: subclasses set `name` and implement open/send/close."""

    name = "publisher"
    inline = False  # send on the caller's thread while healthy (only for sends that never block)
    # a server that takes over its predecessor's sockets as it starts: a reload starts it at
    # the swap, on the frame loop; every other output is started before, beside the stream
    takes_over = False

    def __init__(self, rate_hz: float = 0.0, queue_size: int = 8, retry_s: float = 1.0) -> None:
        self.rate_hz = float(rate_hz)
        self.retry_s = retry_s
        self._queue: deque = deque(maxlen=max(1, queue_size))
        self._cond = threading.Condition()
        self._stop = False
        self._thread: threading.Thread | None = None
        self._worker: Supervised | None = None
        self._next_due = 0.0
        self._next_open = 0.0  # when a failed output may be opened again
        self._in_flight = False  # the worker holds a frame it has not sent yet
        self.sent = 0
        self.dropped = 0  # frames pushed out of a full queue
        self.errors = 0
        self.last_error = ""
        self.connected = False
        self.send_ns: deque = deque(maxlen=4096)  # (arrival_ns, sent_ns) of recent sends

    # ---- what a protocol implements ----------------------------------------------------

    def open(self) -> None:
        """Open the port or socket; raise OSError (or any error) when it cannot."""

    def send(self, result) -> None:
        """Send one FrameResult (daemon.capture.pipeline) on the open output."""
        raise NotImplementedError

    def close(self) -> None:
        """Release the port or socket; called on errors (before a retry) and at stop."""

    # ---- the machinery -------------------------------------------------------------------

    @property
    def started(self) -> bool:
        return self._worker is not None

    def start(self) -> None:
        self._worker = Supervised(f"pub-{self.name}", self._run, stopping=lambda: self._stop)
        self._thread = self._worker.thread
        self._worker.start()

    @property
    def supervised(self) -> list:
        """The threads `mocapd status` reports (daemon.process.supervise): the worker, and a
        server's own thread where a protocol has one."""
        return [self._worker]

    def submit(self, result) -> None:
        """Hand a frame to the worker; never blocks. Throttled to rate_hz if set."""
        if self.rate_hz > 0:
            now = time.monotonic()
            if now < self._next_due:
                return
            self._next_due = max(self._next_due + 1.0 / self.rate_hz, now - 0.5 / self.rate_hz)
        with self._cond:
            # Inline only when the worker holds nothing: a frame it has popped but not yet
            # sent would otherwise go out after this newer one (frames out of order).
            if self.inline and self.connected and not self._queue and not self._in_flight:
                try:
                    self.send(result)
                    self.sent += 1
                    self.send_ns.append((result.arrival_ns, time.monotonic_ns()))
                    return
                except Exception:  # noqa: BLE001 - the worker logs it and reopens
                    pass
            if len(self._queue) == self._queue.maxlen:
                self.dropped += 1
            self._queue.append(result)
            self._cond.notify()

    def stop(self, timeout: float = 2.0) -> None:
        """Send what is queued (flush), then close."""
        with self._cond:
            self._stop = True
            self._cond.notify()
        if self._worker is not None:
            self._worker.join(timeout)
            if not self._worker.is_alive():  # a worker that failed at the stop closes nothing
                self._safe_close()

    def status(self) -> dict:
        threads = threads_status(self)
        return {"name": self.name, "connected": self.connected, "sent": self.sent,
                "dropped": self.dropped, "errors": self.errors, "last_error": self.last_error,
                "threads": threads, "restarts": sum(t["restarts"] for t in threads)}

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._stop:
                    self._cond.wait(0.5)
                # at stop: flush what is queued, opening the output first if it never was
                # (a recording stopped before its worker ran must still be written); an
                # output that already failed to open is not waited for
                if self._stop and (not self._queue
                                   or (not self.connected and self._next_open > 0)):
                    break
                result = self._queue.popleft() if self._queue else None
                self._in_flight = result is not None
            try:
                if result is not None:
                    self._deliver(result)
            finally:
                self._in_flight = False
        self._safe_close()

    def _deliver(self, result) -> None:
        """Open the output if needed (at most once per retry_s) and send one frame."""
        if not self.connected:
            if time.monotonic() < self._next_open:
                self.dropped += 1
                return
            try:
                self.open()
                self.connected = True
                log.info("%s: open", self.name)
            except Exception as exc:  # noqa: BLE001 - any failure is retried
                self._failed(f"cannot open: {exc}")
                self._next_open = time.monotonic() + self.retry_s
                self.dropped += 1
                return
        try:
            self.send(result)
            self.sent += 1
            self.send_ns.append((result.arrival_ns, time.monotonic_ns()))
        except Exception as exc:  # noqa: BLE001
            self._failed(f"send failed: {exc}")
            self._safe_close()
            self._next_open = time.monotonic() + self.retry_s

    def _failed(self, message: str) -> None:
        self.errors += 1
        if message != self.last_error:
            log.warning("%s: %s (retrying every %g s)", self.name, message, self.retry_s)
        self.last_error = message

    def _safe_close(self) -> None:
        if self.connected:
            try:
                self.close()
            except Exception as exc:  # noqa: BLE001
                log.warning("%s: close failed: %s", self.name, exc)
        self.connected = False
