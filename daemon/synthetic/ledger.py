"""The simulator's ledger: which trigger each delivered frame was, and when it was taken.

Why its own structure: the scorers find a sample's truth by the camera's own frame counter
and timestamp, so the scene must remember the recent deliveries of every camera. Kept in a
Python dict, every entry cost about 290 bytes (two key ints, two value ints, two tuples,
the dict's slot): 76 MB for 8 cameras x 32768 frames, reached 2-3 minutes into a run and
most of the RSS rise issue 30 saw. Here an entry is five int64 (40 bytes) in fixed arrays,
allocated once.

The layout is a small set-associative cache: frame id modulo the number of sets picks a
set of WAYS rows, a new entry replaces the least recently written row of its set, and a
look-up compares frame id and device time in the set's rows. A camera's ids run 0, 1, 2...
in a session, so one session keeps its last `sets x WAYS` frames as a ring would; a camera
that reconnects counts from 0 again, and the ways keep the earlier session's frames with
the same ids beside the new ones (up to WAYS sessions overlapping).

Each camera's rows are written only by its capture thread. A row's frame id is written
last and checked with the device time, so a look-up racing a write sees the old entry, a
mismatch (None), or the new one, never a mix.
"""

from __future__ import annotations

import numpy as np

WAYS = 4


class Ledger:
    """Per camera, the (trigger, taken_ns) of its last `capacity` delivered frames, looked
    up by (frame id, device time)."""

    def __init__(self, cameras: int, capacity: int) -> None:
        self.sets = max(1, capacity // WAYS)
        shape = (cameras, self.sets, WAYS)
        # zeros: pages are touched as they fill; frame ids are stored plus one (0: empty)
        self._key = np.zeros(shape, dtype=np.int64)
        self._device = np.zeros(shape, dtype=np.int64)
        self._trigger = np.zeros(shape, dtype=np.int64)
        self._taken = np.zeros(shape, dtype=np.int64)
        self._written = np.zeros(shape, dtype=np.int64)  # write count when written
        self._count = np.zeros(cameras, dtype=np.int64)

    def add(self, camera: int, frame_id: int, device_ns: int, trigger: int,
            taken_ns: int) -> None:
        s = frame_id % self.sets
        row = self._written[camera, s]
        key = self._key[camera, s]
        same = np.flatnonzero((key == frame_id + 1) & (self._device[camera, s] == device_ns))
        w = int(same[0]) if len(same) else int(np.argmin(row))
        self._count[camera] += 1
        self._key[camera, s, w] = 0  # the row is being rewritten: no look-up matches it
        self._device[camera, s, w] = device_ns
        self._trigger[camera, s, w] = trigger
        self._taken[camera, s, w] = taken_ns
        self._written[camera, s, w] = self._count[camera]
        self._key[camera, s, w] = frame_id + 1

    def get(self, camera: int, frame_id: int, device_ns: int) -> tuple[int, int] | None:
        """(trigger, taken_ns) of that delivery, or None if never held or forgotten."""
        if frame_id is None or device_ns is None or frame_id < 0:
            return None
        s = frame_id % self.sets
        key = self._key[camera, s].tolist()
        device = self._device[camera, s].tolist()
        for w in range(WAYS):
            if key[w] == frame_id + 1 and device[w] == device_ns:
                entry = (int(self._trigger[camera, s, w]), int(self._taken[camera, s, w]))
                # written again meanwhile: the entry read may be the new one's
                if self._key[camera, s, w] == frame_id + 1 \
                        and self._device[camera, s, w] == device_ns:
                    return entry
                return None
        return None
