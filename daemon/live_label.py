"""The daemon's labelling stage: names the frame's tracked markers with a marker set.

Why a stage of its own: the labeller (daemon.markers.label) works on bare 3D points, one frame at a
time; the pipeline has tracks, bodies and publishers. This module sits between them
(`Pipeline(labeller=...)`): it hands the frame's seen track positions to the labeller and
returns, per labelled marker, its index in the set, position, confidence and the track it
came from, with the set's names for the outputs (UDP packet, NatNet). It runs on the frame
loop, so it does nothing else: no copies beyond the seen rows, no Python loop per marker.
Markers a rigid body holds are left out: they are named already (the body's), and to the
labeller they would only be more points that fit no marker (ghosts), which make its start
from the set alone go wrong far more often.

Starting is the exception: labelling a frame from the marker set alone (no previous
labels) searches the set's segments and takes a few hundred milliseconds, which would
stall the stream. So when the daemon is paced by cameras the start runs on a thread of
its own (`_Search`) and frames go out without labelled markers until it is done; a run as
fast as possible (`background=False`: a simulation or replay) starts on the frame loop
instead, so the labels are the same on every run. A start (`_Start`) keeps its result by
track id, which the tracker keeps through the frames a search takes: it is accepted when
a second search a quarter second later names the tracks both named alike (a start from
the set alone can mistake a mirrored pair, and tracking would carry the mistake along),
and the accepted labels start the labeller on the current frame's tracks, so nothing is
replayed and a busy machine only delays the start. Searches wait for a frame showing
most of the set (`start_fraction` of its markers, or any after `settle_s`). A start is
made again when the labeller has named nothing for `lost_s` while markers are seen (the
subject left and came back), and after a labeller failure (a bug, not a user error:
logged once, never a stopped stream).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from daemon.markers.label import Labeller
from daemon.markers.markerset import MarkerSet, open_set, shipped_sets
from daemon.markers.markerset import resolve as _resolve

log = logging.getLogger("mocapd.label")

__all__ = ["LiveLabeller", "LabelledMarkers", "load", "resolve", "shipped_sets"]


@dataclass(eq=False)
class LabelledMarkers:
    """One frame's named markers (rows are labelled markers, in the order found)."""

    set_name: str
    names: list[str]            # the set's marker names: names[index] names a row
    index: np.ndarray           # (k,) marker index in the set
    xyz: np.ndarray             # (k, 3) metres, world frame
    confidence: np.ndarray      # (k,) 0..1, the labeller's confidence in the name
    track: np.ndarray           # (k,) the tracker's id of the track the marker is


def resolve(value: str, base: Path) -> Path:
    """A `markerset` value to a file: a shipped set's name, else a path relative to the
    configuration's folder."""
    return _resolve(value, base)


def load(path: Path) -> MarkerSet:
    """The marker set at `path`; UserError (one line) if it is missing or malformed."""
    return open_set(path)


class _Start:
    """Starting from the marker set alone, by track: searches that must agree.

    A search labels one frame's points from the set alone (a few hundred milliseconds);
    its result is kept by track id, since the tracker keeps a marker's track through the
    frames the search took. A start from the set alone can mistake a near-symmetric
    group (a wrist's two markers, a foot's four mirrored), so it is accepted only when
    the next search, `check_frames` later, names every track both named alike (at least
    half the set); at a disagreement the newer search is checked in its turn (after
    `max_tries` searches the newest is taken). Searches are made on frames showing most
    of the set (`start_points`), or on any frame with points after `settle_frames`.
    Nothing is replayed: the accepted labels start a labeller on the current frame's
    tracks, so a start costs two searches however busy the machine is."""

    def __init__(self, ms: MarkerSet, rate_hz: float, check_frames: int, start_points: int,
                 settle_frames: int, max_tries: int = 6) -> None:
        self.ms, self.rate_hz = ms, rate_hz
        self.check_frames, self.start_points = check_frames, start_points
        self.settle_frames, self.max_tries = settle_frames, max_tries
        self.last = None  # frame number of the latest search
        self.waited_from = None  # first frame offered since the latest search
        self.ids = self.labels = None  # the candidate: labelled track ids and their labels
        self.tries = 0
        self.accepted = False

    def want(self, frame: int, n_points: int) -> bool:
        """Whether to search this frame (it is due and shows enough of the set)."""
        if self.accepted or n_points < 3:
            return False
        if self.last is not None and frame - self.last < self.check_frames:
            return False
        if self.waited_from is None:
            self.waited_from = frame
        return n_points >= self.start_points or frame - self.waited_from >= self.settle_frames

    def search(self, frame: int, xyz: np.ndarray, ids: np.ndarray) -> None:
        """Label one frame from the set alone; check it against the candidate."""
        labels = Labeller(self.ms, rate_hz=self.rate_hz).update(xyz)[0]
        got = labels >= 0
        ids, labels = ids[got], labels[got]
        self.last, self.waited_from = frame, None
        self.tries += 1
        if self.ids is not None:
            common, a, b = np.intersect1d(self.ids, ids, return_indices=True)
            if (len(common) >= max(3, self.ms.n // 2)
                    and np.array_equal(self.labels[a], labels[b])):
                self.accepted = True
            else:
                log.info("labelling: two starts from the marker set disagree on %d of %d "
                         "tracks; checking again", int(np.sum(self.labels[a] != labels[b])),
                         len(common))
        self.ids, self.labels = ids, labels
        self.accepted |= self.tries >= self.max_tries

    def labeller(self, xyz: np.ndarray, ids: np.ndarray) -> Labeller:
        """A labeller started from the accepted labels at this frame's tracks."""
        labelled = np.full((self.ms.n, 3), np.nan)
        _, a, b = np.intersect1d(ids, self.ids, return_indices=True)
        labelled[self.labels[b]] = xyz[a]
        lab = Labeller(self.ms, rate_hz=self.rate_hz)
        lab.start_from_labelled(labelled)
        return lab


class _Search:
    """A _Start run on a thread: it searches the newest frame offered whenever one is
    due, until the start is accepted."""

    def __init__(self, start: _Start) -> None:
        self.start = start
        self.cond = threading.Condition()
        self.latest = None  # (frame, xyz, ids) the newest frame offered
        self.cancelled = False
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, name="label-start", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while True:
            with self.cond:
                while self.latest is None and not self.cancelled:
                    self.cond.wait(0.5)
                if self.cancelled:
                    return
                frame, xyz, ids = self.latest
                self.latest = None
            try:
                if self.start.want(frame, len(xyz)):
                    self.start.search(frame, xyz, ids)
            except Exception as exc:  # noqa: BLE001 - reported by the stage
                self.error = exc
                return
            if self.start.accepted:
                return

    def offer(self, frame: int, xyz: np.ndarray, ids: np.ndarray) -> bool:
        """Hand the search this frame; True once the start is accepted."""
        if self.start.accepted:
            return True
        with self.cond:
            self.latest = (frame, xyz, ids)
            self.cond.notify()
        return False


class LiveLabeller:
    """The pipeline's labelling stage: `stage(result) -> LabelledMarkers`."""

    def __init__(self, markerset: MarkerSet, rate_hz: float, source: str = "",
                 lost_s: float = 0.5, background: bool = True, start_fraction: float = 0.9,
                 settle_s: float = 2.0, check_s: float = 0.25) -> None:
        self.ms = markerset
        self.rate_hz = float(rate_hz)
        self.source = source  # the file it came from, for status
        self.names = list(markerset.labels)
        self.set_name = markerset.name
        self.labeller: Labeller | None = None  # None while starting (or before)
        self.start: _Start | None = None  # the start in progress
        self.search: _Search | None = None  # its thread (realtime)
        self.check_frames = max(1, int(round(check_s * self.rate_hz)))
        self.background = background
        self.start_points = max(3, int(np.ceil(start_fraction * markerset.n)))
        self.settle_frames = max(1, int(round(settle_s * self.rate_hz)))
        self.hold_until = 0  # after a failure: no new start before this frame
        self.lost_frames = max(1, int(round(lost_s * self.rate_hz)))
        self.time_ns: deque = deque(maxlen=4096)  # what the stage took, recent frames
        self.frames = 0
        self.labelled = 0  # markers labelled in the latest frame
        self.unlabelled_run = 0  # frames in a row with points seen and none labelled
        self.failures = 0
        self.starts = 0  # starts from the marker set alone
        self._last_t_ns = None  # capture time of the previous frame
        self._empty = LabelledMarkers(self.set_name, self.names, np.zeros(0, np.int64),
                                      np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))

    def __call__(self, result) -> LabelledMarkers:
        t0 = time.monotonic_ns()
        tr = result.tracks
        seen = np.asarray(tr.seen, bool)
        ids = np.asarray(tr.ids)
        held = getattr(getattr(result, "poses", None), "tracks", None)
        if held is not None and np.size(held):
            held = np.asarray(held)
            seen = seen & ~np.isin(ids, held[held >= 0])
        xyz = np.asarray(tr.xyz)[seen]
        self.frames += 1
        # frames the loop skipped to stay live: the labeller predicts motion over them
        t_ns = getattr(result, "t_ns", None)
        steps = 1
        if t_ns is not None and self._last_t_ns is not None and t_ns > self._last_t_ns:
            steps = max(1, int(round((t_ns - self._last_t_ns) * 1e-9 * self.rate_hz)))
        self._last_t_ns = t_ns
        out = self._label(xyz, ids[seen], steps)
        self.labelled = len(out.index)
        self.time_ns.append(time.monotonic_ns() - t0)
        return out

    def _label(self, xyz: np.ndarray, ids: np.ndarray, steps: int = 1) -> LabelledMarkers:
        if self.labeller is None and not self._started(xyz, ids):
            return self._empty
        try:
            labels, conf = self.labeller.update(xyz, steps)
        except Exception as exc:  # noqa: BLE001 - a labelling bug must not stop the stream
            self._failed(exc)
            return self._empty
        keep = labels >= 0
        if keep.any() or len(xyz) < 3:
            self.unlabelled_run = 0
        else:
            self.unlabelled_run += 1
            if self.unlabelled_run >= self.lost_frames:  # lost the subject: start again
                self.labeller, self.unlabelled_run = None, 0
        return LabelledMarkers(self.set_name, self.names, labels[keep].astype(np.int64),
                               xyz[keep], conf[keep], ids[keep])

    def _started(self, xyz: np.ndarray, ids: np.ndarray) -> bool:
        """Advance the start with this frame; True when the labeller is ready for it."""
        if self.frames < self.hold_until:
            return False
        if self.start is None:
            self.starts += 1
            self.start = _Start(self.ms, self.rate_hz, self.check_frames, self.start_points,
                                self.settle_frames)
        try:
            if self.background:
                if self.search is None:
                    self.search = _Search(self.start)
                if self.search.error is not None:
                    raise self.search.error
                done = self.search.offer(self.frames, xyz, ids)
            else:
                if self.start.want(self.frames, len(xyz)):
                    self.start.search(self.frames, xyz, ids)
                done = self.start.accepted
            if not done:
                return False
            self.labeller = self.start.labeller(xyz, ids)
        except Exception as exc:  # noqa: BLE001 - a labelling bug must not stop the stream
            self._failed(exc)
            return False
        self.start = self.search = None
        return True

    def _failed(self, exc: BaseException) -> None:
        self.failures += 1
        if self.failures == 1:
            log.error("labelling failed (%s: %s); starting afresh from the marker set",
                      type(exc).__name__, exc, exc_info=exc)
        self.close()
        self.labeller, self.start, self.search = None, None, None
        self.hold_until = self.frames + self.settle_frames  # a failing labeller: not every frame

    def close(self) -> None:
        """Stop a start searching on its thread (the daemon stops, or a reload replaced
        this stage)."""
        search = self.search
        if search is not None:
            with search.cond:
                search.cancelled = True
                search.cond.notify()

    def status(self) -> dict:
        t = np.array(list(self.time_ns), np.float64) * 1e-6  # list(): one atomic copy
        return {"markerset": self.set_name, "path": self.source, "markers": self.names,
                "labelled": self.labelled, "frames": self.frames, "failures": self.failures,
                "starts": self.starts, "searching": self.labeller is None,
                "time_ms_median": float(np.median(t)) if len(t) else None,
                "time_ms_p99": float(np.percentile(t, 99)) if len(t) else None}
