"""Each node's clock against the daemon's: offset and drift from round-trip exchanges.

The daemon sends a ping stamped t1 (its clock); the node stamps its arrival t2 and its
reply t3 (the node's clock); the daemon stamps the reply's arrival t4. If the two legs
took as long as each other, the node's clock was ((t2 - t1) + (t3 - t4)) / 2 ahead of the
daemon's at the daemon's (t1 + t4) / 2, and the round trip took (t4 - t1) - (t3 - t2).
The legs are never quite equal: a queue, a busy interpreter or the link's jitter delays
one and not the other, and the error is at most half the round trip's excess over its
smallest. So, as NTP's clock filter does, only the exchanges of the shortest round trips
are believed: of the last WINDOW exchanges, those whose round trip is within the lower
KEEP fraction; a straight line through their offsets over time gives the drift (the
crystals of two computers differ by tens of ppm) and the offset now. Until the exchanges
span DRIFT_SPAN_NS the line is flat (the median of the believed offsets).

Zenoh stamps messages with its own hybrid logical clock when asked to; those stamps
order events but carry each sender's wall clock, which is neither synchronised here nor
monotonic, so they are not used.
"""

from __future__ import annotations

import threading

import numpy as np

WINDOW = 400  # exchanges remembered (20 s at the daemon's 20 Hz)
KEEP = 0.25  # the fraction of them, shortest round trips first, that the fit believes
READY = 8  # exchanges before a node's times are mapped at all
DRIFT_SPAN_NS = 2_000_000_000  # the drift is fitted once the exchanges span this long
MAX_DRIFT = 1e-3  # 1000 ppm: beyond that no crystal, a clock being stepped


class NodeClock:
    """Maps one node's clock (ns) to the daemon's; fed with round-trip exchanges.

    Thread-safe: exchanges arrive on Zenoh's threads, times are mapped on others; the fit
    is replaced whole (one tuple), so a reader never sees half of one."""

    def __init__(self, window: int = WINDOW, keep: float = KEEP) -> None:
        self.window, self.keep = window, keep
        self._lock = threading.Lock()
        self._mid = np.zeros(window)  # daemon time of each exchange, ns from _base_t
        self._off = np.zeros(window)  # node - daemon, ns from _base_off
        self._rtt = np.zeros(window)
        self._n = 0  # exchanges so far
        self._base_t = 0
        self._base_off = 0
        self.fit: tuple[float, float, int] | None = None  # (offset ns at ref, slope, ref)
        self.last_rtt_ns = 0

    def add(self, t1: int, t2: int, t3: int, t4: int) -> None:
        """One exchange: t1, t4 on the daemon's clock, t2, t3 on the node's (ns)."""
        rtt = (t4 - t1) - (t3 - t2)
        if rtt < 0 or t4 < t1:
            return  # not one exchange (a reply to another ping, a node clock stepped)
        with self._lock:
            if self._n == 0:
                self._base_t = t1
                self._base_off = ((t2 - t1) + (t3 - t4)) // 2
            k = self._n % self.window
            self._mid[k] = (t1 + t4) / 2 - self._base_t
            self._off[k] = ((t2 - t1) + (t3 - t4)) / 2 - self._base_off
            self._rtt[k] = rtt
            self._n += 1
            self.last_rtt_ns = rtt
            self._refit()

    def _refit(self) -> None:
        n = min(self._n, self.window)
        if n < READY:
            return
        mid, off, rtt = self._mid[:n], self._off[:n], self._rtt[:n]
        keep = rtt <= np.quantile(rtt, self.keep)
        x, y = mid[keep], off[keep]
        ref = float(mid.max())
        if np.ptp(x) >= DRIFT_SPAN_NS and len(x) >= 3:
            slope, icpt = np.polyfit(x - ref, y, 1)
            slope = float(np.clip(slope, -MAX_DRIFT, MAX_DRIFT))
            at_ref = float(np.mean(y - slope * (x - ref)))
        else:
            slope, at_ref = 0.0, float(np.median(y))
        self.fit = (at_ref + self._base_off, slope, int(ref + self._base_t))

    @property
    def ready(self) -> bool:
        return self.fit is not None

    def offset_ns(self, daemon_ns: int) -> float:
        """Node clock minus daemon clock at daemon time `daemon_ns`."""
        off, slope, ref = self.fit
        return off + slope * (daemon_ns - ref)

    def to_daemon(self, node_ns: int) -> int:
        """The daemon time of node time `node_ns` (the clock must be ready)."""
        off, slope, ref = self.fit
        # node = daemon + off + slope * (daemon - ref), solved for daemon
        return round(ref + (node_ns - ref - off) / (1.0 + slope))

    def to_daemon_array(self, node_ns: np.ndarray) -> np.ndarray:
        """to_daemon of many times at once (int64 ns): a node's set of frames is mapped in
        one call. Differences from the fit's reference are taken in integers first, so the
        float64 step loses nothing at monotonic-clock magnitudes."""
        off, slope, ref = self.fit
        d = (np.asarray(node_ns, dtype=np.int64) - ref).astype(np.float64)
        return ref + np.rint((d - off) / (1.0 + slope)).astype(np.int64)

    def status(self) -> dict:
        n = min(self._n, self.window)
        rtt = self._rtt[:n]
        fit = self.fit
        return {"exchanges": self._n, "ready": fit is not None,
                "offset_ms": None if fit is None else fit[0] * 1e-6,
                "at_ns": None if fit is None else fit[2],  # the daemon time of offset_ms
                "drift_ppm": None if fit is None else fit[1] * 1e6,
                "rtt_ms": float(np.median(rtt)) * 1e-6 if n else None,
                "rtt_min_ms": float(rtt.min()) * 1e-6 if n else None}
