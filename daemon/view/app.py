"""The live view's process: a viser web server showing the rig as the daemon sees it.

It gets the daemon's frames (daemon.view.link: the newest, up to 30 a second) down a
pipe and asks the daemon everything else through its control socket, as the `mocapd`
commands do: `status` for each camera's rate and drops, `markers` and `reload` to define a
body. The page: per camera a thumbnail (daemon.view.draw.thumbnail, a few a second over
viser's websocket) and its figures; a 3D view of the frusta, the floor, the markers
(free, on a body, picked, labelled with the marker set's sticks) and the bodies with their
axes and trails; bodies made from picked markers, renamed and removed.
"""

from __future__ import annotations

import contextlib
import io
import logging
import threading
import time
from collections import deque

import numpy as np

from calibkit.core.errors import UserError
from calibkit.vision.masks import load_mask
from daemon.publish.bad_input import BadInput
from daemon.service.control import request
from daemon.view import draw, quiet
from daemon.view.detection_panel import DetectionPanel
from daemon.view.scene import Scene, marker_colours

log = logging.getLogger("mocapd.view")
THUMB_HZ = 8.0  # thumbnails a second, per camera
SCENE_HZ = 30.0  # 3D updates a second
STATUS_HZ = 2.0  # `status` requests a second
TRAIL_S = 2.0


def main(conn, host: str, port: int) -> None:
    """The process: serve, say so (or why not), then follow the daemon until it stops."""
    logging.basicConfig(level=logging.WARNING, format="mocapd-view: %(message)s")
    quiet.install(log)  # bad requests: one line per kind a minute, never a traceback
    try:
        # deferred on purpose: loads viser only where used
        import viser

        with contextlib.redirect_stdout(io.StringIO()):  # its banner: the daemon logs the URL
            server = viser.ViserServer(host=host, port=port, label="mocapd", verbose=False)
        # viser can tunnel a page to its public share service when a client asks; the rig
        # is shown only where the operator said (--view), so that request does nothing
        server.request_share_url = lambda *args, **kwargs: None
    except Exception as exc:  # noqa: BLE001 - any failure to serve goes back as one line
        conn.send({"error": f"cannot serve on {host}:{port}: {exc}"})
        return
    if server.get_port() != port:
        server.stop()
        conn.send({"error": f"port {port} on {host} is taken; choose another"})
        return
    conn.send({"ready": True})
    view = LiveView(server)
    try:
        view.follow(conn)
    finally:
        view.close()




def _finite(*values, shapes: tuple) -> list[np.ndarray]:
    """Values of a page's event as float arrays of the given shapes; ValueError if one is
    not finite or of another shape (a nested list broadcasts into picks of no marker)."""
    out = [np.asarray(v, dtype=np.float64) for v in values]
    if tuple(v.shape for v in out) != shapes:
        raise ValueError("a value of the wrong shape")
    if not all(np.isfinite(v).all() for v in out):
        raise ValueError("a value that is not a finite number")
    return out


def _next(due: float, hz: float, now: float) -> float:
    """The next deadline of a redraw done `hz` times a second: one period after the last
    one, so the rate holds whatever the redraw costs, but never half a period in the past
    (a stall is not caught up)."""
    return max(due + 1.0 / hz, now - 0.5 / hz)

class LiveView:
    """The page's contents, updated from the daemon's frames."""

    def __init__(self, server) -> None:
        self.server = server
        self.desc: dict | None = None
        self.frame: dict | None = None
        self.dirty = False  # a frame or a pick the 3D view has not drawn yet
        self.blobs: dict[int, tuple] = {}  # camera -> (uv, area) of its newest sample
        self.status: dict | None = None
        self.picked: set[int] = set()
        self.picked_at: dict[int, np.ndarray] = {}  # where each picked marker was picked
        self.trails: dict[int, deque] = {}
        self.thumbs: list = []
        self.masks: dict = {}
        self.cam_md: list = []
        self.frames_drawn = 0
        self.thumbs_drawn = 0
        self._rates = deque(maxlen=2)  # (time, scenes drawn, thumbnail rounds drawn)
        self._stop = threading.Event()
        self._busy = threading.Lock()  # one body edit at a time
        self.bad = BadInput(log, "view")  # crafted page events, once a minute per kind
        server.gui.configure_theme(control_width="large", dark_mode=True, show_logo=False,
                                  show_share_button=False)
        server.scene.set_up_direction("+z")
        self.head = server.gui.add_markdown("**mocapd**: waiting for the daemon's rig")

    # ---- from the daemon -------------------------------------------------------------------

    def follow(self, conn) -> None:
        """Read the pipe (the newest frame wins), redraw at the scene's and thumbnails'
        rates, ask for the status now and then; until the daemon stops or goes away."""
        next_scene = next_thumb = next_status = 0.0
        threading.Thread(target=self._status_loop, name="view-status", daemon=True).start()
        while True:
            try:
                if conn.poll(0.01):
                    while True:  # drain: set-ups in order, the last frame kept
                        msg = conn.recv()
                        if "stop" in msg:
                            return
                        if "setup" in msg:
                            self.setup(msg["setup"])
                        elif "frame" in msg:
                            self.take(msg["frame"])
                        if not conn.poll(0):
                            break
            except (EOFError, OSError):
                return
            if self.desc is None:
                continue
            now = time.monotonic()
            if now >= next_scene and self.frame is not None and self.dirty:
                next_scene = _next(next_scene, SCENE_HZ, now)
                self.draw_scene()
            if now >= next_thumb:
                next_thumb = _next(next_thumb, THUMB_HZ, now)
                self.draw_thumbnails()
            if now >= next_status:
                next_status = _next(next_status, STATUS_HZ, now)
                self.draw_figures()

    def take(self, frame: dict) -> None:
        self.frame = frame
        self.dirty = True
        for cam, uv, area in frame["cameras"]:
            self.blobs[cam] = (uv, area)
        now = frame["t_ns"] * 1e-9
        for i, ok, p in zip(frame["body_ids"].tolist(), frame["body_valid"].tolist(),
                            frame["body_position"], strict=True):
            trail = self.trails.setdefault(i, deque(maxlen=int(TRAIL_S * SCENE_HZ) + 1))
            trail.append((now, p if ok else np.full(3, np.nan, np.float32)))

    def _status_loop(self) -> None:
        while not self._stop.wait(1.0 / STATUS_HZ):
            if self.desc is None:
                continue
            try:
                self.status = request(self.desc["runtime_dir"], {"cmd": "status"},
                                      timeout_s=2.0)
            except Exception as exc:  # noqa: BLE001 - the daemon may be going away
                log.debug("status: %s", exc)

    # ---- building the page -------------------------------------------------------------------

    def setup(self, desc: dict) -> None:
        """The rig's scene and the page's panels, once; the body list again after a reload."""
        first = self.desc is None
        self.desc = desc
        self.masks = self._load_masks(desc)
        if first:
            self._build_scene(desc["rig"])
            self._build_gui(desc)
        else:
            self.detection.fill()
        self._build_bodies(desc["bodies"])
        self._build_sticks()

    @staticmethod
    def _load_masks(desc: dict) -> dict:
        """camera name -> its detection mask (bool), drawn in blue on its thumbnail."""
        out = {}
        for name, c in desc["cameras"].items():
            if c.get("mask"):
                try:
                    out[name] = load_mask(c["mask"])
                except Exception as exc:  # noqa: BLE001 - a mask the daemon refused too
                    log.warning("mask of %s: %s", name, exc)
        return out

    def _build_scene(self, rig) -> None:
        self.scene = Scene(self.server, rig)
        self.server.scene.on_click()(self._on_click)
        self.server.scene.on_rect_select(modifier="shift")(self._on_rect)

    def _build_gui(self, desc: dict) -> None:
        gui = self.server.gui
        rig = desc["rig"]
        tabs = gui.add_tab_group()
        cams = tabs.add_tab("Cameras", icon="camera")
        with cams:  # the thumbnails first: the panel is never text before pictures
            for cam in rig:
                blank = draw.thumbnail(cam.size, np.zeros((0, 2)), np.zeros(0))
                self.thumbs.append(gui.add_image(blank, label=cam.name, format="jpeg",
                                                 jpeg_quality=75))
                self.cam_md.append(gui.add_markdown(f"`{cam.name}`: waiting"))
            if desc["simulated"]:
                gui.add_markdown("_Simulated cameras give blobs, not images: each thumbnail "
                                 "is the blobs drawn on a dark frame of the camera's size._")
        with tabs.add_tab("Detection", icon="adjustments"):
            self.detection = DetectionPanel(gui, self)
        bodies = tabs.add_tab("Bodies", icon="cube")
        with bodies:
            self.bodies_md = gui.add_markdown("no rigid bodies")
            gui.add_markdown("**New body**: click markers in the 3D view (shift-drag a box "
                             "to pick several), hold the body still, name it, create.")
            self.picked_md = gui.add_markdown("picked: none")
            clear = gui.add_button("Clear picks")
            self.new_name = gui.add_text("Name", "")
            create = gui.add_button("Create body from picked markers", color="green")
            gui.add_markdown("**Existing body**")
            self.body_choice = gui.add_dropdown("Body", ["-"])
            self.rename_to = gui.add_text("Rename to", "")
            rename = gui.add_button("Rename")
            remove = gui.add_button("Remove", color="red")
            self.message = gui.add_markdown("")
        clear.on_click(lambda _: self._set_picked(set()))
        create.on_click(lambda _: self.run_edit(self._create, self.message))
        rename.on_click(lambda _: self.run_edit(self._rename, self.message))
        remove.on_click(lambda _: self.run_edit(self._remove, self.message))

    def _build_sticks(self) -> None:
        """The set's sticks, coloured by segment once (only their ends move afterwards)."""
        self._pairs = np.asarray(self.desc.get("sticks") or [], np.int64).reshape(-1, 2)
        n = len(self._pairs)
        self.scene.set_sticks(marker_colours(n, np.full(n, -1), np.zeros(n, bool),
                                             self._segment_of(self._pairs[:, 0])))

    def _build_bodies(self, bodies: list) -> None:
        self.scene.set_bodies(bodies)
        names = [n for _, n in bodies]
        self.body_choice.options = names or ["-"]
        self.names = dict(bodies)

    # ---- drawing ----------------------------------------------------------------------------

    def draw_scene(self) -> None:
        """The frame's markers (a labelled marker drawn once, in its segment's colour, with
        the set's sticks), the bodies at their poses and their trails."""
        f = self.frame
        self.dirty = False
        seen = f["track_seen"]
        ids, xyz = f["track_ids"][seen], f["track_xyz"][seen]
        held_by = f["track_body"][seen] if "track_body" in f else \
            np.where(f["track_held"][seen], 0, -1)
        lab_idx = f.get("labelled_index")
        stick_seg = None
        if lab_idx is not None and len(lab_idx):
            lab_xyz = np.asarray(f["labelled_xyz"], np.float32)
            lab_seg = self._segment_of(lab_idx)
            # tracks the labeller named are drawn as labelled markers, not twice
            if len(xyz):
                near = np.linalg.norm(xyz[:, None] - lab_xyz[None], axis=2).min(axis=1)
                keep = near >= 1e-4
                ids, xyz, held_by = ids[keep], xyz[keep], held_by[keep]
            stick_seg = self._stick_segments(lab_idx, lab_xyz)
        else:
            lab_xyz, lab_seg = np.zeros((0, 3), np.float32), np.zeros(0, np.int64)
        picked = np.isin(ids, list(self.picked))
        n_free = len(xyz)
        all_xyz = np.concatenate([xyz, lab_xyz]).astype(np.float32)
        colours = marker_colours(len(all_xyz),
                                 np.concatenate([held_by, np.full(len(lab_xyz), -1)]),
                                 np.concatenate([picked, np.zeros(len(lab_xyz), bool)]),
                                 np.concatenate([np.full(n_free, -1), lab_seg]))
        big = np.concatenate([picked, np.zeros(len(lab_xyz), bool)])
        segs = [draw.trail_segments(np.array([p for _, p in t])) for t in self.trails.values()]
        segs = np.concatenate(segs) if segs else np.zeros((0, 2, 3), np.float32)
        with self.server.atomic():
            self.scene.draw_markers(all_xyz, colours, big)
            self.scene.draw_sticks(stick_seg)
            self.scene.draw_bodies(f["body_ids"].tolist(), f["body_valid"].tolist(),
                                   f["body_position"], f["body_quaternion"])
            self.scene.draw_trails(segs)
        self.frames_drawn += 1

    def _segment_of(self, index: np.ndarray) -> np.ndarray:
        """The segment of each of the marker set's markers (-1 for one the set lacks)."""
        segment_of = np.asarray(self.desc.get("segment_of") or [], np.int64)
        out = np.full(len(index), -1, np.int64)
        ok = (index >= 0) & (index < len(segment_of))
        out[ok] = segment_of[index[ok]]
        return out

    def _stick_segments(self, index: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        """(P, 2, 3): every stick of the set, in the set's order; a stick whose markers are
        not both labelled this frame shrinks to nothing (at its marker that is, else at the
        origin), so the page gets the same sticks every frame and only their ends move."""
        pairs = self._pairs
        where = np.full(max(int(index.max()) + 1, int(pairs.max(initial=-1)) + 1), -1)
        where[index] = np.arange(len(index))
        ends = where[pairs]  # (P, 2), -1 where not labelled
        seg = np.zeros((len(pairs), 2, 3), np.float32)
        ok = ends >= 0
        seg[ok] = xyz[ends[ok]]
        one = ok.any(axis=1) & ~ok.all(axis=1)  # a stick with one end: a point there
        seg[one] = seg[one][np.arange(one.sum()), ok[one].argmax(axis=1)][:, None]
        return seg

    def draw_thumbnails(self) -> None:
        rig = self.desc["rig"]
        thr = self.desc["cameras"]
        for c, cam in enumerate(rig):
            uv, area = self.blobs.get(c, (np.zeros((0, 2)), np.zeros(0)))
            t = thr.get(cam.name, {}).get("threshold")
            self.thumbs[c].image = draw.thumbnail(cam.size, uv, area, threshold=t,
                                                  mask=self.masks.get(cam.name))
        self.thumbs_drawn += 1

    def draw_figures(self) -> None:
        st, f = self.status, self.frame
        self.scene.draw_camera_states(st)
        if f is not None:
            valid = [self.names.get(i, str(i)) for i, ok in
                     zip(f["body_ids"].tolist(), f["body_valid"].tolist(), strict=True) if ok]
            rate = f"{st['rate_hz']:.0f} fps, " if st else ""
            lat = st["latency"]["median_ms"] if st else None
            self._rates.append((time.monotonic(), self.frames_drawn, self.thumbs_drawn))
            (t0, s0, h0), (t1, s1, h1) = self._rates[0], self._rates[-1]
            dt = max(t1 - t0, 1e-9)
            view = (f"  \nview: 3D {(s1 - s0) / dt:.0f}/s, thumbnails {(h1 - h0) / dt:.1f}/s "
                    "per camera" if t1 > t0 else "")
            self.head.content = (
                f"**mocapd** frame {f['frame']}: {rate}"
                + (f"latency {lat:.2f} ms median, " if lat is not None else "")
                + f"{int(f['track_seen'].sum())} markers, "
                f"{len(valid)} of {len(self.names)} bodies tracked" + view)
            rows = "\n".join(f"| {n} | {i} | {'tracked' if n in valid else 'lost'} |"
                             for i, n in self.names.items())
            self.bodies_md.content = ("| body | id | |\n|---|---|---|\n" + rows
                                      if rows else "no rigid bodies")
        cams = {c["name"]: c for c in (st or {}).get("cameras", [])}
        for c, cam in enumerate(self.desc["rig"]):
            s = cams.get(cam.name)
            n = len(self.blobs.get(c, ((),))[0])
            if s is None:
                self.cam_md[c].content = f"`{cam.name}`: {n} blobs"
            else:
                det = "" if "threshold" not in s else (
                    f", threshold {s['threshold']}" + (", masked" if s.get("mask") else ""))
                self.cam_md[c].content = (
                    f"`{cam.name}`: {s['rate_hz']:.0f} fps, {s['dropped']} dropped, "
                    f"{n} blobs{det}" + ("" if s["connected"] else ", **disconnected**"))

    # ---- picking and editing ----------------------------------------------------------------

    def _free_seen(self):
        f = self.frame
        if f is None:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        sel = f["track_seen"] & ~f["track_held"]
        return f["track_ids"][sel], f["track_xyz"][sel]

    def _set_picked(self, picked: set, ids=(), xyz=()) -> None:
        """The picked track ids; `ids`, `xyz`: where markers were when picked (a body is
        then captured by position if its tracks were lost and found again meanwhile)."""
        self.picked = set(picked)
        self.picked_at.update({int(i): np.asarray(x, float) for i, x in zip(ids, xyz,
                                                                          strict=True)})
        self.picked_at = {i: x for i, x in self.picked_at.items() if i in self.picked}
        self.dirty = True
        self.picked_md.content = ("picked: " + (", ".join(f"marker {i}" for i in
                                                          sorted(self.picked)) or "none"))

    def _on_click(self, event) -> None:
        try:
            ids, xyz = self._free_seen()
            k = draw.pick_by_ray(xyz, *_finite(event.ray_origin, event.ray_direction,
                                               shapes=((3,), (3,))))
        except (TypeError, ValueError) as exc:  # a crafted click: no ray, NaN, text...
            self.bad("click that is no ray", exc)
            return
        if k >= 0:
            self._set_picked(self.picked ^ {int(ids[k])}, ids[k:k + 1], xyz[k:k + 1])

    def _on_rect(self, event) -> None:
        try:
            ids, xyz = self._free_seen()
            cam = event.client.camera
            inside = draw.pick_in_rect(xyz, *_finite(cam.position, cam.wxyz, cam.fov,
                                                     cam.aspect, event.screen_min,
                                                     event.screen_max,
                                                     shapes=((3,), (4,), (), (), (2,), (2,))))
        except (TypeError, ValueError, ArithmeticError) as exc:  # a window 0 px high too
            self.bad("box selection that is no box", exc)
            return
        self._set_picked(self.picked | {int(i) for i in ids[inside]}, ids[inside], xyz[inside])

    def run_edit(self, action, message) -> None:
        """Edits of the configuration run on a thread of their own (a body's creation
        watches 30 frames) and one at a time, then the daemon reloads; their outcome, or
        the user's error, is written in `message` (a markdown under the buttons)."""
        def run():
            if not self._busy.acquire(blocking=False):
                message.content = "busy with the last request"
                return
            try:
                done = action()
                message.content = done + "; the daemon is reloading"
                answer = request(self.desc["runtime_dir"], {"cmd": "reload"})
                if not answer.get("pending"):
                    message.content = done + "; the daemon reloaded"
            except UserError as exc:
                message.content = f"**not done**: {exc}"
            except Exception as exc:  # noqa: BLE001 - the page must say, not die
                log.exception("edit failed")
                message.content = f"**failed**: {exc}"
            finally:
                self._busy.release()

        message.content = "working..."
        threading.Thread(target=run, name="view-edit", daemon=True).start()

    def _create(self) -> str:
        # deferred on purpose: loads numba kernels, SciPy... only where used
        from daemon.view.bodies import add_picked

        rt = self.desc["runtime_dir"]
        name = quiet.text(self.new_name.value, "name", 64)
        body_id, n = add_picked(self.desc["config"], name, self.picked,
                                lambda: request(rt, {"cmd": "markers"}), at=self.picked_at)
        self._set_picked(set())
        return f"added rigid body {name.strip()!r} (id {body_id}, {n} markers)"

    def _rename(self) -> str:
        # deferred on purpose: loads numba (compiled kernels), tomli_w only where used
        from daemon.view.bodies import rename_body

        old = quiet.choice(self.body_choice.value, self.body_choice.options, "body")
        new = quiet.text(self.rename_to.value, "new name", 64)
        rename_body(self.desc["config"], old, new)
        return f"renamed {old!r} to {new.strip()!r}"

    def _remove(self) -> str:
        # deferred on purpose: loads numba (compiled kernels), tomli_w only where used
        from daemon.view.bodies import remove_body

        name = quiet.choice(self.body_choice.value, self.body_choice.options, "body")
        remove_body(self.desc["config"], name)
        return f"removed {name!r}"

    def close(self) -> None:
        self._stop.set()
        self.server.stop()
