"""The live view's 3D scene: floor, world axes, cameras and their state, markers, bodies.

It is judged by a person glancing at it, often from across a room, so everything is sized
from the rig's own extent rather than in fixed metres: a 14 mm marker drawn true to size is
two pixels wide seen from behind a camera 3 m away. Markers are lit spheres (their shading
outlines them against the floor) in saturated colours, each meaning one thing: orange on
no body, the body's colour on a body, magenta picked, the segment's colour when the marker
set labels them. The floor is a light plane with a grid, under a dark sky, so markers,
the bodies' red, green and blue axes and the cameras all stand out against it. A camera's
frustum and name are coloured by its state (connected, dropped out, no frames), read
from the daemon's status.

The markers are one batched mesh of a few hundred triangles per sphere, updated in place
(positions, colours, scales) 30 times a second; instances beyond this frame's markers are
scaled to nothing, so its size changes only when the markers outgrow it.
"""

from __future__ import annotations

import numpy as np

from daemon.view import draw

FLOOR_RGB = (226, 229, 234)  # a light plane...
GRID_CELL_RGB = (170, 176, 186)  # ...with its 0.5 m grid...
GRID_SECTION_RGB = (110, 118, 130)  # ...and 1 m lines a shade darker
FREE_RGB = (255, 120, 0)  # a marker on no body
PICKED_RGB = (255, 0, 200)
BODY_RGB = [(0, 150, 255), (0, 200, 120), (255, 200, 0), (170, 90, 255),
            (0, 210, 220), (255, 90, 160), (140, 200, 0), (255, 60, 40)]
# one per segment of a marker set (hue steps far apart, all saturated)
SEGMENT_RGB = [(255, 60, 60), (40, 130, 255), (40, 210, 90), (255, 170, 0),
               (190, 80, 255), (0, 215, 215), (255, 80, 190), (150, 210, 0),
               (255, 120, 60), (90, 100, 255), (0, 170, 130), (230, 200, 0)]
CAMERA_RGB = {"connected": (40, 200, 90), "dropped": (235, 45, 45),
              "no frames": (250, 165, 0), "waiting": (150, 150, 150)}
VIEW_FOV_RAD = np.radians(50.0)  # the page's first view; narrower than viser's 75 degrees


def scales(rig) -> dict:
    """Sizes of what is drawn, from the rig's extent (the side of the floor under it):
    at 6 m, markers 7 cm across, body axes 25 cm, world axes 50 cm, frusta 20 cm deep."""
    _, side = draw.floor_extent(rig)
    return {"marker_radius_m": float(np.clip(0.006 * side, 0.01, 0.08)),
            "stick_m": float(np.clip(0.0025 * side, 0.004, 0.03)),
            "body_axes_m": float(np.clip(0.04 * side, 0.1, 0.6)),
            "world_axes_m": float(np.clip(0.08 * side, 0.2, 1.2)),
            "frustum_m": float(np.clip(0.033 * side, 0.1, 0.5)),
            "side_m": side}


def initial_view(rig) -> dict:
    """Where the page looks from at first: at the volume's centre (at about a person's
    chest) from above and beyond the wall between the first two cameras, so that no
    camera's frustum stands in front of the volume and the whole rig is in sight."""
    centre, side = draw.floor_extent(rig)
    target = np.array([centre[0], centre[1], 0.8])
    c = rig.centres()
    between = (c[0] + c[1 % len(c)]) / 2 - target
    away = between[:2] / max(np.linalg.norm(between[:2]), 1e-9)
    position = target + np.array([*(0.7 * side * away), 0.4 * side])
    # the page's panel covers its right third: look a little right of the volume's centre
    # so that the volume sits in the part left free
    fwd = (target - position) / np.linalg.norm(target - position)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    look_at = target + 0.1 * side * right / np.linalg.norm(right)
    return {"position": position, "look_at": look_at,
            "up": np.array([0.0, 0.0, 1.0]), "fov_rad": float(VIEW_FOV_RAD)}


def camera_state(status: dict | None) -> str:
    """A camera's state from its `status` entry: dropped out (its driver says it is not
    connected), no frames (connected, but nothing came in the last second), connected."""
    if status is None:
        return "waiting"
    if not status.get("connected", True):
        return "dropped"
    if status.get("rate_hz", 0.0) < 0.5:
        return "no frames"
    return "connected"


def marker_colours(n: int, held_by: np.ndarray, picked: np.ndarray,
                   segment: np.ndarray) -> np.ndarray:
    """(n, 3) uint8 colour of each marker: picked, else its segment's (segment >= 0), else
    its body's (held_by >= 0: the body's row), else free."""
    out = np.tile(np.array(FREE_RGB, np.uint8), (n, 1))
    body = np.asarray(BODY_RGB, np.uint8)
    on = held_by >= 0
    out[on] = body[held_by[on] % len(body)]
    seg = np.asarray(SEGMENT_RGB, np.uint8)
    lab = segment >= 0
    out[lab] = seg[segment[lab] % len(seg)]
    out[picked] = PICKED_RGB
    return out


def _sphere(subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A unit sphere's vertices and faces (an icosphere: even triangles, smooth shading)."""
    # deferred on purpose: trimesh comes with viser, loaded only in the view's process
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return np.asarray(s.vertices, np.float32), np.asarray(s.faces, np.uint32)


class Scene:
    """The scene's nodes on a viser server, and their updates."""

    def __init__(self, server, rig) -> None:
        self.server, self.rig = server, rig
        self.size = scales(rig)
        sc = server.scene
        # viser's environment map and default lights wash saturated colours out to
        # pastels, which the light floor then swallows: a dim ambient light and one
        # light from above keep a marker's colour and shade it into a sphere
        sc.configure_environment_map(hdri=None)
        sc.configure_default_lights(enabled=False)
        sc.add_light_ambient("/lights/ambient", intensity=0.7)
        sc.add_light_directional("/lights/above", intensity=1.6, position=(1.0, -2.0, 4.0))
        centre, side = draw.floor_extent(rig)
        sc.add_grid("/floor", width=side, height=side, plane="xy", cell_size=0.5,
                    section_size=1.0, position=(float(centre[0]), float(centre[1]), 0.0),
                    cell_color=GRID_CELL_RGB, section_color=GRID_SECTION_RGB,
                    cell_thickness=1.0, section_thickness=1.5, plane_color=FLOOR_RGB,
                    plane_opacity=1.0, shadow_opacity=0.2)
        ax = self.size["world_axes_m"]
        sc.add_frame("/world", axes_length=ax, axes_radius=ax / 40, origin_radius=ax / 20,
                     origin_color=(40, 40, 40))
        for k, name in enumerate("xyz"):
            tip = np.zeros(3)
            tip[k] = ax * 1.08
            sc.add_label(f"/world/{name}", name, position=tuple(tip), font_screen_scale=0.7)
        self.frusta, self.camera_labels, self.states = [], [], []
        waiting = CAMERA_RGB["waiting"]
        for f in draw.camera_frusta(rig):
            self.frusta.append(sc.add_camera_frustum(
                f"/cameras/{f['name']}", fov=float(f["fov"]), aspect=float(f["aspect"]),
                scale=self.size["frustum_m"], thickness=2.5, thickness_units="screen",
                color=waiting, wxyz=f["wxyz"], position=f["position"]))
            self.camera_labels.append(sc.add_label(f"/cameras/{f['name']}/label",
                                                   f["name"], font_screen_scale=0.9))
            self.states.append("waiting")
        self._verts, self._faces = _sphere()
        self.markers = None
        self._capacity = 0
        self.sticks = sc.add_line_segments("/markers/sticks", np.zeros((1, 2, 3), np.float32),
                                           SEGMENT_RGB[0], thickness=self.size["stick_m"],
                                           visible=False)
        self.trails = sc.add_line_segments("/bodies/trails", np.zeros((1, 2, 3), np.float32),
                                           (60, 60, 70), thickness=self.size["stick_m"] / 2,
                                           visible=False)
        self._sticks_n = 0
        self.bodies: dict[int, object] = {}
        self.body_labels: dict[int, object] = {}
        view = initial_view(rig)
        cam = server.initial_camera
        cam.look_at = tuple(view["look_at"].tolist())
        cam.position = tuple(view["position"].tolist())
        cam.up = tuple(view["up"].tolist())
        cam.fov = view["fov_rad"]

    # ---- markers ------------------------------------------------------------------------------

    def _ensure(self, n: int) -> None:
        """A marker mesh with room for n spheres (grown by doubling, never shrunk)."""
        if n <= self._capacity and self.markers is not None:
            return
        cap = max(64, 1 << int(np.ceil(np.log2(max(n, 1)))))
        if self.markers is not None:
            self.markers.remove()
        self.markers = self.server.scene.add_batched_meshes_simple(
            "/markers/spheres", self._verts, self._faces,
            batched_wxyzs=np.tile(np.array([1.0, 0, 0, 0], np.float32), (cap, 1)),
            batched_positions=np.zeros((cap, 3), np.float32),
            batched_scales=np.zeros(cap, np.float32), batched_colors=FREE_RGB,
            lod="off", cast_shadow=False, receive_shadow=False)
        self.markers.batched_colors = np.tile(np.array(FREE_RGB, np.uint8), (cap, 1))
        self._sent_colours = self._sent_scales = None
        self._capacity = cap

    def draw_markers(self, xyz: np.ndarray, colours: np.ndarray, big: np.ndarray) -> None:
        """The markers as spheres (`big`: drawn half as large again, the picked ones)."""
        n = len(xyz)
        self._ensure(n)
        cap = self._capacity
        pos = np.zeros((cap, 3), np.float32)
        pos[:n] = xyz
        col = np.zeros((cap, 3), np.uint8)
        col[:n] = colours
        r = self.size["marker_radius_m"]
        sc = np.zeros(cap, np.float32)
        sc[:n] = np.where(big, 1.5 * r, r)
        self.markers.batched_positions = pos
        # colours and sizes go out only when they change: each change of them makes the
        # browser rebuild the mesh's buffers (in software rendering, a frame's worth of work)
        if self._sent_colours is None or not np.array_equal(col, self._sent_colours):
            self.markers.batched_colors = col
            self._sent_colours = col
        if self._sent_scales is None or not np.array_equal(sc, self._sent_scales):
            self.markers.batched_scales = sc
            self._sent_scales = sc

    def set_sticks(self, colours: np.ndarray) -> None:
        """The marker set's sticks, (P, 3) uint8 colours, sent once: a change of colours
        makes the browser rebuild the lines, a change of their ends does not."""
        self._sticks_n = len(colours)
        if len(colours):
            self.sticks.points = np.zeros((len(colours), 2, 3), np.float32)
            self.sticks.colors = np.repeat(np.asarray(colours, np.uint8)[:, None], 2, axis=1)
        self.sticks.visible = False

    def draw_sticks(self, segments: np.ndarray | None) -> None:
        """(P, 2, 3) the sticks' ends this frame (None: nothing labelled, hidden)."""
        show = segments is not None and len(segments) == self._sticks_n > 0
        self.sticks.visible = show
        if show:
            self.sticks.points = np.asarray(segments, np.float32)

    def draw_trails(self, segments: np.ndarray) -> None:
        self.trails.visible = len(segments) > 0
        if len(segments):
            self.trails.points = segments

    # ---- bodies -------------------------------------------------------------------------------

    def set_bodies(self, bodies: list) -> None:
        """A frame (red, green, blue axes) and a name for each (id, name) body."""
        for h in self.bodies.values():  # its label goes with it
            h.remove()
        self.bodies, self.body_labels = {}, {}
        sc = self.server.scene
        ax = self.size["body_axes_m"]
        for k, (i, name) in enumerate(bodies):
            self.bodies[i] = sc.add_frame(
                f"/bodies/{name}", axes_length=ax, axes_radius=ax / 25,
                origin_radius=ax / 12, origin_color=BODY_RGB[k % len(BODY_RGB)], visible=False)
            self.body_labels[i] = sc.add_label(f"/bodies/{name}/label", name,
                                               position=(0.0, 0.0, ax * 0.5),
                                               font_screen_scale=1.0)

    def draw_bodies(self, ids, valid, position, quaternion) -> None:
        """Each body at its pose (quaternions x, y, z, w as the daemon gives them), hidden
        while it is not tracked."""
        for i, ok, p, q in zip(ids, valid, position, quaternion, strict=True):
            h = self.bodies.get(i)
            if h is None:
                continue
            h.visible = bool(ok)
            if ok:
                h.position = p.astype(np.float64)
                h.wxyz = np.array([q[3], q[0], q[1], q[2]], np.float64)

    # ---- cameras ------------------------------------------------------------------------------

    def draw_camera_states(self, status: dict | None) -> None:
        """Each frustum in its state's colour, its name saying the state when not connected
        (only what changed is sent)."""
        cams = {c["name"]: c for c in (status or {}).get("cameras", [])}
        for k, cam in enumerate(self.rig):
            state = camera_state(cams.get(cam.name)) if status is not None else "waiting"
            if state == self.states[k]:
                continue
            self.states[k] = state
            self.frusta[k].color = CAMERA_RGB[state]
            self.camera_labels[k].text = cam.name if state in ("connected", "waiting") \
                else f"{cam.name}: {state}"
