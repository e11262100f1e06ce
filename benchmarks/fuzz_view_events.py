"""The live view's page events fuzzed in-process: what a crafted websocket client can put in
every widget, click and box (issue 30).

Why in-process: the values a page sends reach the view's handlers through viser, which
casts a widget's new value to its old value's type (`type(old)(new)`: a text field gets
any string, a number field any float, NaN and infinity included) and passes a click's ray,
a box's corners and the browser camera's fields on as they came (any msgpack value). Here
a real viser server holds the real LiveView's widgets (the Bodies and Detection tabs, a
rig of three cameras, a configuration with two bodies) and each input is one event,
delivered as viser delivers it: a widget's value set with viser's cast and its callbacks
run (a button press runs its edit at once, as the view's edit thread would: a UserError
is what the page shows the user, anything else would be a traceback in the log), a click,
or a box selection seen through a browser camera made of the message's fields. An edit
that succeeds writes the configuration; the file is put back after it, so every input
meets the same file. The daemon's control socket is a stand-in that answers `markers`
with the frame's free markers.

`page_events()` gives run_parser (benchmarks/fuzz_parsers.py) its good inputs, a junk
maker and the entry point.
"""

from __future__ import annotations

import atexit
import contextlib
import io
import tempfile
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from calibkit.core.errors import UserError

EDITS: Counter = Counter()  # each edit's outcomes: done (the file written), refused
GOOD_TEXT = ["wand", "probe", "quad 1", "cam0", "cam1", "cam2", "auto", "40", "12.5", "-",
             "drone"]
SPECIAL = ['"', "'", "\\", "\n", "\r", "\t", "\x00", "#", "[", "]", "=", "'''", '"""',
           "\u2028", "\ufeff", "é", "\U0001f600", " ", "nan", "inf", "-1", "1e999", "..", "/"]


def _value(rng, depth: int = 0):
    """Any value a msgpack message can carry."""
    pick = int(rng.integers(0, 12 if depth < 2 else 9))
    if pick == 0:
        return None
    if pick == 1:
        return bool(rng.random() < 0.5)
    if pick == 2:
        return int(rng.choice([0, 1, -1, 3, 2**31, -(2**63), 2**63 - 1, 65536]))
    if pick == 3:
        return float(rng.choice([0.0, -0.0, 1.5, -3.0, 1e308, -1e308, 5e-324, np.nan,
                                 np.inf, -np.inf, 2.0, 50.0, 4000.0, 1e7, 1e7 + 1]))
    if pick == 4:
        return float(rng.normal(0, 10 ** rng.integers(0, 8)))
    if pick in (5, 6):
        return _text(rng)
    if pick == 7:
        return rng.integers(0, 256, int(rng.integers(0, 12)), np.uint8).tobytes()
    if pick == 8:
        return GOOD_TEXT[int(rng.integers(0, len(GOOD_TEXT)))]
    if pick in (9, 10):
        return [_value(rng, depth + 1) for _ in range(int(rng.integers(0, 5)))]
    return {_text(rng)[:8]: _value(rng, depth + 1) for _ in range(int(rng.integers(0, 3)))}


def _text(rng) -> str:
    """A string: a good value changed by specials, random code points, or long."""
    pick = int(rng.integers(0, 4))
    if pick == 0:
        return "".join(chr(int(c)) for c in rng.integers(1, 0x3000, int(rng.integers(0, 20))))
    if pick == 1:
        return "x" * int(rng.integers(15, 400))
    s = list(GOOD_TEXT[int(rng.integers(0, len(GOOD_TEXT)))])
    for _ in range(int(rng.integers(1, 4))):
        s.insert(int(rng.integers(0, len(s) + 1)), SPECIAL[int(rng.integers(0, len(SPECIAL)))])
    return "".join(s)


def _vector(rng, good, n: int):
    """A vector of n floats: the good one with parts changed, or any value."""
    r = rng.random()
    if r < 0.3:
        return _value(rng)
    if r < 0.4:  # nested: one per marker, a column, a vector per component
        return [[list(good)] * int(rng.integers(1, 4)), [[x] for x in good],
                [list(good)] * n][int(rng.integers(0, 3))]
    v = list(good) if r < 0.8 else [float(x) for x in rng.normal(0, 3, n)]
    for _ in range(int(rng.integers(0, 3))):
        k = int(rng.integers(0, n + 1))
        change = int(rng.integers(0, 3))
        if change == 0 and k < len(v):
            v[k] = _value(rng)
        elif change == 1:
            v = v[:k]
        else:
            v.append(_value(rng))
    return v


class _Camera:
    """A browser camera as viser builds it from a ViewerCameraMessage: arrays of the
    message's vectors (np.array: a ragged list is refused there, before the view), its
    fov as sent, the aspect computed when read."""

    def __init__(self, wxyz, position, fov, width, height) -> None:
        self.wxyz, self.position = np.array(wxyz), np.array(position)
        self.fov, self._w, self._h = fov, width, height

    @property
    def aspect(self) -> float:
        return float(self._w) / self._h


CONFIG = """# a rig of three cameras
rig = "rig.toml"
[pipeline]
fps = 30

{cameras}
[[rigid_body]]
name = "wand"  # the calibration wand
id = 1
markers = [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.15, 0.0], [0.0, 0.0, 0.2]]

[[rigid_body]]
name = "probe"
id = 2
markers = [[0.0, 0.0, 0.0], [0.12, 0.0, 0.0], [0.0, 0.07, 0.0], [0.05, 0.05, 0.1]]
"""


def _live_view(folder: Path):
    """A LiveView on a real viser server, set up with a rig, a configuration and a frame
    of 6 free markers (one camera's blobs too)."""
    import viser

    from calibkit.synthetic import sim
    from daemon.config.mocapd import load_config
    from daemon.view.app import LiveView
    from tests.test_natnet import free_ports

    rig = sim.make_rig(3, 4.0, seed=8)
    rig.save(folder / "rig.toml")
    for cam in rig:
        (folder / cam.name).mkdir()
    path = folder / "mocapd.toml"
    path.write_text(CONFIG.format(cameras="".join(
        f'[[camera]]\nname = "{c.name}"\nsource = "{c.name}"\nfps = 30\n\n' for c in rig)))
    cfg = load_config(path)
    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host="127.0.0.1", port=free_ports(1)[0], verbose=False)
    atexit.register(server.stop)
    view = LiveView(server)
    view.setup({"rig": rig, "bodies": [(b.id, b.name) for b in cfg.bodies],
                "runtime_dir": str(folder / "rt"), "config": str(path),
                "cameras": {c.name: {"threshold": c.threshold, "min_area": c.min_area,
                                     "max_area": c.max_area, "mask": None}
                            for c in cfg.cameras},
                "simulated": False, "sticks": None, "segment_of": None, "fps": 30})
    xyz = np.array([[0.5, 0.5, 1.0], [0.6, 0.5, 1.0], [0.5, 0.7, 1.1], [0.4, 0.4, 0.9],
                    [-0.5, 0.2, 1.2], [0.0, -0.6, 0.8]])
    n = len(xyz)
    view.take({"frame": 1, "t_ns": 10**9, "latency_ms": 1.0,
               "cameras": [(0, np.array([[100.0, 200.0], [300.0, 50.5]], np.float32),
                            np.array([9.0, 20.0], np.float32))],
               "track_ids": np.arange(10, 10 + n), "track_xyz": xyz.astype(np.float32),
               "track_seen": np.ones(n, bool), "track_held": np.zeros(n, bool),
               "track_body": np.full(n, -1), "body_ids": np.array([1, 2]),
               "body_valid": np.zeros(2, bool), "body_position": np.zeros((2, 3), np.float32),
               "body_quaternion": np.tile(np.float32([1, 0, 0, 0]), (2, 1))})
    return server, view, path, xyz


def page_events():
    """(good events, a junk maker, the entry point) of the view's page."""
    from daemon.service import live_bodies
    from daemon.view import app

    folder = Path(tempfile.mkdtemp(prefix="fuzz_view_events_"))
    server, view, path, xyz = _live_view(folder)
    original = path.read_text()
    # the daemon's control socket: `markers` answers with the frame's free markers at once
    markers = {"markers": [{"id": 10 + i, "xyz": p.tolist(), "body": False}
                           for i, p in enumerate(xyz)]}
    app.request = lambda rt, req, **kw: markers if req.get("cmd") == "markers" else {}
    live_bodies.time = SimpleNamespace(sleep=lambda s: None)  # 30 answers, no waiting

    def run_edit(action, message):
        """As the view's edit thread runs an edit, at once; the file put back after."""
        try:
            message.content = action()
            EDITS[f"{action.__name__}: done"] += 1
        except UserError as exc:
            message.content = f"**not done**: {exc}"
            EDITS[f"{action.__name__}: refused"] += 1
        finally:
            if path.read_text() != original:
                path.write_text(original)

    view.run_edit = run_edit
    handles = sorted(server.gui._gui_input_handle_from_uuid.values(),
                     key=lambda h: h._impl.uuid)
    eye = np.array([0.5, 0.5, 3.0])
    cam_good = ([0.0, 1.0, 0.0, 0.0], [0.5, 0.5, 3.0], 0.9, 800, 600)  # looking down

    def call(event):
        kind, a, b = event
        if kind == "update":  # viser: the value cast to the old one's type, then callbacks
            handle = handles[a % len(handles)]
            state = handle._impl
            try:
                value = type(state.value)(b)
            except Exception:  # noqa: BLE001 - refused by viser, never reaches the view
                return
            changed = value != state.value
            state.value = value
            if changed or state.is_button:
                for cb in list(state.update_cb):
                    cb(SimpleNamespace(client=None, client_id=0, target=handle))
        elif kind == "click":
            view._on_click(SimpleNamespace(ray_origin=a, ray_direction=b))
        else:
            try:
                camera = _Camera(*a)
            except Exception:  # noqa: BLE001 - refused by viser, never reaches the view
                return
            view._on_rect(SimpleNamespace(client=SimpleNamespace(camera=camera),
                                          screen_min=b[0], screen_max=b[1]))

    buttons = [i for i, h in enumerate(handles) if h._impl.is_button]
    fields = [i for i, h in enumerate(handles) if not h._impl.is_button]
    good = [("click", eye.tolist(), (p - eye).tolist()) for p in xyz[:4]]
    good += [("rect", cam_good, ((0.0, 0.0), (1.0, 1.0))),
             ("rect", cam_good, ((0.4, 0.4), (0.6, 0.6)))]
    good += [("update", i, GOOD_TEXT[k % len(GOOD_TEXT)]) for k, i in enumerate(fields)]
    good += [("update", i, True) for i in buttons]

    def junk(rng):
        r = rng.random()
        if r < 0.1:  # a good event between the bad: picks add up, a body can be made
            return good[int(rng.integers(0, len(good)))]
        if r < 0.5:
            i = int(rng.integers(0, len(handles)))
            if i in buttons:
                return "update", i, True if rng.random() < 0.8 else _value(rng)
            r = rng.random()  # a good value a third of the time: the edits go further
            v = GOOD_TEXT[int(rng.integers(0, len(GOOD_TEXT)))] if r < 0.3 else \
                _text(rng) if r < 0.6 else _value(rng)
            return "update", i, v
        if r < 0.77:
            p = xyz[int(rng.integers(0, len(xyz)))]
            return "click", _vector(rng, eye, 3), _vector(rng, p - eye, 3)
        c = [_vector(rng, cam_good[0], 4), _vector(rng, cam_good[1], 3)]
        c += [_value(rng) if rng.random() < 0.3 else v for v in cam_good[2:]]
        lo, hi = sorted(rng.random(2)), sorted(rng.random(2))
        return "rect", c, (_vector(rng, [lo[0], hi[0]], 2), _vector(rng, [lo[1], hi[1]], 2))

    return good, junk, call
