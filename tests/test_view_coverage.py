"""`calibkit wand --view`: each camera's wand coverage filling in on a page, in headless
Chromium, against the capture monitor that decides when a camera has enough."""

from __future__ import annotations

import re
import socket
import threading
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
    batches = [obs.select(obs.frame // 20 == k) for k in range(30)]
    fed = threading.Event()

    def wave():  # the wand waved: a batch of 20 frames every 0.25 s
        for k, batch in enumerate(batches):
            monitor.add(identify(batch, spec, rig))
            view.update(monitor, 20 * (k + 1), final=k == len(batches) - 1)
            time.sleep(0.25)
        fed.set()

    b = Browser(1200, 1400)
    try:
        b.open(f"http://127.0.0.1:{port}")
        assert b.wait_for("document.body && document.body.innerText.includes('cam3')", 30)
        thread = threading.Thread(target=wave, daemon=True)
        thread.start()
        seen = []
        while not fed.is_set():
            m = re.search(r"cam0: (\d+) sightings", b.text())
            if m:
                seen.append(int(m.group(1)))
            time.sleep(0.3)
        thread.join()
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
