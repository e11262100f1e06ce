"""The daemon's labelling stage: names the frame's tracked markers with a marker set.

Why a stage of its own: the labeller (daemon.label) works on bare 3D points, one frame at a
time; the pipeline has tracks, bodies and publishers. This module sits between them
(`Pipeline(labeller=...)`): it hands the frame's seen track positions to the labeller and
returns, per labelled marker, its index in the set, position, confidence and the track it
came from, with the set's names for the outputs (UDP packet, NatNet). It runs on the frame
loop, so it does nothing else: no copies beyond the seen rows, no Python loop per marker.

Starting is the exception: labelling a frame from the marker set alone (no previous
labels) searches the set's segments and takes a few hundred milliseconds, which would
stall the stream. So a fresh labeller starts on a thread of its own (`_Search`): it
labels the frame it was given, then catches up on every frame that came since (each a
normal, sub-millisecond update) and is handed to the frame loop once it is current;
until then frames go out without labelled markers. The same happens when the labeller
has named nothing for `lost_s` seconds while markers are seen (the subject left and came
back), and after a labeller failure (a bug, not a user error: logged once, never a
stopped stream). A run that is not paced by cameras (a simulation or replay as fast as
possible, `background=False`) starts inline instead: nothing is missed and the labels are
the same on every run.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibkit.errors import UserError
from daemon.label import Labeller
from daemon.markerset import MarkerSet

log = logging.getLogger("mocapd.label")

SHIPPED = Path(__file__).resolve().parent / "markersets"  # cmu41.toml, sim_person.toml, ...


@dataclass(eq=False)
class LabelledMarkers:
    """One frame's named markers (rows are labelled markers, in the order found)."""

    set_name: str
    names: list[str]            # the set's marker names: names[index] names a row
    index: np.ndarray           # (k,) marker index in the set
    xyz: np.ndarray             # (k, 3) metres, world frame
    confidence: np.ndarray      # (k,) 0..1, the labeller's confidence in the name
    track: np.ndarray           # (k,) the tracker's id of the track the marker is


def shipped_sets() -> list[str]:
    """Names of the marker sets that ship with mocapd (`markerset = "cmu41"`)."""
    return sorted(p.stem for p in SHIPPED.glob("*.toml"))


def resolve(value: str, base: Path) -> Path:
    """A `markerset` value to a file: a shipped set's name, else a path relative to the
    configuration's folder."""
    if "/" not in value and not value.endswith(".toml") and (SHIPPED / f"{value}.toml").exists():
        return SHIPPED / f"{value}.toml"
    return base / value


def load(path: Path) -> MarkerSet:
    """The marker set at `path`; UserError (one line) if it is missing or malformed."""
    if path.is_dir():
        raise UserError(f"marker set {path} is a folder, not a TOML file")
    ms = MarkerSet.load(path)
    if ms.n < 3:
        raise UserError(f"marker set {path} has {ms.n} markers; labelling needs at least 3")
    return ms


class _Search:
    """A fresh labeller started on a thread: the first frame from the marker set alone,
    then every frame queued since, until it is current (see the module docstring)."""

    def __init__(self, ms: MarkerSet, rate_hz: float, first: np.ndarray,
                 max_behind: int) -> None:
        self.labeller = Labeller(ms, rate_hz=rate_hz)
        self.queue: deque = deque([first])
        self.max_behind = max_behind
        self.cond = threading.Condition()
        self.ready = False  # caught up: the frame loop may take the labeller
        self.cancelled = False
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, name="label-start", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while True:
            with self.cond:
                if self.cancelled:
                    return
                if not self.queue:
                    self.ready = True
                    return
                xyz = self.queue.popleft()
            try:
                self.labeller.update(xyz)
            except Exception as exc:  # noqa: BLE001 - reported by the stage
                self.error = exc
                return

    def offer(self, xyz: np.ndarray) -> Labeller | None:
        """Hand the search this frame; the caught-up labeller when it is ready (the
        frame is then left for the caller to label), else None (the frame is queued)."""
        with self.cond:
            if self.ready:
                return self.labeller
            if len(self.queue) >= self.max_behind:  # too far behind: start again
                self.cancelled = True
            else:
                self.queue.append(xyz)
            return None


class LiveLabeller:
    """The pipeline's labelling stage: `stage(result) -> LabelledMarkers`."""

    def __init__(self, markerset: MarkerSet, rate_hz: float, source: str = "",
                 lost_s: float = 0.5, background: bool = True) -> None:
        self.ms = markerset
        self.rate_hz = float(rate_hz)
        self.source = source  # the file it came from, for status
        self.names = list(markerset.labels)
        self.set_name = markerset.name
        self.labeller: Labeller | None = None  # None while a search runs (or before one)
        self.search: _Search | None = None
        self.background = background
        self.lost_frames = max(1, int(round(lost_s * self.rate_hz)))
        self.max_behind = max(16, int(5 * self.rate_hz))  # frames a search may queue
        self.time_ns: deque = deque(maxlen=4096)  # what the stage took, recent frames
        self.frames = 0
        self.labelled = 0  # markers labelled in the latest frame
        self.unlabelled_run = 0  # frames in a row with points seen and none labelled
        self.failures = 0
        self.starts = 0  # searches started (from the marker set alone)
        self._empty = LabelledMarkers(self.set_name, self.names, np.zeros(0, np.int64),
                                      np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))

    def __call__(self, result) -> LabelledMarkers:
        t0 = time.monotonic_ns()
        tr = result.tracks
        seen = np.asarray(tr.seen, bool)
        xyz = np.asarray(tr.xyz)[seen]
        self.frames += 1
        out = self._label(xyz, np.asarray(tr.ids)[seen])
        self.labelled = len(out.index)
        self.time_ns.append(time.monotonic_ns() - t0)
        return out

    def _label(self, xyz: np.ndarray, ids: np.ndarray) -> LabelledMarkers:
        if self.labeller is None and not self.background and len(xyz) >= 3:
            self.starts += 1
            self.labeller = Labeller(self.ms, rate_hz=self.rate_hz)
        if self.labeller is None:
            if self.search is not None:
                self.labeller = self.search.offer(xyz)
                if self.search.error is not None:
                    self._failed(self.search.error)
                elif self.search.cancelled:
                    self.search = None
            if self.labeller is None:
                if self.search is None and len(xyz) >= 3:
                    self.starts += 1
                    self.search = _Search(self.ms, self.rate_hz, xyz, self.max_behind)
                return self._empty
            self.search = None
        try:
            labels, conf = self.labeller.update(xyz)
        except Exception as exc:  # noqa: BLE001 - a labelling bug must not stop the stream
            self._failed(exc)
            return self._empty
        keep = labels >= 0
        if keep.any() or len(xyz) < 3:
            self.unlabelled_run = 0
        else:
            self.unlabelled_run += 1
            if self.unlabelled_run >= self.lost_frames:  # lost the subject: search again
                self.labeller, self.unlabelled_run = None, 0
        return LabelledMarkers(self.set_name, self.names, labels[keep].astype(np.int64),
                               xyz[keep], conf[keep], ids[keep])

    def _failed(self, exc: BaseException) -> None:
        self.failures += 1
        if self.failures == 1:
            log.error("labelling failed (%s: %s); starting afresh from the marker set",
                      type(exc).__name__, exc, exc_info=exc)
        self.labeller, self.search = None, None

    def close(self) -> None:
        """Stop a search in progress (the daemon stops, or a reload replaced this stage)."""
        search = self.search
        if search is not None:
            with search.cond:
                search.cancelled = True

    def status(self) -> dict:
        t = np.array(list(self.time_ns), np.float64) * 1e-6  # list(): one atomic copy
        return {"markerset": self.set_name, "path": self.source, "markers": self.names,
                "labelled": self.labelled, "frames": self.frames, "failures": self.failures,
                "starts": self.starts, "searching": self.labeller is None,
                "time_ms_median": float(np.median(t)) if len(t) else None,
                "time_ms_p99": float(np.percentile(t, 99)) if len(t) else None}


def sim_person_set() -> MarkerSet:
    """The marker set of the simulator's person (calibkit.sim_person), learned from a
    range-of-motion take and a walk of it: what daemon/markersets/sim_person.toml holds
    (`python -c "from daemon.live_label import sim_person_set as s;
    s().save('daemon/markersets/sim_person.toml')"` writes it again)."""
    from calibkit import sim_person
    from daemon.c3dio import Take
    from daemon.markerset import learn

    rom = sim_person.range_of_motion(2400, 120.0, noise_m=0.0003, seed=3)
    walk = sim_person.walk_circle(1200, 120.0, noise_m=0.0003, seed=4)
    return learn([Take(rom.labels, rom.markers_m, 120.0), Take(walk.labels, walk.markers_m,
                                                                 120.0)], name="sim_person")
