"""Recording outputs that never lose what they have written: one file, opened once.

Why not the other outputs' retry: a pose stream that fails is reopened a second later and
nothing is lost but the frames in between. A recording reopened the same way is truncated:
after a full disk the old recorder reopened its file with mode "w" every 5 s, and a late
flush of the first handle then filled the start of the new file with NUL bytes, so a take
of 2928 frames read back 298. Here the first failure (ENOSPC, an I/O error, the free-space
floor) ends the recording: the file keeps every frame written before it (each record is a
flushed line or an MCAP chunk), later frames are counted as lost, and the error stays in
`mocapd status` until `mocapd record --stop`.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from daemon.publish.base import Publisher

log = logging.getLogger("mocapd.publish")

SPACE_CHECK_S = 0.5  # how often the free space is looked at while recording


def free_mb(folder: Path) -> float:
    """Free space an ordinary process may use in `folder`'s file system, in MB."""
    st = os.statvfs(folder)
    return st.f_bavail * st.f_frsize / 1e6


class RecordingOutput(Publisher):
    """Base of the recorders: a deep queue (a recording should be whole), open once, stop
    for good at the first failure or when free space falls below `min_free_mb`."""

    def __init__(self, path, min_free_mb: float = 0.0) -> None:
        super().__init__(queue_size=4096, retry_s=5.0)
        self.path = Path(path)
        self.name = f"record:{path}"
        self.min_free_mb = float(min_free_mb)
        self.failed = ""  # why the recording stopped early ("" while it goes on)
        self.lost = 0  # frames handed over after it stopped
        self.handed = 0  # frames the frame loop handed over (written, lost or left queued)
        self._space_due = 0.0

    def submit(self, result) -> None:
        self.handed += 1
        super().submit(result)

    def stop(self, timeout: float = 2.0) -> None:
        """Write what is queued, close, and say in one line whether every frame handed over
        is in the file (what a stop by SIGTERM must leave: benchmarks/bench_stop.py reads
        this line)."""
        super().stop(timeout)
        missing = self.handed - self.sent
        log.info("%s: recording closed, %d of %d frames written%s", self.name, self.sent,
                 self.handed, "" if not missing else
                 f" ({self.lost} after it stopped, {missing - self.lost} not written)")

    def _deliver(self, result) -> None:
        if self.failed:
            self.lost += 1
            return
        try:
            if not self.connected:
                self.open()
                self.connected = True
                log.info("%s: open", self.name)
            self._check_space()
            self.send(result)
        except Exception as exc:  # noqa: BLE001 - any failure ends the recording
            self._stop_for_good(str(exc) if isinstance(exc, OSError)
                                else f"{type(exc).__name__}: {exc}")
            self.lost += 1
            return
        self.sent += 1
        self.send_ns.append((result.arrival_ns, time.monotonic_ns()))

    def _check_space(self) -> None:
        now = time.monotonic()
        if self.min_free_mb <= 0 or now < self._space_due:
            return
        self._space_due = now + SPACE_CHECK_S
        left = free_mb(self.path.parent)
        if left < self.min_free_mb:
            raise OSError(f"{left:.0f} MB free on the disk, under the floor of "
                          f"{self.min_free_mb:g} MB (record_min_free_mb)")

    def _stop_for_good(self, message: str) -> None:
        self.failed = message
        self.errors += 1
        self.last_error = f"recording stopped: {message}"
        log.error("%s: recording stopped after %d frames, which are kept: %s", self.name,
                  self.sent, message)
        self._safe_close()

    def status(self) -> dict:
        st = super().status()
        st.update(path=str(self.path), failed=self.failed or None, lost=self.lost,
                  handed=self.handed)
        return st
