"""The replay page (`mocapd view FILE`): a take or a recording, scrubbed frame by frame.

A C3D or labelled CSV take is shown as its markers with their names, and with a marker
set its sticks (each segment a tree of its nearest markers, as the live view draws them).
A recording (.mcrec) holds blobs, not markers: its frames are matched and triangulated
once at the start with the rig, the way `calibkit triangulate` does, and the page shows
the unlabelled markers. Everything is loaded before the page serves, so moving the slider
only picks a slice of arrays already in memory.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.recording import load_observations
from calibkit.vision.correspondence import match_frames
from calibkit.vision.gates import gated_config
from daemon.formats.c3dio import read_take
from daemon.view import draw

LABELLED = (60, 220, 90)
UNLABELLED = (235, 235, 235)
SUFFIXES = (".c3d", ".csv", ".mcrec")


@dataclass
class ReplayFrames:
    """Markers of every frame, ragged: frame k's are rows offsets[k]:offsets[k + 1]."""

    frame: np.ndarray  # (F,) the file's frame numbers
    t_s: np.ndarray  # (F,) seconds from the first frame
    offsets: np.ndarray  # (F + 1,)
    xyz: np.ndarray  # (P, 3) metres
    label: np.ndarray  # (P,) index into labels, -1 for an unlabelled marker
    labels: list[str] = field(default_factory=list)
    sticks: list[tuple[int, int]] = field(default_factory=list)  # pairs of label indices
    kind: str = ""

    def __len__(self) -> int:
        return len(self.frame)

    def at(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(xyz, label) of the k-th frame (k counts from 0, whatever the file numbers)."""
        a, b = self.offsets[k], self.offsets[k + 1]
        return self.xyz[a:b], self.label[a:b]


def from_take(take, ms=None) -> ReplayFrames:
    """A labelled take (daemon.formats.c3dio.Take); sticks from the marker set `ms` for
    the labels the take has."""
    vis = np.isfinite(take.xyz_m).all(axis=2)
    _, col = np.nonzero(vis)
    n = len(take.xyz_m)
    offsets = np.r_[0, np.cumsum(vis.sum(axis=1))]
    sticks = []
    if ms is not None:
        # deferred on purpose: loads OpenCV only where used
        from daemon.view.draw import markerset_sticks

        where = {name: k for k, name in enumerate(take.labels)}
        sticks = [(where[ms.labels[a]], where[ms.labels[b]]) for a, b in markerset_sticks(ms)
                  if ms.labels[a] in where and ms.labels[b] in where]
        if not sticks:
            raise UserError(f"marker set {ms.name}: none of its markers is named in the take "
                            f"({', '.join(take.labels[:5])}, ...)")
    return ReplayFrames(take.first_frame + np.arange(n), np.arange(n) / take.rate_hz, offsets,
                        take.xyz_m[vis], col.astype(np.int64), list(take.labels), sticks,
                        f"{len(take.labels)} labelled markers, {take.rate_hz:g} Hz")


def from_recording(path: Path, rig, progress=None) -> ReplayFrames:
    """A recording's blobs matched across cameras and triangulated, frame by frame, with
    `calibkit triangulate`'s gates (they follow the rig's residual)."""
    obs, _ = load_observations(path, rig)
    if len(obs) == 0:
        raise UserError(f"{path}: holds no blobs")
    cfg, _ = gated_config(rig, obs)
    pts = match_frames(rig, obs, cfg, progress=progress)
    frames = obs.frames()
    order = np.argsort(pts.frame, kind="stable")
    f = pts.frame[order]
    offsets = np.searchsorted(f, np.r_[frames, frames[-1] + 1])
    first_t = np.full(len(frames), np.iinfo(np.int64).max)
    np.minimum.at(first_t, np.searchsorted(frames, obs.frame), obs.t_ns)
    fps = f", {obs.fps:g} fps" if obs.fps else ""
    return ReplayFrames(frames, (first_t - first_t[0]) * 1e-9, offsets, pts.xyz[order],
                        np.full(len(f), -1, np.int64), [], [],
                        f"unlabelled markers triangulated from {len(obs.camera_names)} "
                        f"cameras{fps}")


def load_replay(path: Path, rig_path: Path | None = None, markerset: str | None = None,
                progress=None) -> tuple[ReplayFrames, object]:
    """(the frames, the rig or None) from what the user gave; UserError in one line."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise UserError(f"{path}: the replay page shows a take (.c3d, .csv) or a recording "
                        f"(.mcrec), got {suffix or 'no suffix'}")
    if not path.is_file():
        raise UserError(f"{path}: no such file")
    rig = Rig.load(rig_path) if rig_path is not None else None
    if suffix == ".mcrec":
        if rig is None:
            raise UserError(f"{path} holds blobs: give the rig that recorded it (--rig "
                            "RIG.toml) to triangulate its markers")
        if markerset is not None:
            raise UserError("--markerset draws a labelled take's sticks; a recording's "
                            "markers are unlabelled")
        return from_recording(path, rig, progress), rig
    ms = None
    if markerset is not None:
        # deferred on purpose: loads tomli_w only where used
        from daemon.labelling.markerset import open_set

        ms = open_set(markerset)
    return from_take(read_take(path), ms), rig


class ReplayView:
    """The page: a frame slider, play and step buttons, the markers of the chosen frame
    (with names and sticks for a labelled take) over a floor grid and the rig's frusta."""

    def __init__(self, server, frames: ReplayFrames, rig=None, title: str = "") -> None:
        self.server, self.frames, self.rig = server, frames, rig
        self.k = -1
        self.drawn = np.zeros((0, 3), np.float32)  # what the 3D view shows now
        self._lock = threading.Lock()
        self._stop = threading.Event()
        gui, sc = server.gui, server.scene
        gui.configure_theme(control_width="large", dark_mode=True, show_logo=False,
                            show_share_button=False)
        sc.set_up_direction("+z")
        self._build_scene()
        gui.add_markdown(f"**{title}**: {len(frames)} frames, {frames.kind}")
        # the slider runs over the file's own frame numbers, as the readout says them
        first, last = int(frames.frame[0]), int(frames.frame[-1])
        self.slider = gui.add_slider("Frame", min=first, max=max(last, first + 1), step=1,
                                     initial_value=first)
        self.readout = gui.add_markdown("")
        with gui.add_folder("Play"):
            self.playing = gui.add_checkbox("Play", False)
            self.speed = gui.add_dropdown("Speed", ["0.25", "0.5", "1", "2", "4"],
                                          initial_value="1")
            back = gui.add_button("Previous frame")
            fwd = gui.add_button("Next frame")
        self.show_labels = gui.add_checkbox("Marker names", False,
                                            disabled=not frames.labels)
        self.slider.on_update(lambda _: self.show(self.index_of(int(self.slider.value))))
        self.show_labels.on_update(lambda _: self.show(self.k, force=True))
        back.on_click(lambda _: self._step(-1))
        fwd.on_click(lambda _: self._step(1))
        self.show(0)
        threading.Thread(target=self._play, name="replay-play", daemon=True).start()

    def _build_scene(self) -> None:
        sc, fr = self.server.scene, self.frames
        pts = fr.xyz if len(fr.xyz) else np.zeros((1, 3))
        lo, hi = np.percentile(pts[:, :2], [1, 99], axis=0)
        centre = (lo + hi) / 2
        side = float(max(np.max(hi - lo) + 1.0, 2.0))
        if self.rig is not None:
            centre, side = draw.floor_extent(self.rig)
            for f in draw.camera_frusta(self.rig):
                sc.add_camera_frustum(f"/cameras/{f['name']}", fov=float(f["fov"]),
                                      aspect=float(f["aspect"]), scale=0.25, thickness=0.01,
                                      color=(200, 200, 120), wxyz=f["wxyz"],
                                      position=f["position"])
        sc.add_grid("/floor", width=side, height=side, plane="xy", cell_size=0.5,
                    section_size=1.0, position=(float(centre[0]), float(centre[1]), 0.0),
                    cell_color=(90, 90, 90), section_color=(130, 130, 130))
        sc.add_frame("/world", axes_length=0.3, axes_radius=0.008)
        empty = np.zeros((1, 3), np.float32)
        self.cloud = sc.add_point_cloud("/markers", empty, UNLABELLED, point_size=0.03,
                                        point_shape="circle", precision="float32",
                                        visible=False)
        self.sticks = sc.add_line_segments("/sticks", np.zeros((1, 2, 3), np.float32),
                                           LABELLED, thickness=0.006, visible=False)
        self.names = [sc.add_label(f"/names/{k}", name, font_screen_scale=0.6,
                                   visible=False) for k, name in enumerate(fr.labels)]
        mid = np.median(pts, axis=0)
        self.server.initial_camera.look_at = tuple(float(v) for v in mid)
        self.server.initial_camera.position = (float(mid[0]) - 2.2, float(mid[1]) - 2.2,
                                               float(mid[2]) + 0.9)
        self.server.initial_camera.up = (0.0, 0.0, 1.0)

    def index_of(self, frame_number: int) -> int:
        """The frame shown for a file frame number: that one, or the last before it (a
        recording skips frames in which no camera saw anything)."""
        k = int(np.searchsorted(self.frames.frame, frame_number, side="right")) - 1
        return max(k, 0)

    def show(self, k: int, force: bool = False) -> None:
        """Draw frame k (0-based) and say which it is."""
        fr = self.frames
        k = int(np.clip(k, 0, len(fr) - 1))
        with self._lock:
            if k == self.k and not force:
                return
            xyz, label = fr.at(k)
            xyz = np.asarray(xyz, np.float32)
            with self.server.atomic():
                self.cloud.visible = len(xyz) > 0
                if len(xyz):
                    self.cloud.points = xyz
                    self.cloud.colors = np.where((label >= 0)[:, None],
                                                 np.array(LABELLED, np.uint8),
                                                 np.array(UNLABELLED, np.uint8))
                where = {int(m): i for i, m in enumerate(label.tolist()) if m >= 0}
                seg = [(xyz[where[a]], xyz[where[b]]) for a, b in fr.sticks
                       if a in where and b in where]
                self.sticks.visible = bool(seg)
                if seg:
                    self.sticks.points = np.asarray(seg, np.float32)
                names_on = bool(self.show_labels.value) if hasattr(self, "show_labels") \
                    else False
                for m, handle in enumerate(self.names):
                    i = where.get(m)
                    handle.visible = names_on and i is not None
                    if i is not None and names_on:
                        handle.position = xyz[i].astype(np.float64)
            self.k, self.drawn = k, xyz
            n_lab = int((label >= 0).sum())
            self.readout.content = (
                f"frame **{int(fr.frame[k])}** at {fr.t_s[k]:.3f} s: {len(xyz)} markers"
                + (f", {n_lab} of {len(fr.labels)} named" if fr.labels else ""))
        if self.index_of(int(self.slider.value)) != k:
            self.slider.value = int(fr.frame[k])

    def _step(self, d: int) -> None:
        self.playing.value = False
        self.show(self.k + d)

    def _play(self) -> None:
        """While Play is ticked: frames at their own times (times the chosen speed),
        skipping those the page cannot keep up with; back to the start at the end."""
        t_wall = t_file = None
        while not self._stop.wait(1 / 60):
            if not self.playing.value or len(self.frames) < 2:
                t_wall = None
                continue
            now = time.monotonic()
            if t_wall is None:
                t_wall, t_file = now, float(self.frames.t_s[max(self.k, 0)])
            target = t_file + (now - t_wall) * float(self.speed.value)
            k = int(np.searchsorted(self.frames.t_s, target, side="right")) - 1
            if k >= len(self.frames) - 1:
                t_wall = None
                k = 0
            self.show(k)

    def close(self) -> None:
        self._stop.set()
