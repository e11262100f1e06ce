"""`calibkit intrinsic --display --sim`: the monitor path a real monitor takes, with the window
drawn off-screen by the same display code onto a simulated monitor that a simulated camera
watches; scored against the simulator's truth, which only this test reads."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from calibkit.core.camera import Rig
from calibkit.synthetic.monitor import MonitorSimConfig, make_monitor_sim
from calibkit.synthetic.monitor_bench import open_bench, sim_screens
from projector import display as display_module
from projector.display import OffscreenDisplay
from projector.dots import Dots

SMALL = ("--views", 3, "--size", "320x240", "--step", 160, "--radius", 12)


@pytest.mark.slow  # a whole run of the command
def test_display_sim_recovers_the_simulated_camera(calibkit_cli, tmp_path, monkeypatch):
    shown = []
    real_show = OffscreenDisplay.show

    def counting_show(self, dots):
        shown.append(len(dots.xy))
        real_show(self, dots)

    monkeypatch.setattr(OffscreenDisplay, "show", counting_show)
    rig_path, json_path = tmp_path / "rig.toml", tmp_path / "intr.json"
    r = calibkit_cli("intrinsic", "--display", "--sim", *SMALL, "--rig", rig_path, "--json",
                     json_path)
    assert r.code == 0, r.err
    # scored here, outside the estimate: the estimated rig file against the true one
    est, truth = Rig.load(rig_path)["cam0"], Rig.load(tmp_path / "rig.truth.toml")["cam0"]
    data = json.loads(json_path.read_text())
    assert data["capture"] == "display" and data["views"] == 3
    assert abs(est.fx / truth.fx - 1) < 1e-3 and abs(est.fy / truth.fy - 1) < 1e-3
    assert abs(est.cx - truth.cx) < 0.5 and abs(est.cy - truth.cy) < 0.5
    assert abs(est.fx - truth.fx) < 5 * data["std"]["fx"]
    assert np.abs(np.asarray(est.dist[:2]) - truth.dist[:2]).max() < 0.03
    assert data["rms_px"] < 0.15
    # every pattern the capture showed went through the display code, on and off frames
    # alike (some are empty), and nothing else was drawn for the camera
    assert len(shown) >= 3 * 13 and max(shown) > 10 and min(shown) == 0
    assert "against the simulator's truth" in r.out
    last = [line for line in r.err.splitlines() if line.startswith("rendering:")][-1]
    assert last.startswith("rendering: 39/39 (100%)") and "elapsed" in last


@pytest.mark.slow  # a whole run of the command
def test_the_camera_sees_only_what_the_display_draws(calibkit_cli, monkeypatch):
    """With a display that draws nothing, the simulated camera sees no dots: the pattern
    cannot come from anywhere but the display code. One clear line, exit 2."""
    monkeypatch.setattr(display_module._Renderer, "draw",
                        lambda self, dots: self.ctx.clear(0.0, 0.0, 0.0, 1.0))
    r = calibkit_cli("intrinsic", "--display", "--sim", *SMALL)
    assert r.code == 2
    assert len(r.err.strip().splitlines()[-1]) > 20 and "Traceback" not in r.err


@pytest.mark.slow  # renders frames (EGL, spots)
def test_a_drawn_frame_and_the_simulators_own_render_give_the_same_image():
    """show_image(what the display drew) is the very picture show(dots) puts on the glass."""
    cfg = MonitorSimConfig(seed=3)
    dots = Dots.make([[400.0, 300.5], [960.25, 540.0], [1500.0, 800.0]], 8.0)
    images = []
    for through_display in (False, True):
        with make_monitor_sim(1, (320, 240), 3, cfg, fill=0.8) as sim, \
                OffscreenDisplay(cfg.screen_px) as window:
            sim.set_view(0)
            window.watch(sim.show_image)
            if through_display:
                window.show(dots)
            else:
                sim.show(dots)
            images.append([sim.grab() for _ in range(6)])
    np.testing.assert_array_equal(images[0], images[1])
    assert images[0][-1].max() > 100  # the dots were seen


def test_the_simulated_monitor_reports_its_size_as_an_edid_does():
    cfg = MonitorSimConfig()
    (screen,) = sim_screens(cfg)
    assert (screen.width_px, screen.height_px) == cfg.screen_px
    assert screen.width_mm == round(cfg.screen_px[0] * cfg.pixel_pitch_mm)
    assert screen.pixel_pitch_mm == pytest.approx(cfg.pixel_pitch_mm, rel=2e-3)


@pytest.mark.slow  # renders frames (EGL, spots)
def test_bench_frames_come_from_a_live_camera(tmp_path):
    from calibkit.synthetic.sim import make_rig

    truth = make_rig(2, size=(160, 120), seed=1)["cam1"]
    with open_bench(truth, 2, 0.8, MonitorSimConfig(seed=1)) as bench:
        bench.tilt(0, 2)
        frames = iter(bench.source)
        a, b = next(frames), next(frames)
        assert a.camera == "cam1" and (a.index, b.index) == (0, 1) and b.t_ns > a.t_ns
        assert a.image.shape == (120, 160) and a.image.dtype == np.uint8


@pytest.mark.parametrize("args, words", [
    (("--display", "--sim", "--no-render"), "--no-render"),
    (("--images", ".", "--sim"), "--images"),
    (("--display", "--sim", "--monitor", 2), "no monitor 2"),
])
def test_refused_with_one_line(calibkit_cli, args, words):
    r = calibkit_cli("intrinsic", *args)
    assert r.code == 2 and words in r.err and len(r.err.strip().splitlines()) == 1, r.err


def test_run_progress_says_done_elapsed_and_time_left():
    from calibkit.commands.intrinsic_cmd import _RunProgress

    stream = io.StringIO()
    run = _RunProgress(20, every_s=0.0, stream=stream)
    run.camera = "cam0"
    view = run("view 1/2", 10)
    view.update(5)
    view.finish("done")
    run("view 2/2", 10).update(3)
    run.finish()
    lines = stream.getvalue().splitlines()
    assert lines[0].startswith("rendering: 5/20 (25%)") and "s left (cam0 view 1/2)" in lines[0]
    assert any(line.startswith("rendering: 13/20 (65%)") for line in lines)
    assert lines[-1].startswith("rendering: 13/20") and "elapsed" in lines[-1]
