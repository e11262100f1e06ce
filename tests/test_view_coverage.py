"""`calibkit wand --view`: each camera's wand coverage filling in on a page, in headless
Chromium, against the capture monitor that decides when a camera has enough."""

from __future__ import annotations

import contextlib
import json
import re
import socket
import time

import numpy as np
import pytest
from browser import CHROMIUM, Browser

from calibkit.calibrate.wand import CaptureMonitor, WandSpec, identify
from calibkit.commands.coverage_view import CoverageView, coverage_image

SPACING = (0.0, 0.2, 0.5)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_coverage_image_marks_the_visited_cells():
    cells = np.zeros((6, 8), bool)
    cells[2, 3] = cells[5, 7] = True
    img = coverage_image(cells, (640, 480), False)
    assert img.shape == (180, 240, 3)
    cw, ch = 240 / 8, 180 / 6
    for y in range(6):
        for x in range(8):
            px = img[int((y + 0.5) * ch), int((x + 0.5) * cw)]
            assert (px[1] > 150) == cells[y, x]


@pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium package "
                    "(.ci/run installs it)")
def test_the_page_fills_in_as_the_wand_is_waved():
    from calibkit.synthetic import sim

    rig = sim.make_rig(4, 4.0, seed=3)
    truth = sim.wand_motion(600, 100.0, 4.0, SPACING, seed=3)
    obs = sim.observe(rig, truth, noise_px=0.1, fps=100.0, seed=3)
    spec = WandSpec(SPACING)
    monitor = CaptureMonitor(rig.names, [c.size for c in rig], 400, 0.5)
    port = _free_port()
    view = CoverageView("127.0.0.1", port, monitor)
    # the wand waved in 10 batches of 60 frames; after each, the page is read once it shows
    # that batch (the view redraws at most REDRAW_HZ times a second, so the batch is offered
    # again until it is drawn): each state the page showed is the monitor's at that batch
    batches = [obs.select(obs.frame // 60 == k) for k in range(10)]

    b = Browser(1200, 1400)
    try:
        b.open(f"http://127.0.0.1:{port}")
        assert b.wait_for("document.body && document.body.innerText.includes('cam3')", 60)
        seen = []
        for k, batch in enumerate(batches):
            monitor.add(identify(batch, spec, rig))
            frames, final = 60 * (k + 1), k == len(batches) - 1
            shown = f"): {frames} frames"  # the head line: "(capturing): N frames"
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                view.update(monitor, frames, final=final)
                if b.wait_for(f"document.body.innerText.includes({shown!r})", 0.3, 0.05):
                    break
            m = re.search(r"cam0: (\d+) sightings", b.text())
            assert m and int(m.group(1)) == int(monitor.samples[0]), (k, b.text())
            seen.append(int(m.group(1)))
        assert len(set(seen)) >= 3 and seen == sorted(seen), seen  # it filled in, live
        assert b.wait_for("document.body.innerText.includes('(captured)')", 10)
        text = b.text()
        for c, name in enumerate(rig.names):
            want = (f"{name}: {int(monitor.samples[c])} sightings of 400, "
                    f"{100 * monitor.coverage[c]:.0f} % covered of 50 %")
            assert want in text, (want, text)
        # each thumbnail's cells, read back from the picture the browser shows
        grids = b.js(f"""(() => {{
            const imgs = [...document.querySelectorAll('img')]
                .filter(i => i.complete && i.naturalWidth === 240);
            return imgs.map(img => {{
                const c = document.createElement('canvas');
                c.width = img.naturalWidth; c.height = img.naturalHeight;
                const g = c.getContext('2d'); g.drawImage(img, 0, 0);
                const out = [];
                for (let y = 0; y < {monitor.gy}; y++) {{ const row = [];
                    for (let x = 0; x < {monitor.gx}; x++) {{
                        const p = g.getImageData(Math.floor((x + 0.5) * c.width / {monitor.gx}),
                            Math.floor((y + 0.5) * c.height / {monitor.gy}), 1, 1).data;
                        row.push(p[1] > 150); }}
                    out.push(row); }}
                return out; }}); }})()""")
        assert len(grids) == len(rig)
        for c in range(len(rig)):
            assert np.array_equal(np.array(grids[c]), monitor.cells[c]), c
        assert monitor.cells.any(axis=(1, 2)).all()
    finally:
        b.close()
        view.close()


def test_view_needs_a_capture(calibkit_cli, tmp_path):
    (tmp_path / "w.mcrec").write_text("")
    for extra, words in ((["--from", tmp_path / "w.mcrec", "--view", "8080"], "--from reads"),
                         (["--sim", "--view", "localhost:1"], "--view: expected")):
        r = calibkit_cli("wand", "--out", tmp_path / "o.toml", "--intrinsics",
                         tmp_path / "i.toml", *extra)
        assert r.code == 2 and words in r.err and len(r.err.strip().splitlines()) == 1, r.err


@pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium package "
                    "(.ci/run installs it)")
def test_intrinsic_views_page_shows_each_views_dots_and_the_coverage():
    """`calibkit intrinsic --view`: after each view the page shows the views so far, their
    dot counts, the coverage figure the solve reports and the cells it counts."""
    from calibkit.calibrate.intrinsic import PlaneView, coverage
    from calibkit.commands.coverage_view import IntrinsicView
    from calibkit.synthetic import sim

    cam = sim.make_rig(2, 4.0, seed=1)[0]
    rng = np.random.default_rng(2)
    views = []
    for k, shift in enumerate((-0.35, 0.0, 0.35)):  # a grid held left, centre, right
        g = np.stack(np.meshgrid(np.linspace(-0.3, 0.3, 12), np.linspace(-0.2, 0.2, 9)),
                     -1).reshape(-1, 2)
        pts = np.column_stack([g[:, 0] + shift, g[:, 1], np.full(len(g), 1.2)])
        world = (pts - cam.t) @ cam.R  # camera frame -> world
        uv, _ = cam.project(world)
        uv = uv + rng.normal(0, 0.05, uv.shape)
        views.append(PlaneView(np.column_stack([g, np.zeros(len(g))]), uv, f"view{k + 1}"))
    port = _free_port()
    page = IntrinsicView("127.0.0.1", port)
    b = Browser(1200, 1000)
    try:
        b.open(f"http://127.0.0.1:{port}")
        assert b.wait_for("document.body && document.body.innerText.includes('intrinsic')", 30)
        for n in (1, 2, 3):
            page.show(cam.name, cam.size, views[:n], 4)
            uv = np.concatenate([v.uv for v in views[:n]])
            want = (f"{cam.name}: {n} of 4 views, dots per view "
                    + ", ".join(str(len(v.uv)) for v in views[:n])
                    + f"; image coverage {100 * coverage(uv, cam.size):.0f} %")
            assert b.wait_for(f"document.body.innerText.includes({want!r})", 15), b.text()
        assert "next:" in b.text()  # what to do for the fourth view
        cells = b.js("""(() => { const img = [...document.querySelectorAll('img')]
            .find(i => i.complete && i.naturalWidth === 240);
            const c = document.createElement('canvas');
            c.width = img.naturalWidth; c.height = img.naturalHeight;
            const g = c.getContext('2d'); g.drawImage(img, 0, 0);
            const d = g.getImageData(0, 0, c.width, c.height).data, out = [];
            for (let y = 0; y < 6; y++) { const row = [];
                for (let x = 0; x < 8; x++) { let green = 0;
                    for (let v = Math.floor(y * c.height / 6) + 2;
                         v < Math.floor((y + 1) * c.height / 6) - 1; v++)
                        for (let u = Math.floor(x * c.width / 8) + 2;
                             u < Math.floor((x + 1) * c.width / 8) - 1; u++) {
                            const i = 4 * (v * c.width + u);
                            if (d[i] === 30 && d[i + 1] === 80 && d[i + 2] === 45) green++; }
                    row.push(green > 0); }
                out.push(row); }
            return out; })()""")
        uv = np.concatenate([v.uv for v in views])
        want = np.zeros((6, 8), bool)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & \
            (uv[:, 1] < cam.height)
        want[(uv[inside, 1] / cam.height * 6).astype(int),
             (uv[inside, 0] / cam.width * 8).astype(int)] = True
        assert np.array_equal(np.array(cells), want)
        assert want.mean() == pytest.approx(coverage(uv[inside], cam.size))
    finally:
        b.close()
        page.close()


@pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium package "
                    "(.ci/run installs it)")
def test_intrinsic_display_view_shows_the_views_before_each_prompt(calibkit_cli, monkeypatch,
                                                                   tmp_path):
    """`calibkit intrinsic --display --view PORT` end to end, the window and the camera
    replaced by the simulator as in test_intrinsic: at each "hold the monitor" prompt a
    browser on the page finds the views taken so far, and at the end all of them with the
    coverage the command prints."""
    import builtins

    import calibkit.cameras
    import projector.display
    import projector.screens
    from calibkit.cameras import Frame
    from calibkit.synthetic.monitor import MonitorSimConfig, make_monitor_sim
    from projector.screens import Screen

    config = MonitorSimConfig(screen_px=(960, 540), pixel_pitch_mm=0.543)
    sim = make_monitor_sim(3, (320, 240), 0, config)

    class FakeCamera:
        def __init__(self, spec, name=None):
            self.camera = name

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            sim.close()

        def __iter__(self):
            i = 0
            while True:
                yield Frame(self.camera, i, i, np.dstack([sim.grab()] * 3))
                i += 1

    class FakeWindow:
        def __init__(self, monitor):
            pass

        def show(self, dots):
            sim.show(dots)

        def close(self):
            pass

    port = _free_port()
    b = Browser(1200, 1000)
    seen = []

    def prompt(text=""):  # the user looks at the page, then tilts the monitor
        v = len(seen)
        if v == 0:
            b.open(f"http://127.0.0.1:{port}")
        ok = b.wait_for(f"document.body && document.body.innerText.includes("
                        f"'cam0: {v} of 3 views')", 30)
        seen.append(bool(ok))
        sim.set_view(v)

    screen = Screen(0, "sim", *config.screen_px, 0.0, 0.0)
    monkeypatch.setattr(projector.screens, "require_display", lambda: None)
    monkeypatch.setattr(projector.screens, "pick_screen",
                        lambda index, pitch: (screen, config.pixel_pitch_mm))
    monkeypatch.setattr(calibkit.cameras, "open_camera", FakeCamera)
    monkeypatch.setattr(projector.display, "WindowDisplay", FakeWindow)
    monkeypatch.setattr(builtins, "input", prompt)
    # the page closes with the command: keep it up to look at the last state
    from calibkit.commands import coverage_view

    monkeypatch.setattr(coverage_view.IntrinsicView, "close", lambda self: None)
    pages = []
    real_init = coverage_view.IntrinsicView.__init__

    def init(self, host, port_):
        real_init(self, host, port_)
        pages.append(self)

    monkeypatch.setattr(coverage_view.IntrinsicView, "__init__", init)
    try:
        r = calibkit_cli("intrinsic", "--display", "--views", 3, "--json",
                         tmp_path / "i.json", "--view", port)
        assert r.code == 0, r.err
        assert seen == [True, True, True]  # 0, 1 and 2 views shown before each prompt
        data = json.loads((tmp_path / "i.json").read_text())
        assert b.wait_for("document.body.innerText.includes('cam0: 3 of 3 views')", 15)
        assert f"image coverage {100 * data['coverage']:.0f} %" in b.text()
        assert "next:" not in b.text()
    finally:
        b.close()
        for p in pages:
            with contextlib.suppress(Exception):
                p.server.stop()
