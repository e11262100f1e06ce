"""Bad input from the network counted by kind and logged at most once per kind a minute.

Why: every parser of a network input (NatNet commands, MAVLink, Zenoh messages, the view's
requests) meets junk sooner or later: a port scanner, a client of another version, a
fuzzer. A log line per bad datagram turns such a flood into a flood of the journal, which
hides what matters and costs the frame loop its time. So each parser counts what it
refuses by kind (shown in the status) and says so once per kind and interval, with how
many it refused since it last said so.
"""

from __future__ import annotations

import logging
import threading
import time

INTERVAL_S = 60.0


class BadInput:
    """Counts of refused inputs by kind, and the rate-limited log line saying so."""

    def __init__(self, logger: logging.Logger, what: str, interval_s: float = INTERVAL_S,
                 level: int = logging.WARNING) -> None:
        self.log, self.what, self.interval_s, self.level = logger, what, interval_s, level
        self.counts: dict[str, int] = {}
        self._said: dict[str, tuple[float, int]] = {}  # kind -> (when logged, count then)
        self._lock = threading.Lock()

    def __call__(self, kind: str, detail: object = "") -> None:
        """One input of `kind` refused; `detail` (the first of its kind, say) is logged."""
        now = time.monotonic()
        with self._lock:
            n = self.counts[kind] = self.counts.get(kind, 0) + 1
            when, before = self._said.get(kind, (-1e18, 0))
            if now - when < self.interval_s:
                return
            self._said[kind] = (now, n)
        more = f" ({n - before} of this kind since the last line)" if n - before > 1 else ""
        # one line, and short: the detail may be the attacker's own bytes
        said = " ".join(str(detail).split())[:160]
        self.log.log(self.level, "%s: ignoring %s%s%s", self.what, kind,
                     f": {said}" if said else "", more)

    @property
    def total(self) -> int:
        return sum(self.counts.values())
