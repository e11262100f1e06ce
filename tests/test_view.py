"""The live view's pure parts: --view addresses, thumbnails, picking, body edits in the
configuration file. (The page itself, in a browser: tests/test_view_browser.py.)"""

from __future__ import annotations

import numpy as np
import pytest

from calibkit.clitools import parse_view
from calibkit.core.errors import UserError
from daemon.config.mocapd import load_config
from daemon.view import bodies, draw


def test_view_address_is_loopback_unless_told():
    assert parse_view("8080") == ("127.0.0.1", 8080)
    assert parse_view("0.0.0.0:9000") == ("0.0.0.0", 9000)
    for bad in ("localhost:80", "8080x", "127.0.0.1:70000", ""):
        with pytest.raises(UserError, match="--view"):
            parse_view(bad)


def test_thumbnail_draws_each_blob_where_it_is_scaled():
    uv = np.array([[100.0, 100.0], [500.0, 300.0]])
    img = draw.thumbnail((640, 480), uv, np.array([30.0, 30.0]), threshold=40)
    assert img.shape == (180, 240, 3)
    s = 240 / 640
    for x, y in uv * s:
        assert img[round(y), round(x)].min() > 200  # a white disc at each blob
    assert img[10, 120].max() < 30  # dark elsewhere


def test_picking_by_ray_and_by_rectangle_agree_with_the_camera_model():
    """A camera looking at points: the ray through a point's pixel picks it; a rectangle
    around its projection (computed as calibkit's Camera projects) holds it alone."""
    from calibkit.synthetic import sim

    rig = sim.make_rig(4, 4.0, seed=2)
    cam = rig[0]
    rng = np.random.default_rng(1)
    pts = np.array([2.0, 2.0, 1.0]) + rng.uniform(-0.8, 0.8, (20, 3))
    f = draw.camera_frusta(rig)[0]
    uv_screen, front = draw.project_to_screen(pts, f["position"], f["wxyz"], f["fov"],
                                              f["aspect"])
    px, _ = cam.project(pts)
    # viser's camera has no distortion and a centred principal point: compare loosely
    ideal = cam.to_camera(pts)
    ideal = ideal[:, :2] / ideal[:, 2:]
    want = np.stack([0.5 + ideal[:, 0] * cam.K[1, 1] / cam.width,
                     0.5 + ideal[:, 1] * cam.K[1, 1] / cam.height], axis=1)
    np.testing.assert_allclose(uv_screen, want, atol=1e-9)
    assert front.all() and px.shape == (20, 2)
    k = 7
    d = pts[k] - f["position"]
    assert draw.pick_by_ray(pts, f["position"] + 0.0, d + rng.normal(0, 1e-4, 3)) == k
    lo, hi = uv_screen[k] - 1e-4, uv_screen[k] + 1e-4
    assert draw.pick_in_rect(pts, f["position"], f["wxyz"], f["fov"], f["aspect"], lo,
                             hi).tolist() == [k]
    assert draw.pick_by_ray(pts, f["position"], -d) == -1  # behind the camera: nothing


CONFIG = """# my rig
[sim]
cameras = 6  # six of them

[[rigid_body]]
name = "probe"   # the pointer
id = 1
markers = [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.08, 0.0], [0.0, 0.0, 0.05]]

[[rigid_body]]
name = "drone"
id = 2
markers = [
    [0.0, 0.0, 0.0],
    [0.12, 0.0, 0.0],
    [0.0, 0.15, 0.0],
    [0.03, 0.0, 0.09],
]
"""


def test_rename_and_remove_edit_one_table_and_keep_the_rest(tmp_path):
    path = tmp_path / "m.toml"
    path.write_text(CONFIG)
    bodies.rename_body(path, "drone", "quad 1")
    text = path.read_text()
    assert text == CONFIG.replace('name = "drone"', 'name = "quad 1"')
    assert [b.name for b in load_config(path).bodies] == ["probe", "quad 1"]
    bodies.remove_body(path, "probe")
    text = path.read_text()
    assert text.startswith("# my rig\n[sim]\ncameras = 6  # six of them\n")
    assert "probe" not in text and [b.name for b in load_config(path).bodies] == ["quad 1"]
    for call, match in ((lambda: bodies.remove_body(path, "nope"), "no rigid body"),
                        (lambda: bodies.rename_body(path, "quad 1", 'a"b'), "quotes"),
                        (lambda: bodies.rename_body(None, "a", "b"), "--config")):
        with pytest.raises(UserError, match=match):
            call()
    assert path.read_text() == text  # refused: nothing written


def test_add_picked_refuses_what_cannot_make_a_body(tmp_path):
    path = tmp_path / "m.toml"
    path.write_text(CONFIG)
    with pytest.raises(UserError, match="exists already"):
        bodies.add_picked(path, "probe", [1, 2, 3], lambda: {"markers": []})
    with pytest.raises(UserError, match="3 to 8"):
        bodies.add_picked(path, "new", [1, 2], lambda: {"markers": []})
    assert path.read_text() == CONFIG


def test_add_picked_follows_a_picked_marker_whose_track_was_found_again(tmp_path):
    """Two picked tracks are lost and found again under new ids (a loaded machine skipping
    frame sets), before the capture or during it: the markers where they were stand for
    them, a free marker 5 cm away does not, and the body has its true shape."""
    path = tmp_path / "m.toml"
    rng = np.random.default_rng(3)
    shape = np.array([[0, 0, 0], [0.08, 0, 0], [0, 0.06, 0], [0.03, 0.03, 0.05]]) + 1.0
    calls = []

    def asker(found_again_at: int):
        def ask():
            k = len(calls)
            calls.append(k)
            ids = [7, 8, 9, 10] if k < found_again_at else [7, 8, 31, 32]
            xyz = shape + rng.normal(0, 0.0002, shape.shape)
            out = [{"id": i, "xyz": x.tolist(), "body": None}
                   for i, x in zip(ids, xyz, strict=True)]
            return {"markers": out + [{"id": 40, "xyz": [1.05, 1.0, 1.0], "body": None}]}
        return ask

    picked_at = dict(zip([7, 8, 9, 10], shape, strict=True))
    d_true = np.sort(np.linalg.norm(shape[:, None] - shape[None], axis=2).ravel())
    for found_again_at, at in ((0, picked_at), (10, None)):  # where picked; where first seen
        path.write_text(CONFIG)
        calls.clear()
        body_id, n = bodies.add_picked(path, "new", [7, 8, 9, 10], asker(found_again_at),
                                       at=at)
        assert n == 4 and len(calls) == 30
        got = next(b for b in load_config(path).bodies if b.name == "new")
        assert got.id == body_id
        d_got = np.linalg.norm(got.markers[:, None] - got.markers[None], axis=2)
        np.testing.assert_allclose(np.sort(d_got.ravel()), d_true, atol=5e-4)
    # lost before the capture, and where they were picked not given: by ids alone, no body
    path.write_text(CONFIG)
    with pytest.raises(UserError, match="three markers"):  # 2 in each frame
        bodies.add_picked(path, "new", [7, 8, 9, 10], asker(0))
    with pytest.raises(UserError, match="none of the picked markers"):  # every one lost
        bodies.add_picked(path, "new", [9, 10, 11], asker(0))
    assert path.read_text() == CONFIG
