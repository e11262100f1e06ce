"""Benchmark: monitor-dot intrinsic calibration against an OpenCV chessboard baseline.

Each run simulates one 640x480 camera (its own lens and principal point, from the seed)
watching a 1920x1080 monitor in 6 tilted views (calibkit.synthetic.monitor): the coded dot
schedule is captured and solved (calibkit.calibrate.intrinsic), and in the same views the monitor
shows a chessboard filling the screen, which OpenCV's findChessboardCorners/cornerSubPix/
calibrateCamera calibrate from (the same camera, noise, blur and averaging of 3 frames).
Prints per-run figures and the medians, and the ratio of the baseline's errors to ours.

    python benchmarks/bench_intrinsic.py [--runs 3] [--views 6]
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np

from calibkit.calibrate.dotcapture import DotCapture
from calibkit.calibrate.intrinsic import calibrate, monitor_plane_view
from calibkit.synthetic.monitor import MonitorSimConfig, make_monitor_sim
from projector.patterns import coded_schedule, raster_schedule


def chessboard_screen(screen_px, square_px=120, cols=15, rows=8):
    """A chessboard filling the screen (float 0..1) and its inner corners in screen px."""
    w, h = screen_px
    x0 = (w - cols * square_px) // 2
    y0 = (h - rows * square_px) // 2
    img = np.ones((h, w), np.float32)  # a white border, as a printed board has
    for r in range(rows):
        for c in range(cols):
            if (r + c) % 2 == 1:
                img[y0 + r * square_px:y0 + (r + 1) * square_px,
                    x0 + c * square_px:x0 + (c + 1) * square_px] = 0.0
    gx, gy = np.meshgrid(np.arange(1, cols), np.arange(1, rows))
    # a square edge lies between pixels: pixel centres at integers, so corners sit at -0.5
    corners = np.column_stack([x0 + gx.ravel() * square_px - 0.5,
                               y0 + gy.ravel() * square_px - 0.5])
    return img, corners, (cols - 1, rows - 1)


def opencv_chessboard(sim, n_views, rng):
    """OpenCV's chessboard calibration in the same simulated views."""
    cfg = sim.config
    board, corners, pattern = chessboard_screen(cfg.screen_px)
    obj = np.column_stack([corners * cfg.pixel_pitch_mm / 1000.0,
                           np.zeros(len(corners))]).astype(np.float32)
    objs, imgs = [], []
    for v in range(n_views):
        sim.set_view(v)
        clean = sim.warp(board)
        shots = [np.clip(clean + rng.normal(0, cfg.noise_dn, clean.shape), 0, 255)
                 for _ in range(3)]
        img = np.clip(np.rint(np.mean(shots, axis=0)), 0, 255).astype(np.uint8)
        ok, found = cv2.findChessboardCorners(img, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH
                                              | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok:
            continue
        found = cv2.cornerSubPix(img, found, (5, 5), (-1, -1),
                                 (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4))
        objs.append(obj)
        imgs.append(found)
    if len(objs) < 3:
        return None, len(objs)
    _, K, dist, _, _ = cv2.calibrateCamera(objs, imgs, sim.camera.size, None, None)
    return K, len(objs)


def one_run(seed: int, n_views: int, fill: float = 0.8, baseline: bool = True) -> dict:
    cfg = MonitorSimConfig(seed=seed)
    sim = make_monitor_sim(n_views, (640, 480), seed, cfg, fill=fill)
    truth = sim.camera
    schedule = coded_schedule(cfg.screen_px, 80.0, 2, 6.0)
    views, frames = [], []
    t0 = time.perf_counter()
    with sim:
        cap = DotCapture(sim, schedule)
        for v in range(n_views):
            sim.set_view(v)
            dots = cap.run()
            frames.append(dots.frames)
            views.append(monitor_plane_view(dots, schedule, cfg.pixel_pitch_mm))
        sim_s = time.perf_counter() - t0
        t1 = time.perf_counter()
        res = calibrate(views, truth.size, dot_radius_m=6.0 * cfg.pixel_pitch_mm / 1000.0)
        solve_s = time.perf_counter() - t1
        K, cv_views = (opencv_chessboard(sim, n_views, np.random.default_rng(seed + 100))
                       if baseline else (None, 0))
    c = res.camera
    out = {
        "seed": seed, "frames_per_view": float(np.median(frames)),
        "capture_s_per_view": float(np.median(frames)) / cfg.fps,
        "points": res.points, "rms_px": res.rms_px, "coverage": res.coverage,
        "fx_err_pct": 100 * abs(c.fx / truth.fx - 1), "fy_err_pct": 100 * abs(c.fy / truth.fy - 1),
        "cx_err_px": abs(c.cx - truth.cx), "cy_err_px": abs(c.cy - truth.cy),
        "solve_s": solve_s, "sim_s": sim_s, "cv_views": cv_views,
    }
    if K is not None:
        out.update({"cv_fx_err_pct": 100 * abs(K[0, 0] / truth.fx - 1),
                    "cv_fy_err_pct": 100 * abs(K[1, 1] / truth.fy - 1),
                    "cv_cx_err_px": abs(K[0, 2] - truth.cx),
                    "cv_cy_err_px": abs(K[1, 2] - truth.cy)})
    # the original single-dot scan at the same spacing: frames it would need per view,
    # at the frames per pattern measured here
    per_pattern = np.median(frames) / len(schedule.frames)
    out["raster_frames_per_view"] = len(raster_schedule(cfg.screen_px, 80.0).frames) * per_pattern
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--views", type=int, default=6)
    args = ap.parse_args()
    runs = [one_run(seed, args.views) for seed in range(args.runs)]
    keys = ["frames_per_view", "capture_s_per_view", "points", "coverage", "rms_px",
            "fx_err_pct",
            "fy_err_pct", "cx_err_px", "cy_err_px", "cv_fx_err_pct", "cv_fy_err_pct",
            "cv_cx_err_px", "cv_cy_err_px", "cv_views", "solve_s", "raster_frames_per_view"]
    print(f"monitor intrinsic calibration: 640x480 camera, {args.views} views, "
          f"{args.runs} runs (seeds 0..{args.runs - 1})")
    print(f"{'figure':24s}" + "".join(f"{'run ' + str(r['seed']):>11s}" for r in runs)
          + f"{'median':>11s}")
    med = {}
    for k in keys:
        vals = [r.get(k, float("nan")) for r in runs]
        med[k] = float(np.nanmedian(vals))
        print(f"{k:24s}" + "".join(f"{v:11.4g}" for v in vals) + f"{med[k]:11.4g}")
    print("(cv_views: views in which OpenCV found the whole chessboard; it needs 3)")
    print("\nratio of errors, OpenCV chessboard / monitor dots (median over runs; > 1 means "
          "the dots are more accurate):")
    for p, unit in (("fx", "pct"), ("fy", "pct"), ("cx", "px"), ("cy", "px")):
        ratios = [r[f"cv_{p}_err_{unit}"] / max(r[f"{p}_err_{unit}"], 1e-12) for r in runs
                  if f"cv_{p}_err_{unit}" in r]
        print(f"  {p}: {np.median(ratios):.2f}  (runs: "
              + ", ".join(f"{x:.2f}" for x in ratios) + ")")
    print(f"\ncapture per view {med['capture_s_per_view']:.1f} s at 30 fps (single-dot scan: "
          f"{med['raster_frames_per_view'] / 30:.0f} s), all views "
          f"{args.views * med['capture_s_per_view']:.0f} s")
    # the monitor nearer, overflowing the image: dots reach the corners (no chessboard
    # baseline: a board must be wholly in view)
    near = [one_run(seed, args.views, fill=1.2, baseline=False) for seed in range(args.runs)]
    print("\nmonitor overflowing the image (fill 1.2), dots only, medians: " + ", ".join(
        f"{k} {np.median([r[k] for r in near]):.4g}" for k in
        ("points", "coverage", "rms_px", "fx_err_pct", "fy_err_pct", "cx_err_px",
         "cy_err_px")))


if __name__ == "__main__":
    main()
