"""Server threads that outlive their own bugs: a failure is logged, counted, and the loop restarts.

Why one helper: the daemon runs a dozen kinds of long-lived threads (each output's worker,
the NatNet command port, the VRPN server, the MAVLink link, the control socket, the view's
feed, one capture thread per camera). Each already catches what it expects (a closed
socket, a camera unplugged, a malformed request), but an exception nobody expected (a bug,
an odd value from a library) used to end its thread silently: VRPN's clients then got no
cookie while `mocapd status` said connected (issue 30). Here every such thread runs its loop
under `Supervised`: an exception that escapes the loop is logged (with its traceback the
first time, then one line a minute per kind, however often it recurs), counted, and the loop
is entered again after a short wait (so a loop that fails at once does not spin a core);
`mocapd status` shows each thread's state and restart count. A loop that returns has ended
on purpose (stopped, a source that ended) and is not restarted.

Some loops watch something outside the interpreter rather than run it (the live view's
process, the Zenoh session): their `reset` brings it back (a new process, a reopened
session), which can fail again and again while, say, the port is still taken. Those use a
back-off (`max_wait_s`): the wait doubles with each failure in a row, up to the maximum,
and starts again from `wait_s` once the loop has run HEALTHY_S without failing. A failure
they expect (the process exited) is an `expected` exception: logged as one line, without a
traceback, since the traceback would only show the watcher noticing.
"""

from __future__ import annotations

import logging
import threading
import time

log = logging.getLogger("mocapd.supervise")

RESTART_WAIT_S = 0.2  # between a failure and the restart: a loop failing at once must not spin
LOG_EVERY_S = 60.0  # one line per kind of failure and thread this often
HEALTHY_S = 30.0  # a loop that ran this long before failing starts its back-off afresh


def _said(exc: BaseException) -> str:
    """`Type: message`, even for an exception whose own str() fails."""
    try:
        text = str(exc)
    except Exception:  # noqa: BLE001 - a broken __str__ must not end the supervisor too
        text = "<unprintable>"
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


class Supervised:
    """One named daemon thread running `loop()`; restarted when it raises.

    `stopping()` says whether the owner is shutting down (no restart then); `reset()`, if
    given, runs before each restart (reopen a socket, clear a half-done state); a `reset`
    that raises counts as one more failure and is retried after the wait. With `max_wait_s`
    the wait backs off (see the module); `expected` exceptions are logged without traceback."""

    def __init__(self, name: str, loop, stopping=None, reset=None,
                 wait_s: float = RESTART_WAIT_S, logger: logging.Logger | None = None,
                 max_wait_s: float | None = None, expected: tuple = ()) -> None:
        self.name, self.loop, self.reset = name, loop, reset
        self.stopping = stopping or (lambda: False)
        self.wait_s = wait_s
        self.max_wait_s = max_wait_s
        self.expected = tuple(expected)
        self._in_a_row = 0  # failures since the loop last ran HEALTHY_S (the back-off's step)
        self.log = logger or log
        self.restarts = 0
        self.last_error = ""
        self.state = "new"  # new, running, restarting, stopped
        self._said: dict[str, float] = {}  # kind of failure -> when last logged
        self._wake = threading.Event()
        self.thread = threading.Thread(target=self._main, name=name, daemon=True)

    def start(self) -> Supervised:
        self.state = "running"
        self.thread.start()
        return self

    def join(self, timeout: float | None = None) -> None:
        self._wake.set()  # a thread waiting to restart need not wait its time out
        if self.thread.ident is not None:
            self.thread.join(timeout)

    def is_alive(self) -> bool:
        return self.thread.is_alive()

    def status(self) -> dict:
        """name, state ("running", "restarting", "stopped"; "dead" for a thread that ended
        without saying so, which only an exception the supervisor cannot catch does),
        restarts and the last failure."""
        state = self.state
        if state in ("running", "restarting") and self.thread.ident is not None \
                and not self.thread.is_alive():
            state = "dead"
        return {"name": self.name, "state": state, "restarts": self.restarts,
                "last_error": self.last_error or None}

    def _main(self) -> None:
        try:
            while True:
                entered = time.monotonic()
                try:
                    self.loop()
                    return  # ended on purpose
                except Exception as exc:  # noqa: BLE001 - the point: nothing ends the thread
                    if time.monotonic() - entered >= HEALTHY_S:
                        self._in_a_row = 0
                    self._failed(exc)
                if not self._restart():
                    return
        finally:
            if self.state != "dead":
                self.state = "stopped"

    def _restart(self) -> bool:
        """Wait, reset, and say whether to enter the loop again."""
        while True:
            self.state = "restarting"
            self._wake.wait(self.next_wait_s())
            if self.stopping():
                return False
            if self.reset is None:
                break
            try:
                self.reset()
                break
            except Exception as exc:  # noqa: BLE001 - a failed reset is one more failure
                self._failed(exc)
        self.state = "running"
        return True

    def next_wait_s(self) -> float:
        """The wait before the next restart: `wait_s`, or with a back-off `wait_s` doubled
        for each failure in a row but the first, at most `max_wait_s`."""
        if self.max_wait_s is None:
            return self.wait_s
        return min(self.max_wait_s, self.wait_s * 2.0 ** min(max(self._in_a_row - 1, 0), 30))

    def _failed(self, exc: Exception) -> None:
        self.restarts += 1
        self._in_a_row += 1
        self.last_error = _said(exc)
        kind = type(exc).__name__
        now = time.monotonic()
        if now - self._said.get(kind, -1e18) < LOG_EVERY_S:
            return
        first = kind not in self._said
        self._said[kind] = now
        if self.stopping():
            return  # a loop failing because its socket closed under a stop: not news
        if first:
            self.log.error("%s: thread failed (%s), restarting it", self.name,
                           self.last_error,
                           exc_info=None if isinstance(exc, self.expected) else exc)
        else:
            self.log.error("%s: thread failed again (%s; %d restarts so far), restarting it",
                           self.name, self.last_error, self.restarts)


def threads_status(*owners) -> list[dict]:
    """The status of every supervised thread of `owners` (objects with a `supervised`
    attribute: a list of Supervised, or None entries for threads not started)."""
    return [s.status() for o in owners if o is not None
            for s in (getattr(o, "supervised", None) or ()) if s is not None]
