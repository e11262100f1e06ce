"""Monitor intrinsic calibration against the simulator's truth: settling, capture, solve,
bias correction, and the command line with its errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibkit.calibrate.dotcapture import DotCapture
from calibkit.calibrate.intrinsic import (
    PlaneView,
    calibrate,
    disc_bias_px,
    guidance,
    monitor_plane_view,
)
from calibkit.calibrate.settle import SettleDetector, signature_noise
from calibkit.core.camera import Camera, Rig, rotation_from_rvec, rvec_from_rotation
from calibkit.core.errors import UserError
from calibkit.synthetic.monitor import MonitorSimConfig, default_sim_camera, make_monitor_sim
from calibkit.synthetic.sim import MonitorView, monitor_points, monitor_views
from projector.dots import Dots
from projector.patterns import coded_schedule, grid_positions

SMALL = dict(screen_px=(960, 540), pixel_pitch_mm=0.543)  # a 52 cm monitor, fewer pixels


def _small_sim(n_views=1, seed=0, **cfg):
    config = MonitorSimConfig(**SMALL, seed=seed, **cfg)
    return make_monitor_sim(n_views, (320, 240), seed, config)


# ---- settling ---------------------------------------------------------------------------------

@pytest.mark.parametrize("latency_s", [0.05, 0.15])
def test_settle_detects_display_latency(latency_s):
    sim = _small_sim(latency_s=latency_s)
    fps, exposure = sim.config.fps, sim.config.exposure_s
    with sim:
        sim.set_view(0)
        a = Dots.make(grid_positions((960, 540), 80.0), 6.0)
        b = Dots.make(grid_positions((960, 540), 80.0, (40.0, 40.0)), 6.0)
        sim.show(a)
        still = [sim.grab() for _ in range(10)]
        det = SettleDetector(noise=signature_noise(still[-5:]), hold=1)
        for pattern, other in ((b, a), (a, b)):
            det.start(still[-1])
            sim.show(pattern)
            for k in range(1, 40):  # noqa: B007 - k is used after the loop
                img = sim.grab()
                if det.feed(img):
                    break
            # the first frame with any of the new pattern, from the latency and the exposure
            first_changed = int(np.floor(latency_s * fps - exposure * fps)) + 2
            assert det.latencies[-1] == first_changed
            # the settled frame shows the new pattern only: compare with both noise-free images
            clean = sim.warp(sim.display.render(pattern))
            wrong = sim.warp(sim.display.render(other))
            assert np.abs(img - clean).mean() < 2.0 < np.abs(img - wrong).mean()
            assert (k - 1) / fps >= latency_s  # its exposure began after the switch
            still = [img]
        assert det.latency_frames == first_changed


# ---- capture -------------------------------------------------------------------------------

def test_capture_identifies_dots_against_truth():
    sim = _small_sim(drop_rate=0.1, seed=1)  # a tenth of the camera frames are lost
    schedule = coded_schedule(sim.config.screen_px, 80.0, 2, 6.0)
    with sim:
        sim.set_view(0)
        dots = DotCapture(sim, schedule).run()
        truth, _ = sim.truth_uv(schedule.points_xy[dots.ids])
        visible_uv, front = sim.truth_uv(schedule.points_xy)
        visible = front & sim.camera.in_image(visible_uv, margin_px=3)
    err = np.linalg.norm(dots.uv - truth, axis=1)
    # 2 DN noise averaged over 3 frames on ~1.6 px dots: a few hundredths of a pixel
    assert err.max() < 0.3  # no dot misidentified
    assert np.sqrt(np.mean(err ** 2)) < 0.1
    assert len(dots) >= 0.9 * visible.sum()
    assert dots.frames <= 10 * 30  # <= 10 s at 30 fps
    assert np.median(dots.scatter_px) < 0.1


def test_monitor_out_of_view_is_a_clear_error():
    cam = default_sim_camera((320, 240))
    away = MonitorView(np.eye(3), np.array([5.0, 5.0, 1.0]))  # far off to the side
    config = MonitorSimConfig(**SMALL)
    from calibkit.synthetic.monitor import MonitorSim

    schedule = coded_schedule(config.screen_px, 80.0, 2, 6.0)
    with MonitorSim(cam, [away], config) as sim:
        sim.set_view(0)
        dots = DotCapture(sim, schedule).run()
    with pytest.raises(UserError, match="monitor is not in view"):
        monitor_plane_view(dots, schedule, config.pixel_pitch_mm)


# ---- the solve ---------------------------------------------------------------------------------

def _synthetic_views(camera: Camera, n_views=6, noise_px=0.1, seed=0, outliers=0.0):
    rng = np.random.default_rng(seed)
    screen, pitch = (1920, 1080), 0.2715
    xy = grid_positions(screen, 60.0)
    views = []
    for view in monitor_views(camera, n_views, screen, pitch, seed=seed):
        pts = monitor_points(view, xy, pitch)
        uv, front = camera.project(pts)
        keep = front & camera.in_image(uv, 2)
        uv = uv[keep] + rng.normal(0, noise_px, (keep.sum(), 2))
        bad = rng.random(len(uv)) < outliers
        uv[bad] += rng.uniform(-8, 8, (bad.sum(), 2))
        obj = np.column_stack([xy[keep] * pitch / 1000, np.zeros(keep.sum())])
        views.append(PlaneView(obj, uv))
    return views


@pytest.mark.parametrize("outliers", [0.0, 0.03])
def test_solve_against_truth(outliers):
    truth = default_sim_camera()
    noise = 0.1
    views = _synthetic_views(truth, noise_px=noise, outliers=outliers)
    r = calibrate(views, truth.size)
    c = r.camera
    for name, err in (("fx", c.fx - truth.fx), ("fy", c.fy - truth.fy),
                      ("cx", c.cx - truth.cx), ("cy", c.cy - truth.cy)):
        assert abs(err) < 4 * r.std[name] + 1e-9, (name, err, r.std[name])
    assert abs(c.fx / truth.fx - 1) < 5e-4
    assert abs(c.cx - truth.cx) < 0.5 and abs(c.cy - truth.cy) < 0.5
    # 2D RMS of Gaussian noise sigma per axis is sigma * sqrt(2)
    assert r.rms_px == pytest.approx(noise * np.sqrt(2), rel=0.1)
    assert r.inliers.mean() == pytest.approx(1 - outliers, abs=0.01)
    np.testing.assert_allclose(c.dist[:2], truth.dist[:2], atol=0.01)
    assert 0 < r.coverage <= 1


def test_disc_bias_matches_integrated_disc_image():
    """The ellipse-centre formula against a brute-force centroid of the disc's image."""
    cam = default_sim_camera().replace(dist=np.zeros(5))
    view = monitor_views(cam, 1, max_tilt_deg=45, seed=3)[0]
    rvec = rvec_from_rotation(view.R)
    centres = np.array([[0.05, 0.05], [0.4, 0.2], [0.1, 0.25]])
    radius = 0.01
    obj = np.column_stack([centres, np.zeros(3)])
    bias = disc_bias_px(cam, rvec[None], view.t[None], [PlaneView(obj, obj[:, :2])], radius)[0]
    # integrate: sample the disc densely, project, weight by the image area each sample
    # covers (the homography's Jacobian), and take the centroid
    g = np.linspace(-radius, radius, 401)
    gx, gy = np.meshgrid(g, g)
    inside = gx ** 2 + gy ** 2 <= radius ** 2
    d = np.column_stack([gx[inside], gy[inside]])
    for i, c in enumerate(centres):
        pts = np.column_stack([c + d, np.zeros(len(d))]) @ view.R.T + view.t
        z = pts[:, 2]
        uv = cam.fx * pts[:, 0] / z + cam.cx, cam.fy * pts[:, 1] / z + cam.cy
        w = 1.0 / z ** 3
        centroid = np.array([np.sum(uv[0] * w), np.sum(uv[1] * w)]) / w.sum()
        centre_img, _ = cam.project(np.array([[*c, 0.0]]) @ view.R.T + view.t)
        np.testing.assert_allclose(centroid - centre_img[0], bias[i], atol=2e-3)
    assert np.abs(bias).max() > 0.05  # large dots, steep tilt: a real bias


def test_bias_correction_removes_large_dot_error():
    truth = default_sim_camera()
    radius = 0.006  # 12 mm dots: a few pixels in the image
    clean = _synthetic_views(truth, noise_px=0.02)
    poses = monitor_views(truth, 6, seed=0)
    rv = np.array([rvec_from_rotation(v.R) for v in poses])
    tv = np.array([v.t for v in poses])
    bias = disc_bias_px(truth, rv, tv, clean, radius)
    biased = [PlaneView(v.obj, v.uv + b) for v, b in zip(clean, bias, strict=True)]
    plain = calibrate(biased, truth.size)
    fixed = calibrate(biased, truth.size, dot_radius_m=radius)
    err_plain = abs(plain.camera.fx / truth.fx - 1)
    err_fixed = abs(fixed.camera.fx / truth.fx - 1)
    assert fixed.bias_corrected
    assert err_fixed < 2e-4 and err_fixed < 0.5 * err_plain


def test_too_few_and_parallel_views_are_clear_errors():
    truth = default_sim_camera()
    views = _synthetic_views(truth, n_views=2)
    with pytest.raises(UserError, match="too few usable views"):
        calibrate(views, truth.size)
    # the same tilt three times, only moved: the focal length is undetermined
    base = monitor_views(truth, 1, seed=0)[0]
    xy = grid_positions((1920, 1080), 60.0)
    parallel = []
    for shift in (-0.03, 0.0, 0.03):
        pts = monitor_points(MonitorView(np.eye(3), base.t + [shift, 0, 0]), xy, 0.2715)
        uv, _ = truth.project(pts)
        keep = truth.in_image(uv, 2)
        obj = np.column_stack([xy[keep] * 0.2715e-3, np.zeros(keep.sum())])
        parallel.append(PlaneView(obj, uv[keep]))
    with pytest.raises(UserError, match="parallel"):
        calibrate(parallel, truth.size)


def test_guidance_names_the_missing_tilt():
    truth = default_sim_camera()
    views = _synthetic_views(truth, n_views=1)
    line = guidance(views, truth.size, 6)
    assert line.startswith("1/6 views") and "coverage" in line and "next: tilt" in line


# ---- the command line ------------------------------------------------------------------------

def test_intrinsic_sim_command(calibkit_cli, tmp_path):
    rig_path = tmp_path / "rig.toml"
    other = Camera("cam1", (640, 480), 500, 500, 320, 240)
    posed = Camera("cam0", (320, 240), 100, 100, 160, 120, 0.0, np.zeros(5), [0.1, 0.2, 0.3],
                   [1.0, 2.0, 3.0])
    Rig((other, posed)).save(rig_path)
    out = tmp_path / "intr.json"
    plot = tmp_path / "dist.png"
    r = calibkit_cli("intrinsic", "--sim", "--views", 3, "--size", "320x240", "--step", 160,
                     "--radius", 12, "--json", out, "--plot", plot, "--rig", rig_path)
    assert r.code == 0, r.err
    data = json.loads(out.read_text())
    for key in ("fx", "fy", "cx", "cy", "skew", "dist", "rms_px", "views", "points", "std",
                "truth"):
        assert key in data
    assert set(data["std"]) >= {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"}
    t = data["truth"]
    assert abs(data["fx"] / t["fx"] - 1) < 1e-3
    assert abs(data["cx"] - t["cx"]) < 0.5 and abs(data["cy"] - t["cy"]) < 0.5
    assert abs(data["fx"] - t["fx"]) < 5 * data["std"]["fx"]
    assert data["rms_px"] < 0.15 and data["views"] == 3
    rig = Rig.load(rig_path)
    cam = rig["cam0"]
    assert cam.fx == pytest.approx(data["fx"]) and rig["cam1"].fx == 500
    np.testing.assert_allclose(cam.rvec, [0.1, 0.2, 0.3])  # the pose is kept
    # the estimate's uncertainty goes into the rig file, one std per parameter
    assert rig.quality["intrinsic"]["cam0"]["std"] == pytest.approx(data["std"])
    # the simulated hardware (cam0 of a ring made from --seed) is the truth file's cam0
    true_cam = Rig.load(tmp_path / "rig.truth.toml")["cam0"]
    assert t["fx"] == pytest.approx(true_cam.fx) and true_cam.size == (320, 240)
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "views" in r.err  # guidance and progress on stderr


def test_every_camera_of_a_simulated_rig(calibkit_cli, tmp_path):
    """--camera all on a true rig file: each camera estimated from its own monitor views
    with that camera's own lens; the estimate differs from the truth by about its std."""
    from calibkit.synthetic import sim

    world = tmp_path / "world.truth.toml"
    true_rig = sim.make_rig(3, 4.0, (320, 240), seed=5)
    # cameras of one rig that really differ: each camera's lens must be its own
    true_rig = Rig(tuple(c.replace(fx=c.fx * (1 + 0.03 * i), dist=c.dist * (1 + 0.5 * i))
                         for i, c in enumerate(true_rig)), meta=true_rig.meta)
    true_rig.save(world)
    intr = tmp_path / "intr.toml"
    r = calibkit_cli("intrinsic", "--sim", "--sim-rig", world, "--camera", "all",
                     "--no-render", "--views", 4, "--step", 120, "--rig", intr, "--json",
                     tmp_path / "i.json")
    assert r.code == 0, r.err
    est = Rig.load(intr)
    assert est.names == true_rig.names
    assert "cameras: 3/3" in r.err  # progress per camera
    figures = json.loads((tmp_path / "i.json").read_text())["cameras"]
    for cam, truth, f in zip(est, true_rig, figures, strict=True):
        std = est.quality["intrinsic"][cam.name]["std"]
        assert set(std) == {"fx", "fy", "cx", "cy", "skew", "k1", "k2", "p1", "p2", "k3"}
        assert cam.fx != truth.fx  # an estimate, not the truth
        # 0.035 px centroid noise: within 5 std of the truth, which the std says is tight
        assert abs(cam.fx - truth.fx) < 5 * std["fx"] and std["fx"] < 0.1
        assert abs(cam.cx - truth.cx) < 5 * std["cx"] and abs(cam.cy - truth.cy) < 5 * std["cy"]
        assert abs(cam.dist[0] - truth.dist[0]) < 5 * std["k1"]
        assert f["camera"] == cam.name and abs(f["error"]["fx_rel"]) < 5e-4
        assert 0.035 < f["rms_px"] < 0.06  # sqrt(2) x 0.035 px per axis
    assert Rig.load(tmp_path / "intr.truth.toml").names == true_rig.names
    # the views themselves, for the wand solve's graph: named by the rig file, every camera's
    # inlier dots with the solved view poses (each view's dots reproject with them)
    from calibkit.calibrate import plane_views

    assert {e["views_file"] for e in est.quality["intrinsic"].values()} == {"intr.views.npz"}
    kept = plane_views.load_for(est.quality, intr, est.names)
    assert kept.camera_names == tuple(est.names) and len(kept.view_camera) == 3 * 4
    for k, (cam, f) in enumerate(zip(est, figures, strict=True)):
        rows = kept.camera == k
        assert abs(rows.sum() - f["points"] * f["inlier_fraction"]) < 1
        v = kept.view[rows]
        pts = np.einsum("nij,nj->ni", np.stack([rotation_from_rvec(r)
                                                for r in kept.view_rvec[v]]),
                        kept.xyz[rows]) + kept.view_tvec[v]
        uv = cam.replace(rvec=np.zeros(3), t=np.zeros(3)).project(pts)[0]
        assert np.sqrt(np.mean((uv - kept.uv[rows]) ** 2)) < 0.06


def test_projected_dots_agree_with_the_rendered_capture():
    """The fast path reports where the rendered capture finds each dot: the centre of the
    dot's image, which for large tilted dots is not where the dot's centre projects."""
    from calibkit.synthetic.monitor import projected_dots

    sim_ = _small_sim(n_views=1, seed=4, noise_dn=0.5)
    schedule = coded_schedule(SMALL["screen_px"], 60.0, 1, 12.0)
    with sim_:
        rendered = DotCapture(sim_, schedule, samples=3).run()
        fast = projected_dots(sim_.camera, sim_.views[0], schedule.points_xy, 12.0,
                              SMALL["pixel_pitch_mm"], 0.0, np.random.default_rng(0))
        centre, _ = sim_.truth_uv(schedule.points_xy)
    common, i_r, i_f = np.intersect1d(rendered.ids, fast.ids, return_indices=True)
    assert len(common) > 0.9 * len(rendered.ids) and len(common) > 50
    d_fast = np.linalg.norm(rendered.uv[i_r] - fast.uv[i_f], axis=1)
    d_centre = np.linalg.norm(rendered.uv[i_r] - centre[common], axis=1)
    assert np.sqrt(np.mean(d_fast**2)) < 0.05  # the rendered capture's own noise
    assert np.sqrt(np.mean(d_centre**2)) > 2 * np.sqrt(np.mean(d_fast**2))


@pytest.mark.parametrize("args, message", [
    ((), "choose one of"),
    (("--sim", "--views", 2), "--views must be at least 3"),
    (("--images", "/nonexistent/folder", "--board", "chessboard:9x6:25"), "no such folder"),
    (("--images", "."), "--images needs --board"),
    (("--sim", "--step", 10, "--radius", 6), "dot pattern"),
    (("--sim", "--pixel-pitch", "527/0"), "--pixel-pitch takes"),
    (("--sim", "--fill", 9), "--fill must be"),
    (("--sim", "--camera", "cam9"), "camera 'cam9' is not in the simulated rig"),
    (("--sim", "--sim-rig", "/nonexistent/world.toml"), "world.toml"),
    (("--images", ".", "--board", "chessboard:9x6:25", "--camera", "all"),
     "--camera all calibrates every camera of a simulated rig"),
])
def test_intrinsic_errors(calibkit_cli, args, message):
    r = calibkit_cli("intrinsic", *args)
    assert r.code == 2 and message in r.err
    assert "Traceback" not in r.err and len(r.err.strip().splitlines()) == 1


def test_display_mode_without_display_or_camera(calibkit_cli, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    r = calibkit_cli("intrinsic", "--display")
    assert r.code == 2 and "no display found" in r.err
    assert len(r.err.strip().splitlines()) == 1
    monkeypatch.setenv("DISPLAY", ":99")  # a display, but no such camera
    r = calibkit_cli("intrinsic", "--display", "--device", 99)
    assert r.code == 2 and "camera device 99 could not be opened" in r.err


def test_raster_scan_capture():
    sim = _small_sim(seed=2)
    from projector.patterns import raster_schedule

    schedule = raster_schedule(sim.config.screen_px, 160.0, 6.0)
    with sim:
        sim.set_view(0)
        dots = DotCapture(sim, schedule).run()
        truth, _ = sim.truth_uv(schedule.points_xy[dots.ids])
    assert len(dots) >= 0.6 * len(schedule.points_xy)
    assert np.linalg.norm(dots.uv - truth, axis=1).max() < 0.3


def test_monitor_partly_out_of_view_reaches_the_corners():
    """A screen larger than the image (its edges out of view): only the dots seen are used,
    none is misnamed, and they cover the image corners a board would miss."""
    config = MonitorSimConfig(**SMALL)
    sim = make_monitor_sim(4, (320, 240), 0, config, fill=1.25)
    schedule = coded_schedule(config.screen_px, 80.0, 2, 6.0)
    views = []
    with sim:
        cap = DotCapture(sim, schedule)
        for v in range(4):
            sim.set_view(v)
            dots = cap.run()
            truth, _ = sim.truth_uv(schedule.points_xy[dots.ids])
            assert np.linalg.norm(dots.uv - truth, axis=1).max() < 0.3
            views.append(monitor_plane_view(dots, schedule, config.pixel_pitch_mm))
    r = calibrate(views, sim.camera.size, dot_radius_m=6 * config.pixel_pitch_mm / 1000)
    assert r.coverage == 1.0
    assert abs(r.camera.fx / sim.camera.fx - 1) < 5e-4
    assert abs(r.camera.cx - sim.camera.cx) < 0.5 and abs(r.camera.cy - sim.camera.cy) < 0.5


@pytest.mark.parametrize("dropped", [None, 4])
def test_decode_rendered_layer_with_a_dropped_frame(dropped):
    """Decoding from camera images of the rendered code frames, noisy, with one frame
    missing: every dot is still named correctly (the parity restores the lost bit)."""
    sim = _small_sim(seed=3)
    schedule = coded_schedule(sim.config.screen_px, 80.0, 1, 6.0)
    rng = np.random.default_rng(3)
    from projector.patterns import decode_layer

    with sim:
        sim.set_view(0)
        images = {}
        for i in schedule.layer_frames(0):
            f = schedule.frames[i]
            clean = sim.warp(sim.display.render(Dots.make(f.xy, schedule.radius_px)))
            images[i] = clean + rng.normal(0, sim.config.noise_dn, clean.shape)
        uv, front = sim.truth_uv(schedule.points_xy)
        seen = front & sim.camera.in_image(uv, margin_px=3)
    if dropped is not None:
        images[schedule.layer_frames(0)[dropped]] = None
    ids, dec = decode_layer(schedule, 0, images, uv[seen])
    assert np.array_equal(ids, np.nonzero(seen)[0])
    assert dec.restored.all() == (dropped is not None)


def test_dot_radius_in_the_image_is_reported():
    sim = _small_sim()
    schedule = coded_schedule(sim.config.screen_px, 80.0, 1, 6.0)
    with sim:
        sim.set_view(0)
        dots = DotCapture(sim, schedule).run()
        # the screen's scale in the image, from two dots a step apart
        a, _ = sim.truth_uv(np.array([[480.0, 270.0], [560.0, 270.0]]))
    expected = 6.0 * np.linalg.norm(a[1] - a[0]) / 80.0
    # the apparent radius (above the detection threshold) includes the blur's skirt:
    # 0.6 px blur sigma, threshold ~5 % of the peak -> up to ~2 sigma more
    assert expected < dots.dot_radius_px < expected + 2 * 0.6 + 0.3


def test_display_mode_runs_with_a_monitor_and_camera(calibkit_cli, monkeypatch, tmp_path):
    """The live --display path end to end, with the window and the camera replaced by the
    simulator (no glfw or camera here): show -> settle -> decode -> solve -> rig."""
    import builtins

    import calibkit.cameras
    import projector.display
    import projector.screens
    from calibkit.cameras import Frame
    from projector.screens import Screen

    config = MonitorSimConfig(**SMALL)
    sim = make_monitor_sim(3, (320, 240), 0, config)
    view = iter(range(3))

    class FakeCamera:
        def __init__(self, spec, name=None):
            assert spec == "0"  # --device's default
            self.camera = name

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            sim.close()

        def __iter__(self):
            i = 0
            while True:
                yield Frame(self.camera, i, i, np.dstack([sim.grab()] * 3))  # BGR, as V4L2
                i += 1

    class FakeWindow:
        def __init__(self, monitor):
            pass

        def show(self, dots):
            sim.show(dots)

        def close(self):
            pass

    screen = Screen(0, "sim", *config.screen_px, 0.0, 0.0)
    monkeypatch.setattr(projector.screens, "require_display", lambda: None)
    monkeypatch.setattr(projector.screens, "pick_screen",
                        lambda index, pitch: (screen, config.pixel_pitch_mm))
    monkeypatch.setattr(calibkit.cameras, "open_camera", FakeCamera)
    monkeypatch.setattr(projector.display, "WindowDisplay", FakeWindow)
    monkeypatch.setattr(builtins, "input", lambda prompt="": sim.set_view(next(view)))
    out = tmp_path / "live.json"
    r = calibkit_cli("intrinsic", "--display", "--views", 3, "--json", out,
                     "--rig", tmp_path / "rig.toml")
    assert r.code == 0, r.err
    data = json.loads(out.read_text())
    assert abs(data["fx"] / sim.camera.fx - 1) < 1e-3
    assert abs(data["cx"] - sim.camera.cx) < 0.5 and abs(data["cy"] - sim.camera.cy) < 0.5
    assert Rig.load(tmp_path / "rig.toml")["cam0"].fx == pytest.approx(data["fx"])


def test_reported_std_matches_the_actual_errors():
    """Over several noise draws, errors divided by the reported std scatter like N(0, 1)."""
    truth = default_sim_camera()
    z = []
    for seed in range(8):
        rng = np.random.default_rng(100 + seed)
        xy = grid_positions((1920, 1080), 120.0)
        views = []
        for view in monitor_views(truth, 5, seed=0):
            uv, front = truth.project(monitor_points(view, xy, 0.2715))
            keep = front & truth.in_image(uv, 2)
            obj = np.column_stack([xy[keep] * 0.2715e-3, np.zeros(keep.sum())])
            views.append(PlaneView(obj, uv[keep] + rng.normal(0, 0.2, (keep.sum(), 2))))
        r = calibrate(views, truth.size)
        c = r.camera
        z += [(c.fx - truth.fx) / r.std["fx"], (c.fy - truth.fy) / r.std["fy"],
              (c.cx - truth.cx) / r.std["cx"], (c.cy - truth.cy) / r.std["cy"]]
    rms_z = float(np.sqrt(np.mean(np.square(z))))
    assert 0.5 < rms_z < 1.6, rms_z


def test_a_shaking_camera_is_told_to_hold_still():
    """Dots that move between the averaged frames are dropped; when the whole image shakes
    (1 px per frame) nothing is kept and the user is told why."""
    config = MonitorSimConfig(**SMALL, shake_px=1.0)
    schedule = coded_schedule(config.screen_px, 80.0, 2, 6.0)
    with make_monitor_sim(1, (320, 240), 0, config) as sim:
        sim.set_view(0)
        dots = DotCapture(sim, schedule).run()
    assert len(dots) < 12 and dots.moved > 100
    with pytest.raises(UserError, match="the image moved"):
        monitor_plane_view(dots, schedule, config.pixel_pitch_mm)
