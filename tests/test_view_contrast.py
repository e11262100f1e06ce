"""The live view's 3D scene read back from the picture a browser draws, not the page state.

The view process (daemon.view.app) is fed one frame made from the simulator's truth: a
walking person labelled with its marker set, two rigid bodies on their markers and two
free markers, with a stand-in for the daemon's control socket whose `status` says one
camera dropped out and one gives no frames. Headless Chromium renders the page; each
marker's and axis's true position is projected through the page's first view, and the
screenshot must hold the marker's colour there, standing out from the floor (a colour
difference, CIE76 in Lab, above CONTRAST_MIN), each body's and the world's red, green and
blue axes, and each camera in its state's colour.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import socket
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from browser import CHROMIUM, Browser

pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium package "
                                "(.ci/run installs it)")
IMAGES = Path(__file__).resolve().parents[1] / "docs" / "images"
CONTRAST_MIN = 35.0  # Lab colour difference, marker against floor (2.3: just noticeable)
DROPPED, NO_FRAMES = "cam5", "cam6"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _frame_from_truth():
    """(desc without runtime dir, frame, truth): one instant of the simulator's scene as
    the daemon would hand it to the view, and the truth that made it."""
    from calibkit.synthetic import person, sim
    from daemon.labelling.markerset import MarkerSet
    from daemon.view.draw import markerset_segments, markerset_sticks

    rig = sim.make_rig(8, 4.0, size=(640, 480), seed=0)
    ms = MarkerSet.load(Path(__file__).resolve().parents[1] / "daemon" / "labelling" / "sets"
                        / "sim_person.toml")
    walker = person.walk_circle(600, 120.0, radius_m=1.0)
    _, bodies = sim.rigid_body_motion(2, 600, 120.0, 4.0, 4, seed=1)
    # the instant the bodies are furthest from each other and from the person: each
    # marker has its place in the picture (which markers hide which is not the question)
    centres = np.stack([b.poses[:, :3, 3] for b in bodies], 1)  # (F, 2, 3)
    apart = np.minimum(np.linalg.norm(centres[:, 0] - centres[:, 1], axis=1),
                       np.linalg.norm(centres - walker.markers_m.mean(axis=1)[:, None],
                                      axis=2).min(axis=1))
    k = int(np.argmax(apart))
    lab_xyz = walker.markers_m[k]
    lab_idx = np.array([ms.labels.index(n) for n in walker.labels])
    body_xyz = [np.einsum("ij,kj->ki", b.poses[k, :3, :3], b.markers_body) + b.poses[k, :3, 3]
                for b in bodies]
    free_xyz = np.array([[1.2, 1.0, 0.4], [-1.0, 1.3, 1.5]])
    # the tracker's view: every marker a track; the person's also labelled by the set
    xyz = np.concatenate([*body_xyz, free_xyz, lab_xyz])
    ids = np.arange(len(xyz)) + 100
    nb = sum(len(b) for b in body_xyz)
    quat = [np.roll(_wxyz(b.poses[k, :3, :3]), -1) for b in bodies]  # x, y, z, w
    frame = {"frame": 1, "t_ns": 0, "latency_ms": 1.0, "cameras": [],
             "track_ids": ids, "track_xyz": xyz.astype(np.float32),
             "track_seen": np.ones(len(ids), bool),
             "track_held": np.arange(len(ids)) < nb,
             "track_body": np.where(np.arange(len(ids)) < nb, np.arange(len(ids)) // 4, -1),
             "body_ids": np.array([b.id for b in bodies]),
             "body_valid": np.ones(len(bodies), bool),
             "body_position": np.array([b.poses[k, :3, 3] for b in bodies], np.float32),
             "body_quaternion": np.array(quat, np.float32),
             "labelled_index": lab_idx, "labelled_xyz": lab_xyz.astype(np.float32)}
    desc = {"rig": rig, "bodies": [(b.id, b.name) for b in bodies], "config": None,
            "cameras": {}, "simulated": True, "sticks": markerset_sticks(ms),
            "segment_of": markerset_segments(ms), "fps": 120.0}
    truth = {"rig": rig, "bodies": bodies, "body_xyz": body_xyz, "free_xyz": free_xyz,
             "lab_xyz": lab_xyz, "lab_segment": np.array(markerset_segments(ms))[lab_idx],
             "k": k}
    return desc, frame, truth


def _wxyz(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def _status(rig) -> dict:
    """The daemon's `status` answer: every camera at 120 fps but one dropped out and one
    connected with no frames."""
    cams = []
    for cam in rig:
        cams.append({"name": cam.name, "connected": cam.name != DROPPED,
                     "rate_hz": 0.0 if cam.name in (DROPPED, NO_FRAMES) else 120.0,
                     "frames": 100, "dropped": 0, "failures": 0})
    return {"ok": True, "rate_hz": 120.0, "frames": 100, "latency": {"median_ms": 1.0},
            "cameras": cams, "bodies": []}


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    """The view process fed the frame, a stand-in control socket, a browser on the page,
    and the screenshot once the page shows the frame and the cameras' states."""
    from daemon.service.control import ControlServer
    from daemon.view.app import main

    desc, frame, truth = _frame_from_truth()
    rt = tmp_path_factory.mktemp("view-rt")
    control = ControlServer(rt, lambda req: _status(desc["rig"]))
    control.open()
    port = _free_port()
    ctx = mp.get_context("spawn")
    conn, child = ctx.Pipe()
    proc = ctx.Process(target=main, args=(child, "127.0.0.1", port), daemon=True)
    proc.start()
    child.close()
    browser = None
    try:
        assert conn.poll(60) and conn.recv() == {"ready": True}
        conn.send({"setup": {**desc, "runtime_dir": str(rt)}})
        conn.send({"frame": frame})
        browser = Browser()
        browser.open(f"http://127.0.0.1:{port}")
        assert browser.wait_for("document.body && document.body.innerText"
                                ".includes('frame 1:')", 120), browser.text()[:300]
        _close_notices(browser)
        yield {"browser": browser, "truth": truth, "desc": desc, "image": _settled(browser)}
    finally:
        if browser is not None:
            browser.close()
        try:
            conn.send({"stop": True})
        except OSError:
            pass
        proc.join(10)
        if proc.is_alive():
            proc.terminate()
        control.close()


def _project(xyz, view: dict, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """World points to the page's pixels through its first view (a pinhole looking from
    `position` at `look_at`, vertical field of view `fov_rad`), and their depths."""
    pos, at, up = (np.asarray(view[k], float) for k in ("position", "look_at", "up"))
    fwd = (at - pos) / np.linalg.norm(at - pos)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    p = (np.asarray(xyz, float).reshape(-1, 3) - pos) @ np.stack([right, down, fwd], 1)
    f_px = height / 2 / np.tan(view["fov_rad"] / 2)
    uv = np.stack([width / 2 + f_px * p[:, 0] / p[:, 2], height / 2 + f_px * p[:, 1] / p[:, 2]], 1)
    return uv, p[:, 2]


def _screenshot(b: Browser) -> np.ndarray:
    return cv2.cvtColor(cv2.imdecode(np.frombuffer(b.screenshot(), np.uint8),
                                     cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def _settled(b: Browser, timeout_s: float = 180.0) -> np.ndarray:
    """The page as RGB once two screenshots a second apart agree (the scene has faded in
    and every node is drawn: the browser renders in software, slowly when loaded)."""
    deadline = time.monotonic() + timeout_s
    last = _screenshot(b)
    while True:
        time.sleep(1.0)
        img = _screenshot(b)
        if np.abs(img.astype(int) - last).mean() < 0.2 or time.monotonic() > deadline:
            return img
        last = img




def _close_notices(b: Browser) -> None:
    """Close viser's notices (software WebGL rendering: this browser's case) so that they
    do not cover the scene; a page without any is left as it is."""
    b.js("""[...document.querySelectorAll('button')].filter(e => e.closest(
        '.mantine-Notification-root, [class*=Notification]')).forEach(e => e.click())""")


def _lab(rgb) -> np.ndarray:
    """RGB (..., 3) uint8 to CIE Lab (L 0-100), float."""
    rgb = np.asarray(rgb, np.float32).reshape(-1, 1, 3) / 255.0
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2Lab).reshape(-1, 3)


def _hue_deg(rgb) -> np.ndarray:
    hsv = cv2.cvtColor(np.asarray(rgb, np.uint8).reshape(-1, 1, 3), cv2.COLOR_RGB2HSV_FULL)
    return hsv.reshape(-1, 3)[:, 0] * 360.0 / 256.0


def _scene_area(b: Browser, img: np.ndarray) -> np.ndarray:
    """Where the 3D view shows on the page: not under the control panel."""
    panel = b.js("""(() => { const e = [...document.querySelectorAll('div')].find(d =>
        d.innerText && d.innerText.startsWith('mocapd') && d.getBoundingClientRect().width
        < window.innerWidth / 2); return e ? e.getBoundingClientRect().left : null; })()""")
    free = np.zeros(img.shape[:2], bool)
    free[:, : int(panel or img.shape[1] * 0.7) - 4] = True
    return free


def _markers(truth, view, img):
    """Every marker's truth with its expected colour: (uv px, radius px, rgb, group)."""
    from daemon.view.scene import BODY_RGB, FREE_RGB, SEGMENT_RGB, scales

    r_m = scales(truth["rig"])["marker_radius_m"]
    rows = [(truth["lab_xyz"], [SEGMENT_RGB[s % len(SEGMENT_RGB)] for s in
                                truth["lab_segment"]], "labelled")]
    for j, xyz in enumerate(truth["body_xyz"]):
        rows.append((xyz, [BODY_RGB[j]] * len(xyz), "body"))
    rows.append((truth["free_xyz"], [FREE_RGB] * len(truth["free_xyz"]), "free"))
    out = []
    for xyz, rgb, group in rows:
        uv, depth = _project(xyz, view, img.shape[1], img.shape[0])
        f_px = img.shape[0] / 2 / np.tan(view["fov_rad"] / 2)
        for p, d, c in zip(uv, depth, rgb, strict=True):
            out.append((p, f_px * r_m / d, np.array(c), group))
    return out


def _floor_rgb(truth, view, img, area) -> np.ndarray:
    """The floor's colour as drawn: the median over the middles of its grid cells in
    sight (away from grid lines), far from every marker."""
    from daemon.view.draw import floor_extent

    centre, side = floor_extent(truth["rig"])
    g = np.arange(-side / 2 + 0.25, side / 2, 0.5)
    gx, gy = np.meshgrid(g + centre[0], g + centre[1])
    pts = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    uv, depth = _project(pts, view, img.shape[1], img.shape[0])
    ij = uv.round().astype(int)
    ok = (depth > 0) & (ij[:, 0] >= 0) & (ij[:, 0] < img.shape[1]) & (ij[:, 1] >= 0) \
        & (ij[:, 1] < img.shape[0])
    ij = ij[ok]
    ij = ij[area[ij[:, 1], ij[:, 0]]]
    return np.median(img[ij[:, 1], ij[:, 0]].astype(float), axis=0)


def test_markers_are_bright_spheres_in_their_colours_standing_out_from_a_light_floor(page):
    from daemon.view.scene import initial_view

    b, truth, img = page["browser"], page["truth"], page["image"]
    if os.environ.get("MOCAPD_VIEW_SCREENSHOTS"):  # the docs' picture of the 3D view
        small = cv2.resize(img[:, : img.shape[1] * 5 // 7], None, fx=0.75, fy=0.75,
                           interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(IMAGES / "view-scene.png"), cv2.cvtColor(small, cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_PNG_COMPRESSION, 9])
    view = initial_view(truth["rig"])
    area = _scene_area(b, img)
    floor = _floor_rgb(truth, view, img, area)
    assert _lab(floor)[0, 0] > 70, floor  # a light floor
    seen, found, contrast = {}, {}, []
    for (u, v), r_px, rgb, group in _markers(truth, view, img):
        if not (r_px < u < img.shape[1] - r_px and r_px < v < img.shape[0] - r_px
                and area[int(v), int(u)]):
            continue
        # big enough to be seen: a sphere at least 8 px across from where the page looks
        assert r_px >= 4.0, (group, r_px)
        seen[group] = seen.get(group, 0) + 1
        yy, xx = np.mgrid[-int(r_px):int(r_px) + 1, -int(r_px):int(r_px) + 1]
        inner = yy ** 2 + xx ** 2 <= (0.6 * r_px) ** 2
        px = img[int(round(v)) + yy[inner], int(round(u)) + xx[inner]]
        med = np.median(px.astype(float), axis=0)
        dhue = abs((_hue_deg(med)[0] - _hue_deg(rgb)[0] + 180) % 360 - 180)
        sat = (med.max() - med.min()) / max(med.max(), 1)
        if dhue < 25 and sat > 0.3:  # the marker's own colour, shaded, is there
            found[group] = found.get(group, 0) + 1
            contrast.append(float(np.linalg.norm(_lab(med) - _lab(floor))))
    # every kind drawn; most markers in sight show their colour (a few hide behind
    # others, or behind a body's axes)
    assert seen.get("labelled", 0) >= 30 and seen.get("body", 0) >= 6 and \
        seen.get("free", 0) >= 1, seen
    for group, n in seen.items():
        assert found.get(group, 0) >= 0.75 * n, (group, found, seen)
    assert sum(found.values()) >= 0.85 * sum(seen.values()), (found, seen)
    # and they stand out from the floor: nearly all of them by far more than a just
    # noticeable difference
    print(f"markers in sight {seen}, in their colour {found}; contrast to the floor "
          f"(Lab difference) 10th percentile {np.percentile(contrast, 10):.1f}, median "
          f"{np.median(contrast):.1f}; floor RGB {floor.round().astype(int).tolist()}")
    assert np.percentile(contrast, 10) >= CONTRAST_MIN, sorted(contrast)[:8]


def _axis_colour_near(img, uv, k: int, radius_px: int = 4) -> bool:
    """Whether a pixel near uv is the axis colour k (0 red, 1 green, 2 blue): that channel
    well above the other two."""
    u, v = (int(round(c)) for c in uv)
    if not (radius_px <= u < img.shape[1] - radius_px and
            radius_px <= v < img.shape[0] - radius_px):
        return False
    win = img[v - radius_px:v + radius_px + 1, u - radius_px:u + radius_px + 1].astype(int)
    others = np.delete(win, k, axis=2)
    return bool(((win[..., k] - others.max(axis=2)) > 60).any())


def test_world_and_body_axes_are_red_green_blue(page):
    from daemon.view.scene import initial_view, scales

    truth, img = page["truth"], page["image"]
    view = initial_view(truth["rig"])
    size = scales(truth["rig"])
    k = truth["k"]
    frames = [(np.eye(3), np.zeros(3), size["world_axes_m"], "world")]
    frames += [(b.poses[k, :3, :3], b.poses[k, :3, 3], size["body_axes_m"], b.name)
               for b in truth["bodies"]]
    missing, checked = [], 0
    for R, t, length, name in frames:
        for axis in range(3):
            # along the axis, past the body's own markers, short of its tip
            pts = t + np.outer([0.0, 0.55, 0.7, 0.85], R[:, axis] * length)
            uv, _ = _project(pts, view, img.shape[1], img.shape[0])
            if np.linalg.norm(uv[-1] - uv[0]) < 20:
                continue  # pointing at or away from the page: too short to be seen
            checked += 1
            if not any(_axis_colour_near(img, p, axis) for p in uv[1:]):
                missing.append((name, "xyz"[axis]))
    assert checked >= 7 and not missing, (checked, missing)


def test_cameras_are_drawn_in_their_state_colours(page):
    from daemon.view.draw import camera_frusta
    from daemon.view.scene import CAMERA_RGB, camera_state, initial_view, scales

    b, truth, img = page["browser"], page["truth"], page["image"]
    view = initial_view(truth["rig"])
    area = _scene_area(b, img)
    scale = scales(truth["rig"])["frustum_m"]
    status = {c["name"]: c for c in _status(truth["rig"])["cameras"]}
    checked = {}
    for cam, f in zip(truth["rig"], camera_frusta(truth["rig"]), strict=True):
        # the frustum's far rectangle as viser draws it (the volume of the pyramid scaled)
        y = np.tan(f["fov"] / 2)
        x, z = y * f["aspect"], 1.0
        vs = np.cbrt(x * y * z / 3.0)
        corners = np.array([[sx * x, sy * y, z] for sx, sy in
                            ((-1, -1), (1, -1), (1, 1), (-1, 1))]) / vs * scale
        mids = (corners + np.roll(corners, 1, axis=0)) / 2
        pts = np.concatenate([corners, mids, mids / 2]) @ cam.R + cam.centre
        uv, depth = _project(pts, view, img.shape[1], img.shape[0])
        ij = uv.round().astype(int)
        ok = (depth > 0) & (ij[:, 0] >= 3) & (ij[:, 0] < img.shape[1] - 3) & \
            (ij[:, 1] >= 3) & (ij[:, 1] < img.shape[0] - 3)
        ok[ok] = area[ij[ok, 1], ij[ok, 0]]
        if ok.sum() < 6:
            continue  # mostly out of sight from the page's first view
        want = np.array(CAMERA_RGB[camera_state(status[cam.name])])
        hits = 0
        for i, j in ij[ok]:
            win = img[j - 3:j + 4, i - 3:i + 4].reshape(-1, 3).astype(int)
            hits += bool((np.abs(win - want).max(axis=1) < 60).any())
        checked[cam.name] = (camera_state(status[cam.name]), hits, int(ok.sum()))
    assert DROPPED in checked and NO_FRAMES in checked, checked
    for name, (state, hits, n) in checked.items():
        assert hits >= n // 2, (name, state, hits, n, checked)
