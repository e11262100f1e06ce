"""Each camera's clock against the daemon's: offset and drift learned online from arrivals.

A camera that stamps its frames (a timestamp, or at least a frame counter) stamps them on a
clock of its own: its own epoch (often its power-up, and a new one when it reopens) and
its own crystal, tens of ppm fast or slow against the computer's. What the daemon knows is
when each frame arrived: the capture instant plus a transfer delay that is never negative
and most often close to its smallest value. So `arrival - device time`, followed over
time, has a lower envelope that is a straight line: its height is the offset between the
clocks (plus that smallest delay, which no clock can reveal: a constant per camera, a
fraction of a millisecond on USB3 or GigE), its slope the drift.

CameraClock follows that envelope: the lowest point of each half second of arrivals, a
straight line fitted through the last twenty seconds of those points (then fitted again
through the lower half of them: a half second in which the computer was busy throughout
has a raised lowest point), and, until three half seconds have passed, the lowest point
so far with no drift. Late frames (the computer was busy, for however long) never move
it.

A frame that arrives earlier than the envelope allows (the envelope was raised by a
busy spell, or the camera's time jumped forward) lowers it to that frame at once, the
drift kept. A device time that does not increase (the camera reset its counter or its
timestamp) starts the clock afresh; the capture thread also resets it whenever it reopens
a camera. A clock that has just started is not trusted (`settled`) until frames arriving
on the envelope (within a fifth of a frame period, at most 1 ms, of it) have spanned a
tenth of a second with no frame lowering it by more than that since: its first frames
alone set its offset, and they may all have come late. A computer busy for longer than
that tenth of a second as a camera opens hands its frames over together when it is free
again; each of them lowers the envelope by a frame period, so such a burst never
settles a clock, and the frames that follow it, on time, do.
"""

from __future__ import annotations

import math
from collections import deque

BLOCK_NS = 500_000_000  # one envelope point per half second of arrivals
BLOCKS = 40  # the drift is fitted over the last 40 points (20 s)
MIN_FIT = 3  # points needed before the drift is fitted
MAX_DRIFT = 0.05  # a slope beyond 5 % is no crystal: a frame-id clock at a wrong fps
SETTLE_NS = 100_000_000  # a restarted clock is trusted after this much of its frames
SETTLE_FRAMES = 5  # and at least this many, each arriving on the envelope


def _line(points) -> tuple[float, float]:
    """Least-squares (intercept, slope) through (x, y) points. Plain Python: at most
    BLOCKS points, on the capture threads' path, where numpy's per-call cost on such small
    arrays (a few hundred microseconds in all) would show in the latency."""
    n = len(points)
    xm = sum(p[0] for p in points) / n
    ym = sum(p[1] for p in points) / n
    var = sum((p[0] - xm) ** 2 for p in points)
    s = sum((p[0] - xm) * (p[1] - ym) for p in points) / var if var > 0 else 0.0
    return ym - s * xm, s


class CameraClock:
    """Maps one camera's device times (ns on its own clock) to the daemon's clock."""

    def __init__(self, period_ns: float, block_ns: int = BLOCK_NS, blocks: int = BLOCKS):
        self.period_ns = float(period_ns)
        self.block_ns = block_ns
        self.blocks = blocks
        # how far below the envelope a frame may arrive before the envelope is lowered to
        # it (its own scatter is microseconds)
        self.ahead_ns = min(1e6, 0.1 * self.period_ns)
        # a frame this close above the envelope arrived on time: evidence for settling
        self.on_time_ns = min(1e6, 0.2 * self.period_ns)
        self.lowered = 0  # times the fitted envelope was lowered to an early frame
        self.kind = "arrival"  # what the camera gives: "device time", "frame id" or none
        self.resets = 0
        self.samples = 0
        self.reset(count=False)

    def reset(self, count: bool = True) -> None:
        """Forget the clock (the camera reopened: a new epoch, a new counter)."""
        self._x0: int | None = None  # device time and arrival of the first frame since
        self._y0 = 0
        self._points: deque = deque(maxlen=self.blocks)  # (dx, r): each block's lowest
        self._block_end = 0.0
        self._block_min = math.inf
        self._block_dx = 0.0
        self._a = 0.0  # the envelope r = a + s * dx, r = arrival - device time (relative)
        self._s = 0.0
        self._last_dx = -1.0
        self._n = 0  # frames since the reset
        self._on_time = 0  # frames on the envelope since it was last lowered much
        self._on_time_dx = 0.0  # the first of them
        self.settled = False  # seen enough frames since it (re)started to be trusted
        if count and self.samples:
            self.resets += 1

    def capture_ns(self, device_ns: int, arrival_ns: int) -> int:
        """The daemon-clock capture time of a frame stamped `device_ns` that arrived at
        `arrival_ns` (both ns); learns from it. (On every sample's path: kept lean.)"""
        if self._x0 is None:
            self._x0, self._y0 = int(device_ns), int(arrival_ns)
            self._block_end = float(self.block_ns)
            self._a = 0.0
        dx = float(device_ns - self._x0)
        if dx <= self._last_dx:
            return self._restart(device_ns, arrival_ns)
        dy = float(arrival_ns - self._y0)
        r = dy - dx
        a, s = self._a, self._s
        fitted = len(self._points) >= MIN_FIT
        below = r - a - s * dx
        if below < -self.ahead_ns and fitted:
            a = self._a = a + below  # the envelope, points and all, down to this frame
            self._points = deque(((x, y + below) for x, y in self._points), maxlen=self.blocks)
            self.lowered += 1
        elif not fitted and r < a:
            a = self._a = r  # no drift yet: the lowest point so far
        self.samples += 1
        self._n += 1
        if not self.settled:
            if below < -self.on_time_ns or self._on_time == 0:
                self._on_time, self._on_time_dx = 0, dx  # what came before was late
            if below <= self.on_time_ns:
                self._on_time += 1
            self.settled = (self._on_time >= SETTLE_FRAMES
                            and dx - self._on_time_dx >= SETTLE_NS)
        if dy >= self._block_end:
            self._close_block(dy)
            a, s = self._a, self._s
        if r < self._block_min:
            self._block_min, self._block_dx = r, dx
        self._last_dx = dx
        return self._y0 + round(dx + a + s * dx)

    def _restart(self, device_ns: int, arrival_ns: int) -> int:
        self.reset()
        return self.capture_ns(device_ns, arrival_ns)

    def _close_block(self, dy: float) -> None:
        if math.isfinite(self._block_min):
            self._points.append((self._block_dx, self._block_min))
        self._block_min = math.inf
        self._block_end = dy + self.block_ns
        pts = self._points
        if len(pts) >= MIN_FIT:
            a, s = _line(pts)
            resid = [y - (a + s * x) for x, y in pts]
            cut = sorted(resid)[(len(resid) - 1) // 2]
            low = [p for p, e in zip(pts, resid, strict=True) if e <= cut]
            if len(low) >= MIN_FIT:
                a, s = _line(low)
            self._s = min(max(s, -MAX_DRIFT), MAX_DRIFT)
            self._a = a + (s - self._s) * sum(p[0] for p in pts) / len(pts)

    # ---- figures -------------------------------------------------------------------------

    @property
    def drift_ppm(self) -> float | None:
        """How fast the camera's clock runs against the daemon's, in ppm (positive: it
        gains; None until fitted). The envelope's slope is the daemon's time per unit of
        device time, less one: its negative, to first order."""
        return -self._s * 1e6 if len(self._points) >= MIN_FIT else None

    @property
    def offset_ns(self) -> int | None:
        """Daemon time minus device time at the latest frame (None before any frame)."""
        if self._x0 is None:
            return None
        return self._y0 - self._x0 + round(self._a + self._s * self._last_dx)

    def status(self) -> dict:
        off = self.offset_ns
        drift = self.drift_ppm
        return {"source": self.kind,
                "offset_ms": None if off is None or self.kind == "arrival" else off * 1e-6,
                "drift_ppm": None if drift is None or self.kind == "arrival" else drift,
                "resets": self.resets}
