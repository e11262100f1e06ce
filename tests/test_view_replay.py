"""The replay page (`mocapd view FILE`): a C3D take and a simulated recording loaded frame
by frame, and the page in headless Chromium: moving the slider draws that frame's markers.
"""

from __future__ import annotations

import socket
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from browser import CHROMIUM, Browser

from daemon.formats.c3dio import read_c3d
from daemon.view.replay import load_replay

ROOT = Path(__file__).resolve().parents[1]
TAKE = ROOT / "fixtures" / "cmu_c3d" / "85_02.c3d"
needs_browser = pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium "
                                   "package (.ci/run installs it)")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_take_frame_by_frame_with_its_names_and_sticks():
    take = read_c3d(TAKE)
    frames, rig = load_replay(TAKE, markerset="cmu41")
    assert rig is None and len(frames) == take.n_frames
    for k in (0, 17, take.n_frames // 2, take.n_frames - 1):
        xyz, label = frames.at(k)
        seen = np.flatnonzero(np.isfinite(take.xyz_m[k]).all(axis=1))
        assert label.tolist() == seen.tolist()
        np.testing.assert_array_equal(xyz, take.xyz_m[k, seen])
    assert frames.t_s[1] == pytest.approx(1 / take.rate_hz)
    # the sticks join markers of one body segment: none longer than a limb
    xyz = take.xyz_m[0]
    lengths = [np.linalg.norm(xyz[a] - xyz[b]) for a, b in frames.sticks
               if np.isfinite(xyz[[a, b]]).all()]
    assert len(frames.sticks) >= 25 and max(lengths) < 0.6


def test_a_recording_is_triangulated_with_its_rig(tmp_path):
    from calibkit.core.recording import save_observations
    from calibkit.synthetic import sim

    rig = sim.make_rig(4, 4.0, seed=2)
    rig.save(tmp_path / "rig.toml")
    truth = sim.static_markers(5, 30, seed=4)
    obs = sim.observe(rig, truth, noise_px=0.1, fps=60.0, seed=5)
    save_observations(tmp_path / "r.mcrec", obs, truth, rig)
    frames, _ = load_replay(tmp_path / "r.mcrec", tmp_path / "rig.toml")
    assert len(frames) == 30 and not frames.labels
    for k in (0, 29):
        xyz, _ = frames.at(k)
        true = truth.xyz[truth.frame == frames.frame[k]]  # the scorer's side only
        d = np.linalg.norm(xyz[:, None] - true[None], axis=2).min(axis=1)
        assert len(xyz) == 5 and d.max() < 3e-3  # each found marker is a true one


def test_bad_input_is_one_line(tmp_path, mocapd_cli):
    (tmp_path / "x.txt").write_text("")
    (tmp_path / "r.mcrec").write_text("")
    for args, words in ((["x.txt"], "a take (.c3d, .csv) or a recording"),
                        (["missing.c3d"], "no such file"),
                        (["r.mcrec"], "--rig"),
                        ([str(TAKE), "--markerset", "nope"], "does not exist"),
                        ([str(TAKE), "--view", "localhost:80"], "--view")):
        r = mocapd_cli("view", *[tmp_path / a if a in ("x.txt", "missing.c3d", "r.mcrec")
                                 else a for a in args])
        assert r.code == 2 and words in r.err, (args, r.err)
        assert len(r.err.strip().splitlines()) == 1


@needs_browser
def test_the_slider_draws_the_chosen_frame():
    from daemon.commands.view_cmd import serve

    take = read_c3d(TAKE)
    frames, _ = load_replay(TAKE, markerset="cmu41")
    port = _free_port()
    server, page = serve(frames, None, "127.0.0.1", port, TAKE.name)
    b = Browser(1400, 900)
    try:
        b.open(f"http://127.0.0.1:{port}")
        assert b.wait_for("document.body && document.body.innerText.includes('named')", 30)
        text = b.text()
        first = take.first_frame  # the page says the file's own frame numbers
        assert f"{take.n_frames} frames" in text and f"frame {first} at 0.000 s" in text
        shot0 = b.screenshot()
        # the user clicks the slider's track at 60 % of its length
        track = b.js("""(() => { const r = document.querySelector('.mantine-Slider-root')
            .getBoundingClientRect(); return [r.left, r.top, r.width, r.height]; })()""")
        x, y, w, h = track
        b.click(x + 0.6 * w, y + h / 2)
        shown = b.wait_for("(document.body.innerText.match(/frame (\\d+) at/) || [])[1] "
                           f"!== '{first}' && "
                           "document.body.innerText.match(/frame (\\d+) at/)[1]", 15)
        k = int(shown) - first
        assert abs(k - 0.6 * (take.n_frames - 1)) < 0.05 * take.n_frames, k
        # the 3D view holds that frame's markers, every one, and the page says how many
        seen = np.isfinite(take.xyz_m[k]).all(axis=1)
        assert page.k == k
        np.testing.assert_allclose(page.drawn, take.xyz_m[k, seen], atol=1e-6)
        np.testing.assert_allclose(page.cloud.points, take.xyz_m[k, seen], atol=1e-6)
        assert f"{int(seen.sum())} markers, {int(seen.sum())} of {len(take.labels)} named" \
            in b.text()
        # and the browser draws something else than at frame 0 (the person moved)
        time.sleep(1.0)
        a = cv2.imdecode(np.frombuffer(shot0, np.uint8), cv2.IMREAD_GRAYSCALE)
        deadline = time.monotonic() + 15
        while True:
            c = cv2.imdecode(np.frombuffer(b.screenshot(), np.uint8), cv2.IMREAD_GRAYSCALE)
            changed = int((np.abs(a[:, :900].astype(int) - c[:, :900]) > 40).sum())
            if changed > 200 or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        assert changed > 200
        # Next frame steps by one
        b.click_text("button", "Next frame")
        assert b.wait_for(f"document.body.innerText.includes('frame {first + k + 1} at')", 10)
        assert page.k == k + 1
    finally:
        b.close()
        page.close()
        server.stop()
