"""The daemon's labelling stage: names the frame's tracked markers with a marker set.

Why a stage of its own: the labeller (daemon.label) works on bare 3D points, one frame at a
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
stall the stream. So a fresh labeller starts on a thread of its own (`_Search`): it
labels the frame it was given, then catches up on every frame that came since (each a
normal, sub-millisecond update) and is handed to the frame loop once it is current;
until then frames go out without labelled markers. The same happens when the labeller
has named nothing for `lost_s` seconds while markers are seen (the subject left and came
back), and after a labeller failure (a bug, not a user error: logged once, never a
stopped stream). A start waits until most of the set (`start_fraction` of its markers)
has been seen for a quarter second in a row (or points for `settle_s`): labelling from
the set alone is far less reliable on a partial view (the tracker's first frames come and
go, a subject walks in), and a wrong start is carried along by the tracking; for the same
reason a start is checked by two more, a quarter second apart (`_Start`). A run that
is not paced by cameras (a simulation or replay as fast as possible, `background=False`)
starts inline instead: nothing is missed and the labels are the same on every run.
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


class _Start:
    """Starting from the marker set alone, checked by further opinions.

    A start from the set alone can mistake a near-symmetric group (a wrist's two markers,
    a foot's four mirrored) and the tracking then carries the mistake along. So the
    candidate is tracked on, and every `check_frames` another start is made from that
    frame's points alone (a frame showing most of the set, if one comes within
    `settle_frames`): once `confirmations` starts in a row name every marker they and the
    candidate both name alike, the candidate is accepted; at a disagreement the new start
    becomes the candidate and is checked in its turn (after `max_tries` checks the
    candidate is taken as it is). One labeller is tracked at a time, so a start costs one
    update a frame plus one search per check."""

    def __init__(self, ms: MarkerSet, rate_hz: float, check_frames: int, start_points: int,
                 settle_frames: int, confirmations: int = 2, max_tries: int = 8) -> None:
        self.ms, self.rate_hz = ms, rate_hz
        self.confirmations, self.agreed = confirmations, 0
        self.check_frames, self.start_points = check_frames, start_points
        self.settle_frames, self.max_tries = settle_frames, max_tries
        self.candidate: Labeller | None = None
        self.since = 0
        self.tries = 0
        self.accepted: Labeller | None = None

    def step(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """This frame's labels by the candidate; makes the check when it is due."""
        if self.candidate is None:
            self.candidate = Labeller(self.ms, rate_hz=self.rate_hz)
        labels, conf = self.candidate.update(xyz)
        if self.accepted is not None:
            return labels, conf
        self.since += 1
        due = self.since > self.check_frames and (
            len(xyz) >= self.start_points or self.since > self.check_frames + self.settle_frames)
        if not due:
            return labels, conf
        fresh = Labeller(self.ms, rate_hz=self.rate_hz)
        second, conf2 = fresh.update(xyz)
        both = (labels >= 0) & (second >= 0)
        self.tries += 1
        # every marker both named, named alike: a swapped pair is two differences in 41
        if both.sum() >= 3 and np.array_equal(labels[both], second[both]):
            self.agreed += 1
            self.since = 0
            if self.agreed >= self.confirmations or self.tries >= self.max_tries:
                self.accepted = self.candidate
            return labels, conf
        log.info("labelling: two starts from the marker set disagree on %d of %d markers; "
                 "checking again", int(np.sum(labels[both] != second[both])), int(both.sum()))
        self.candidate, self.since, self.agreed = fresh, 0, 0
        if self.tries >= self.max_tries:
            self.accepted = fresh
        return second, conf2


class _Search:
    """A _Start run on a thread: the first frame, then every frame queued since, until the
    start is accepted and current (see the module docstring)."""

    def __init__(self, start: _Start, first: np.ndarray, max_behind: int) -> None:
        self.start = start
        self.queue: deque = deque([first])
        self.max_behind = max_behind
        self.cond = threading.Condition()
        self.ready = False  # accepted and caught up: the frame loop may take the labeller
        self.cancelled = False
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, name="label-start", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while True:
            with self.cond:
                while (not self.queue and not self.cancelled
                       and self.start.accepted is None):
                    self.cond.wait(0.5)  # the check needs later frames
                if self.cancelled:
                    return
                if not self.queue:
                    self.ready = True
                    return
                xyz = self.queue.popleft()
            try:
                self.start.step(xyz)
            except Exception as exc:  # noqa: BLE001 - reported by the stage
                self.error = exc
                return

    def offer(self, xyz: np.ndarray) -> Labeller | None:
        """Hand the search this frame; the caught-up labeller when it is ready (the
        frame is then left for the caller to label), else None (the frame is queued)."""
        with self.cond:
            if self.ready:
                return self.start.accepted
            if len(self.queue) >= self.max_behind:  # too far behind: start again
                self.cancelled = True
            else:
                self.queue.append(xyz)
                self.cond.notify()
            return None


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
        self.labeller: Labeller | None = None  # None while a search runs (or before one)
        self.search: _Search | None = None  # a start on its thread (realtime)
        self.inline: _Start | None = None  # a start on the frame loop (background=False)
        self.check_frames = max(1, int(round(check_s * self.rate_hz)))
        self.background = background
        self.start_points = max(3, int(np.ceil(start_fraction * markerset.n)))
        self.settle_frames = max(1, int(round(settle_s * self.rate_hz)))
        self.waiting = 0  # frames with points seen, not yet started from
        self.steady = 0  # frames in a row showing most of the set
        self.hold_until = 0  # after a failure: no new start before this frame
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
        ids = np.asarray(tr.ids)
        held = getattr(getattr(result, "poses", None), "tracks", None)
        if held is not None and np.size(held):
            held = np.asarray(held)
            seen = seen & ~np.isin(ids, held[held >= 0])
        xyz = np.asarray(tr.xyz)[seen]
        self.frames += 1
        out = self._label(xyz, ids[seen])
        self.labelled = len(out.index)
        self.time_ns.append(time.monotonic_ns() - t0)
        return out

    def _label(self, xyz: np.ndarray, ids: np.ndarray) -> LabelledMarkers:
        if (self.labeller is None and self.search is None and self.inline is None
                and not self._may_start(len(xyz))):
            return self._empty
        if self.labeller is None and not self.background:
            if self.inline is None:
                self.starts += 1
                self.inline = self._start()
            try:
                labels, conf = self.inline.step(xyz)
            except Exception as exc:  # noqa: BLE001 - a labelling bug must not stop the stream
                self._failed(exc)
                return self._empty
            if self.inline.accepted is not None:
                self.labeller, self.inline = self.inline.accepted, None
            keep = labels >= 0
            return LabelledMarkers(self.set_name, self.names, labels[keep].astype(np.int64),
                                   xyz[keep], conf[keep], ids[keep])
        if self.labeller is None:
            if self.search is not None:
                self.labeller = self.search.offer(xyz)
                if self.search.error is not None:
                    self._failed(self.search.error)
                elif self.search.cancelled:
                    self.search = None
            if self.labeller is None:
                if self.search is None:
                    self.starts += 1
                    self.search = _Search(self._start(), xyz, self.max_behind)
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

    def _start(self) -> _Start:
        return _Start(self.ms, self.rate_hz, self.check_frames, self.start_points,
                      self.settle_frames)

    def _may_start(self, n_points: int) -> bool:
        """Whether this frame is one to start labelling from: most of the set seen for
        `check_frames` in a row (the tracker's first frames come and go), or points seen
        for `settle_frames` (see the module docstring)."""
        if n_points < 3 or self.frames < self.hold_until:
            self.waiting = self.steady = 0
            return False
        self.waiting += 1
        self.steady = self.steady + 1 if n_points >= self.start_points else 0
        if self.steady >= self.check_frames or self.waiting >= self.settle_frames:
            self.waiting = self.steady = 0
            return True
        return False

    def _failed(self, exc: BaseException) -> None:
        self.failures += 1
        if self.failures == 1:
            log.error("labelling failed (%s: %s); starting afresh from the marker set",
                      type(exc).__name__, exc, exc_info=exc)
        self.labeller, self.search, self.inline = None, None, None
        self.hold_until = self.frames + self.settle_frames  # a failing labeller: once a second

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


class LabelScore:
    """Per-frame hook scoring the labelled markers against the simulated person's truth
    (`mocapd start --sim` with `[sim] person = true`): a marker is named right when the
    true marker nearest its position is the one its name says; position errors are
    taken over those."""

    def __init__(self, scene) -> None:
        self.scene = scene
        self.index = {n: i for i, n in enumerate(scene.person_labels)}
        self._names: list[str] | None = None
        self._to_truth = np.zeros(0, np.int64)
        self.frames = 0  # frames with labelled markers
        self.right = 0
        self.labelled = 0
        self.unknown = 0  # names the person does not wear (another set)
        self.errors: deque = deque(maxlen=100_000)

    def __call__(self, result) -> None:
        lab = result.labelled
        if lab is None or not len(lab.index) or result.scene_frame < 0:
            return
        if lab.names is not self._names:
            self._names = lab.names
            self._to_truth = np.array([self.index.get(n, -1) for n in lab.names])
        truth = self.scene.person_xyz[result.scene_frame]
        want = self._to_truth[lab.index]
        known = want >= 0
        d = np.linalg.norm(lab.xyz[known, None] - truth[None], axis=2)
        nearest = np.argmin(d, axis=1)
        right = nearest == want[known]
        e = d[right, nearest[right]]
        self.frames += 1
        self.labelled += int(known.sum())
        self.unknown += int((~known).sum())
        self.right += int(right.sum())
        self.errors.extend(e.tolist())

    def figures(self) -> dict:
        e = np.array(self.errors) * 1000
        return {"frames": self.frames, "labelled": self.labelled,
                "named_right_fraction": self.right / self.labelled if self.labelled else None,
                "not_in_person": self.unknown,
                "position_error_mm_median": float(np.median(e)) if len(e) else None,
                "position_error_mm_p99": float(np.percentile(e, 99)) if len(e) else None}
