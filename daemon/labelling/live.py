"""The daemon's labelling stage: names the frame's tracked markers with a marker set.

Why a stage of its own: the labeller (daemon.labelling.labeller) works on bare 3D points,
one frame at a time; the pipeline has tracks, bodies and publishers. This module sits between them
(`Pipeline(labeller=...)`): it hands the frame's seen track positions to the labeller and
returns, per labelled marker, its index in the set, position, confidence and the track it
came from, with the set's names for the outputs (UDP packet, NatNet). It runs on the frame
loop, so it does nothing else: no copies beyond the seen rows, no Python loop per marker.
Markers a rigid body holds are left out: they are named already (the body's), and to the
labeller they would only be more points that fit no marker (ghosts).

It starts and checks itself as `mocapd label` does (daemon/labelling/start.py,
verify.py), from the marker set alone on any subject: the frames of the first
second showing most of the set (`start_fraction` of its markers, or any after
`settle_s`) are labelled all at once (`_Start`: a window of `window_s`), the labels kept
by track id (the tracker keeps a marker's track through the window and the search), and
a labeller starts on the current frame's tracks, having learned this body's distances
from the window. Then every 2nd window of labelled frames is checked against the set
(`_Verify`; offline every 4th, but live the frames sent before a check keep their
names); a window gone wrong (a swap, a side mirrored, a marker's point left unlabelled
while its label sits on a neighbour) renames the labeller's markers from the frame the
check ends on.

Both searches take tens to hundreds of milliseconds, which would stall the stream. So
when the daemon is paced by cameras they run on a thread of their own (`_Worker`) and
frames go out without labelled markers until the start is done; a run as fast as possible
(`background=False`: a simulation or replay) runs them on the frame loop instead, so the
labels are the same on every run. The labeller itself is only touched on the frame loop.
A start is made again when the labeller has named nothing for `lost_s` while markers are
seen (the subject left and came back), and after a labeller failure (a bug, not a user
error: logged once, never a stopped stream).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from daemon.labelling.labeller import Labeller
from daemon.labelling.markerset import MarkerSet, open_set, shipped_sets
from daemon.labelling.markerset import resolve as _resolve
from daemon.labelling.start import window_start
from daemon.labelling.verify import STRIDE, check_window

log = logging.getLogger("mocapd.label")

# live, a window found wrong cannot be relabelled in the frames already sent, so windows
# are checked twice as often as offline (every 2nd second; a check is a few tens of
# milliseconds on the worker, a few hundred when the whole assignment runs)
LIVE_STRIDE = 2

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
    """Starting from the marker set alone on a window of frames.

    Frames are buffered from the first showing most of the set (`start_points`), or
    from any with points after `settle_frames`; once `width` are in, the window is
    labelled all at once (daemon/labelling/start.py) and each track id keeps the
    label its points took most often. Nothing is replayed: the labels start a labeller
    on the current frame's tracks (the search may have taken frames), which learns this
    body's distances from the window."""

    def __init__(self, ms: MarkerSet, rate_hz: float, width: int, start_points: int,
                 settle_frames: int) -> None:
        self.ms, self.rate_hz, self.width = ms, rate_hz, width
        self.start_points, self.settle_frames = start_points, settle_frames
        self.frames: list[tuple[np.ndarray, np.ndarray]] = []
        self.waited = 0
        self.searching = False
        self.ids = self.labels = self.xyz = None     # the result: track ids, labels, window

    def offer(self, xyz: np.ndarray, ids: np.ndarray) -> bool:
        """Buffer this frame; True when the window is full (the search is due)."""
        if not self.frames:
            self.waited += 1
            if len(xyz) < 3 or (len(xyz) < self.start_points
                                and self.waited < self.settle_frames):
                return False
        if len(self.frames) < self.width:
            self.frames.append((xyz, ids))
        return len(self.frames) >= self.width

    def search(self) -> None:
        """Label the window from the set alone; keep the labels by track id."""
        per = [x for x, _ in self.frames]
        _, labels, self.xyz = window_start(per, self.ms, width=len(per))
        ids = np.concatenate([i for _, i in self.frames])
        lab = np.concatenate(labels)
        got = lab >= 0
        pair, count = np.unique(np.stack([ids[got], lab[got]], 1), axis=0,
                                return_counts=True)
        # each track its most frequent label, each label its most frequent track
        order = np.argsort(-count, kind="stable")
        pair = pair[order]
        _, first = np.unique(pair[:, 0], return_index=True)
        pair = pair[np.sort(first)]
        _, first = np.unique(pair[:, 1], return_index=True)
        pair = pair[np.sort(first)]
        self.ids, self.labels = pair[:, 0], pair[:, 1]

    def labeller(self, xyz: np.ndarray, ids: np.ndarray) -> Labeller:
        """A labeller started from the window's labels at this frame's tracks."""
        lab = Labeller(self.ms, rate_hz=self.rate_hz)
        lab.start_from_labelled_frames(self.xyz)
        labelled = np.full((self.ms.n, 3), np.nan)
        _, a, b = np.intersect1d(ids, self.ids, return_indices=True)
        labelled[self.labels[b]] = xyz[a]
        lab.start_from_labelled(labelled)
        return lab


class _Verify:
    """Verification while labelling live: the labelled frames (points, track ids, labels)
    are gathered in windows of `width`; every `stride`-th window, and the next after one
    found wrong, is checked against the set (daemon/labelling/verify.py). What it
    finds renames the labeller's markers (`apply`), and a marker whose point the labeller
    left unlabelled is taken up at its track."""

    def __init__(self, ms: MarkerSet, width: int, stride: int = STRIDE) -> None:
        self.ms, self.width, self.stride = ms, width, stride
        self.frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.windows = 0
        self.wrong = False
        self.checked = self.fixed = 0

    def add(self, xyz: np.ndarray, ids: np.ndarray, labels: np.ndarray) -> list | None:
        """Gather a labelled frame; a window's frames when one is due for a check."""
        self.frames.append((xyz, ids, labels))
        if len(self.frames) < self.width:
            return None
        frames, self.frames = self.frames, []
        self.windows += 1
        due = self.wrong or self.windows % self.stride == 1 or self.stride == 1
        return frames if due else None

    def check(self, frames: list) -> tuple | None:
        """A window's renaming: (perm, markers unlabelled tracks took, their track ids in
        the window's last frame, their motion a frame), or None when it is right."""
        per = [x for x, _, _ in frames]
        labels = {w: (lab, np.ones(len(lab))) for w, (_, _, lab) in enumerate(frames)}
        got = check_window(per, labels, list(range(len(frames))), self.ms, 0.003)
        self.checked += 1
        self.wrong = got is not None
        if got is None:
            return None
        self.fixed += 1
        perm, gained, X, rows = got
        e = np.nonzero((gained >= 0) & (rows[:, -1] >= 0))[0]
        last_ids = frames[-1][1]
        v = np.where(np.isfinite(X[e, -2]).all(1)[:, None], X[e, -1] - X[e, -2], 0.0)
        return perm, gained[e], last_ids[rows[e, -1]], v

    @staticmethod
    def apply(lab: Labeller, found: tuple, xyz: np.ndarray, ids: np.ndarray,
              labels: np.ndarray) -> None:
        """Rename `lab`'s markers after this frame (its points `xyz`, track `ids`, the
        labels it gave them); markers taken up by unlabelled tracks start at the track's
        point, if the track is seen and still unlabelled."""
        perm, markers, tracks, vel = found
        lab.relabel(perm)
        free = np.isin(ids, tracks) & (labels < 0)
        _, a, b = np.intersect1d(ids[free], tracks, return_indices=True)
        if len(a):
            lab.found(markers[b], xyz[free][a], vel[b])


class _Worker:
    """One search at a time on a thread of its own: the window start or a verification.
    The frame loop submits a job and polls for its result; a job due while another runs
    is not queued (the next window brings the next)."""

    def __init__(self) -> None:
        self.busy = False
        self.done: list = []             # (job, result or exception), for the frame loop
        self.lock = threading.Lock()

    def submit(self, job, fn) -> bool:
        """Run fn() on a new thread for `job`; False when one is still running."""
        if self.busy:
            return False
        self.busy = True

        def run() -> None:
            try:
                out = fn()
            except Exception as exc:  # noqa: BLE001 - reported by the stage
                out = exc
            with self.lock:
                self.done.append((job, out))
                self.busy = False

        threading.Thread(target=run, name=f"label-{job}", daemon=True).start()
        return True

    def results(self) -> list:
        with self.lock:
            out, self.done = self.done, []
        return out


class LiveLabeller:
    """The pipeline's labelling stage: `stage(result) -> LabelledMarkers`."""

    def __init__(self, markerset: MarkerSet, rate_hz: float, source: str = "",
                 lost_s: float = 0.5, background: bool = True, start_fraction: float = 0.9,
                 settle_s: float = 2.0, window_s: float = 1.0, verify: bool = True,
                 verify_every: int = LIVE_STRIDE) -> None:
        self.ms = markerset
        self.rate_hz = float(rate_hz)
        self.source = source  # the file it came from, for status
        self.names = list(markerset.labels)
        self.set_name = markerset.name
        self.labeller: Labeller | None = None  # None while starting (or before)
        self.start: _Start | None = None  # the start in progress
        self.verify: _Verify | None = None  # the running labeller's verification
        self.check, self.verify_every = verify, verify_every
        self.worker = _Worker() if background else None
        self.width = max(10, int(round(window_s * self.rate_hz)))
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
        self.generation = 0  # labellers started so far: a late result of an older one is dropped
        self.checked = self.relabelled = 0  # windows verified, and renamed by it
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
            self._verified(xyz, ids, labels)
        except Exception as exc:  # noqa: BLE001 - a labelling bug must not stop the stream
            self._failed(exc)
            return self._empty
        keep = labels >= 0
        if keep.any() or len(xyz) < 3:
            self.unlabelled_run = 0
        else:
            self.unlabelled_run += 1
            if self.unlabelled_run >= self.lost_frames:  # lost the subject: start again
                self.labeller, self.verify, self.unlabelled_run = None, None, 0
        return LabelledMarkers(self.set_name, self.names, labels[keep].astype(np.int64),
                               xyz[keep], conf[keep], ids[keep])

    def _run(self, job: str, fn) -> tuple[bool, list]:
        """Run a search `fn` (None: none due): inline (its result now), or on the worker
        thread. Returns whether it was taken (the worker may still be busy with another)
        and the results that arrived since for this labeller's generation."""
        gen = self.generation
        if self.worker is None:
            return True, ([(job, fn())] if fn is not None else [])
        taken = fn is not None and self.worker.submit((job, gen), fn)
        out = []
        for (name, g), res in self.worker.results():
            if isinstance(res, BaseException):
                raise res
            if g == gen:
                out.append((name, res))
        return taken, out

    def _started(self, xyz: np.ndarray, ids: np.ndarray) -> bool:
        """Advance the start with this frame; True when the labeller is ready for it."""
        if self.frames < self.hold_until:
            return False
        if self.start is None:
            self.starts += 1
            self.generation += 1
            self.start = _Start(self.ms, self.rate_hz, self.width, self.start_points,
                                self.settle_frames)
        try:
            start = self.start
            due = start.offer(xyz, ids) and not start.searching
            taken, results = self._run("start", start.search if due else None)
            start.searching |= due and taken   # else again on the next frame
            done = any(job == "start" for job, _ in results)
            if not done:
                return False
            self.labeller = start.labeller(xyz, ids)
            self.verify = _Verify(self.ms, self.width, self.verify_every) if self.check \
                else None
        except Exception as exc:  # noqa: BLE001 - a labelling bug must not stop the stream
            self._failed(exc)
            return False
        self.start = None
        return True

    def _verified(self, xyz: np.ndarray, ids: np.ndarray, labels: np.ndarray) -> None:
        """Gather this labelled frame for verification; apply a check's renaming."""
        if self.verify is None:
            return
        frames = self.verify.add(xyz, ids, labels)
        fn = None if frames is None else (lambda v=self.verify, f=frames: v.check(f))
        for job, found in self._run("verify", fn)[1]:
            if job == "verify":
                self.checked += 1
                if found is not None:
                    self.relabelled += 1
                    _Verify.apply(self.labeller, found, xyz, ids, labels)

    def _failed(self, exc: BaseException) -> None:
        self.failures += 1
        if self.failures == 1:
            log.error("labelling failed (%s: %s); starting afresh from the marker set",
                      type(exc).__name__, exc, exc_info=exc)
        self.labeller, self.start, self.verify = None, None, None
        self.generation += 1  # what the worker still returns for them is dropped
        self.hold_until = self.frames + self.settle_frames  # a failing labeller: not every frame

    def close(self) -> None:
        """Drop what a search on its thread would still return (the daemon stops, or a
        reload replaced this stage); the thread ends with its search."""
        self.generation += 1

    def status(self) -> dict:
        t = np.array(list(self.time_ns), np.float64) * 1e-6  # list(): one atomic copy
        return {"markerset": self.set_name, "path": self.source, "markers": self.names,
                "labelled": self.labelled, "frames": self.frames, "failures": self.failures,
                "starts": self.starts, "searching": self.labeller is None,
                "windows_verified": self.checked, "windows_relabelled": self.relabelled,
                "time_ms_median": float(np.median(t)) if len(t) else None,
                "time_ms_p99": float(np.percentile(t, 99)) if len(t) else None}
