"""Small real-sized wand captures: `calibkit wand`'s solve against a plain reference, and
when the solve refines intrinsics given without uncertainties.

Part 1, small captures (the default). Like a hand-digitised easyWand/DLTdv capture: 3
cameras (sim.make_rig ring, 4 m volume, 640x480, pinhole lenses), 50 frames of a 2-end wand
0.7 m long waved at 5 frames a second (so the frames spread through the volume), 0.5 or
1 px of noise on each end, every end seen where it is in the image (no merged blobs). Both
solvers get the same nominal pinhole intrinsics: the focal length from the lens's nominal
field of view and the principal point at the image centre (the simulator's cameras have
theirs 0.2 % and ~6 px off that), no uncertainties, and neither knows the wand's length.

  ours       calibkit.calibrate.wand_solve.calibrate, as `calibkit wand --spacing 0,1
             --wand-length unknown` runs it: identification (the ends' labels are not used),
             initial poses from pairwise geometry, 10 % of the frames held out, the GTSAM
             bundle adjustment, intrinsics refined only where the capture shows it pays.
  reference  written here, as a plain tool does it, with the digitised end labels: the
             essential matrix of camera 0 with each other camera (RANSAC, then the pose
             whose points are in front), the other pairs' baselines scaled to the first
             pair's by the depths of the points they share, points triangulated, then one
             scipy.optimize.least_squares bundle adjustment of poses and points (camera 0
             held, the nominal pinhole intrinsics held, plain least squares).

Both rigs are scored the same way on every frame with the true end labels (scoring may read
the truth; the solves never do): each end triangulated with the rig, the RMS of its
reprojection error (px, per observation, 2D) and the wand-length variation (the SD of the
end-to-end length over frames / its mean, %: scale-free). grid_mm: compare_rigs against
the true rig after a similarity (scale included). Medians over the seeds.

Part 2, `--intrinsics`: 6 machine-vision cameras with strong distortion (658x492,
BASLER_658x492_DIST), 1500 wand frames (0, 0.2, 0.5 m), 0.1 px, from nothing. The solver is
given intrinsics without uncertainties, either the exact ones or 0.5 % / 2 px / 0.005 k1
off; each solved with the default (intrinsics refined only where it pays), held
(--fix-intrinsics) and refined (--refine-intrinsics). The monitor run: each camera's
intrinsics calibrated from simulated monitor views (calibkit.calibrate.intrinsic, as
`calibkit intrinsic` does) and refined with those views in the graph. Grid RMS vs the
truth, medians over the seeds.

    python benchmarks/bench_wand_small.py [--seeds 0,1,2,3,4] [--noise 0.5,1.0] [--json out.json]
    python benchmarks/bench_wand_small.py --intrinsics [--seeds 0,1,2] [--frames 1500]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from calibkit.calibrate.compare import compare_rigs, grid_points
from calibkit.calibrate.wand_solve import calibrate
from calibkit.clitools import print_table, write_json
from calibkit.core.camera import BASLER_658x492_DIST, Rig, rotation_from_rvec
from calibkit.core.geometry import RigArrays, rigid_fit, triangulate
from calibkit.synthetic import sim
from calibkit.synthetic.miscalibrate import off_intrinsics

WAND_M = 0.7
FRAMES = 50
FPS = 5.0  # hand-digitised captures keep a few frames a second of a longer dance


def small_scene(seed: int, noise_px: float):
    rig = sim.make_rig(3, 4.0, dist=(0, 0, 0, 0, 0), seed=seed)
    truth = sim.wand_motion(FRAMES, FPS, 4.0, (0.0, WAND_M), seed=seed)
    obs = sim.observe(rig, truth, noise_px=noise_px, seed=seed, blobs="ideal")
    w, h = rig[0].size
    f = (w / 2.0) / np.tan(np.radians(70.0) / 2.0)  # the lens's nominal field of view
    nominal = Rig(tuple(c.replace(fx=f, fy=f, cx=(w - 1) / 2.0, cy=(h - 1) / 2.0,
                                  rvec=np.zeros(3), t=np.zeros(3)) for c in rig))
    return rig, obs, nominal


# ---- the plain reference ---------------------------------------------------------------

def _normalised(rig: Rig, cam: np.ndarray, uv: np.ndarray) -> np.ndarray:
    a = RigArrays.from_rig(rig)
    return np.stack([(uv[:, 0] - a.cx[cam]) / a.fx[cam], (uv[:, 1] - a.cy[cam]) / a.fy[cam]],
                    axis=1)


def reference(obs, nominal: Rig) -> Rig:
    """Essential matrices from camera 0 to each other camera, then one least_squares bundle
    adjustment with the pinhole intrinsics held."""
    lab = obs.select(obs.marker >= 0)  # the digitised ends, as the file labels them
    n_cams = len(nominal)
    pid_key = lab.frame.astype(np.int64) * 2 + lab.marker
    keys, pid = np.unique(pid_key, return_inverse=True)
    cam = lab.camera.astype(np.int64)
    norm = _normalised(nominal, cam, lab.uv)
    row = np.full((len(keys), n_cams), -1)
    row[pid, cam] = np.arange(len(lab))
    R = [np.eye(3)]
    t = [np.zeros(3)]
    depth0 = None
    for k in range(1, n_cams):
        both = np.flatnonzero((row[:, 0] >= 0) & (row[:, k] >= 0))
        a, b = norm[row[both, 0]], norm[row[both, k]]
        f = nominal[k].fx
        E, mask = cv2.findEssentialMat(a, b, np.eye(3), method=cv2.RANSAC, prob=0.999,
                                       threshold=2.0 / f)
        _, Rk, tk, _ = cv2.recoverPose(E[:3], a, b, np.eye(3), mask=mask)
        X = cv2.triangulatePoints(np.hstack([np.eye(3), np.zeros((3, 1))]),
                                  np.hstack([Rk, tk]), a.T, b.T)
        d = X[2] / X[3]  # depths in camera 0 at a baseline of 1
        if depth0 is None:
            depth0 = np.full(len(keys), np.nan)
            depth0[both] = d
            scale = 1.0
        else:
            common = np.isfinite(depth0[both]) & (d > 0)
            scale = float(np.median(depth0[both][common] / d[common])) if common.any() else 1.0
        R.append(Rk)
        t.append(tk.ravel() * scale)
    start = Rig(tuple(c.replace(R=Rk, t=tk) for c, Rk, tk in zip(nominal, R, t, strict=True)))
    xyz = triangulate(start, pid, cam, lab.uv, n_points=len(keys), ray_distance=False).xyz
    ok = np.isfinite(xyz).all(axis=1)
    xyz[~ok] = np.nanmedian(xyz, axis=0)
    fx = np.array([c.fx for c in nominal])[cam]
    fy = np.array([c.fy for c in nominal])[cam]
    cx = np.array([c.cx for c in nominal])[cam]
    cy = np.array([c.cy for c in nominal])[cam]
    n_pose = 6 * (n_cams - 1)
    x0 = np.concatenate([np.concatenate([cv2.Rodrigues(r)[0].ravel(), tt])
                         for r, tt in zip(R[1:], t[1:], strict=True)] + [xyz.ravel()])

    def residual(x):
        poses = np.vstack([np.zeros((1, 6)), x[:n_pose].reshape(-1, 6)])
        pts = x[n_pose:].reshape(-1, 3)
        rot = np.stack([rotation_from_rvec(p[:3]) for p in poses])
        pc = np.einsum("nij,nj->ni", rot[cam], pts[pid]) + poses[cam, 3:]
        u = fx * pc[:, 0] / pc[:, 2] + cx
        v = fy * pc[:, 1] / pc[:, 2] + cy
        return np.concatenate([u - lab.uv[:, 0], v - lab.uv[:, 1]])

    sparsity = lil_matrix((2 * len(lab), len(x0)), dtype=int)
    obs_rows = np.arange(len(lab))
    for axis in range(2):
        r = obs_rows + axis * len(lab)
        moving = cam > 0
        for j in range(6):
            sparsity[r[moving], 6 * (cam[moving] - 1) + j] = 1
        for j in range(3):
            sparsity[r, n_pose + 3 * pid + j] = 1
    fit = least_squares(residual, x0, jac_sparsity=sparsity, method="trf", x_scale="jac",
                        max_nfev=200)
    poses = fit.x[:n_pose].reshape(-1, 6)
    cams = [nominal[0].replace(R=np.eye(3), t=np.zeros(3))]
    cams += [nominal[k + 1].replace(rvec=p[:3], t=p[3:]) for k, p in enumerate(poses)]
    return Rig(tuple(cams))


# ---- the one scorer -------------------------------------------------------------------

def score(rig: Rig, obs, true_rig: Rig) -> dict:
    """Every frame's two ends (true labels) triangulated with `rig`: reprojection RMS (px,
    2D per observation) and the end-to-end length's SD / mean (%); grid RMS vs the truth."""
    lab = obs.select(obs.marker >= 0)
    index = {n: i for i, n in enumerate(rig.names)}
    cam = np.array([index[n] for n in lab.camera_names])[lab.camera]
    keys, pid = np.unique(lab.frame.astype(np.int64) * 2 + lab.marker, return_inverse=True)
    tri = triangulate(rig, pid, cam, lab.uv, n_points=len(keys), ray_distance=False)
    proj, _ = RigArrays.from_rig(rig).project(cam, tri.xyz[pid])
    err = np.linalg.norm(lab.uv - proj, axis=1)
    frame, end = keys // 2, keys % 2
    ends = np.full((frame.max() + 1, 2, 3), np.nan)
    ends[frame, end] = tri.xyz
    length = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
    length = length[np.isfinite(length)]
    return {"rms_px": float(np.sqrt(np.nanmean(err**2))),
            "variation_pct": float(100 * np.std(length, ddof=1) / np.mean(length)),
            "grid_mm": compare_rigs(true_rig, rig, align=True)["grid_rms_mm"]}


def best_fit_grid_mm(true_rig: Rig, rig: Rig, grid: np.ndarray | None = None) -> float:
    """Grid RMS (mm) with `rig` aligned by the similarity that best maps its triangulated
    grid onto the true grid (default: compare's grid over the true rig's volume), not by
    the camera centres: a centre's error along its camera's axis (where it trades against
    the focal length, poorly determined once intrinsics are free) then moves no grid point."""
    grid = grid_points(true_rig) if grid is None else grid
    point, camera, uv = [], [], []
    index = {n: i for i, n in enumerate(rig.names)}
    for cam in true_rig:
        px, front = cam.project(grid)
        vis = np.flatnonzero(front & cam.in_image(px))
        point.append(vis)
        camera.append(np.full(len(vis), index[cam.name]))
        uv.append(px[vis])
    point, camera, uv = map(np.concatenate, (point, camera, uv))
    xyz = triangulate(rig, point, camera, uv, n_points=len(grid), ray_distance=False).xyz
    ok = np.isfinite(xyz).all(axis=1)
    R, t, s = rigid_fit(xyz[ok], grid[ok], scale=True)
    d = np.linalg.norm(s * xyz[ok] @ R.T + t - grid[ok], axis=1)
    return float(np.sqrt(np.mean(d**2)) * 1000.0)


def _shape(report: dict) -> tuple[float, float]:
    """The report's predicted shape uncertainty (mm) and, where the default kept
    intrinsics, what refining them would have left."""
    s = report.get("shape_uncertainty", {})
    return float(s.get("grid_rms_mm", np.nan)), float(s.get("if_refined_mm", np.nan))


def run_small(seed: int, noise_px: float) -> dict:
    true_rig, obs, nominal = small_scene(seed, noise_px)
    t0 = time.process_time()
    cal = calibrate(obs, nominal, (0.0, 1.0), holdout=0.1, seed=seed, length_known=False)
    t1 = time.process_time()
    ref = reference(obs, nominal)
    t2 = time.process_time()
    ours, theirs = score(cal.rig, obs, true_rig), score(ref, obs, true_rig)
    refined = sum(c["chosen"] == "refined" for c in cal.report["intrinsics"]["cameras"])
    return {"seed": seed, "noise_px": noise_px,
            **{f"ours_{k}": v for k, v in ours.items()},
            **{f"ref_{k}": v for k, v in theirs.items()},
            "ours_cpu_s": t1 - t0, "ref_cpu_s": t2 - t1, "ours_grade": cal.report["grade"],
            "refined_cameras": refined}


def small_table(runs: list[dict]) -> None:
    rows = []
    for noise in sorted({r["noise_px"] for r in runs}):
        g = [r for r in runs if r["noise_px"] == noise]

        def med(key, g=g):
            return float(np.median([r[key] for r in g]))
        for who in ("ours", "ref"):
            rows.append([noise, "calibkit wand" if who == "ours" else "plain reference",
                         med(f"{who}_rms_px"), med(f"{who}_variation_pct"),
                         med(f"{who}_grid_mm"), med(f"{who}_cpu_s"),
                         sum(r["ours_rms_px"] <= r["ref_rms_px"] * 1.0005 for r in g)
                         if who == "ours" else "",
                         sum(r["ours_variation_pct"] <= r["ref_variation_pct"] for r in g)
                         if who == "ours" else ""])
    print_table(rows, ["noise px", "solver", "reproj RMS px", "length var %", "grid mm",
                       "cpu s", "seeds rms<=ref", "seeds var<=ref"])


# ---- part 2: intrinsics without uncertainties -----------------------------------------

def _monitor_intrinsics(rig: Rig, seed: int):
    """Each camera's intrinsics from simulated monitor views, as `calibkit intrinsic` gives
    them (with their standard deviations), and those views for the wand's graph."""
    from calibkit.calibrate import plane_views
    from calibkit.calibrate.intrinsic import calibrate as calibrate_intrinsic
    from calibkit.calibrate.intrinsic import monitor_plane_view
    from calibkit.synthetic.monitor import MonitorSimConfig, make_monitor_sim, projected_dots
    from projector.patterns import coded_schedule

    views, cams, quality = None, [], {}
    for k, cam in enumerate(rig):
        cfg = MonitorSimConfig(seed=seed + 40 + k)
        schedule = coded_schedule(cfg.screen_px, 80.0, 2, 6.0)
        rng = np.random.default_rng(seed + 40 + k)
        with make_monitor_sim(8, cam.size, seed + 40 + k, cfg, camera=cam, fill=0.8) as mon:
            mv = [monitor_plane_view(projected_dots(cam, view, schedule.points_xy,
                                                    schedule.radius_px, cfg.pixel_pitch_mm,
                                                    0.05, rng), schedule, cfg.pixel_pitch_mm)
                  for view in mon.views]
        result = calibrate_intrinsic(mv, cam.size, cam.name,
                                     dot_radius_m=schedule.radius_px * cfg.pixel_pitch_mm / 1e3)
        views = plane_views.merge(views, plane_views.from_result(cam.name, result.views,
                                                                 result))
        cams.append(result.camera.replace(rvec=np.zeros(3), t=np.zeros(3)))
        quality[cam.name] = {"std": result.std}
    return Rig(tuple(cams), {"intrinsic": quality}, {"volume_m": 4.0}), views


def run_intrinsics(seed: int, frames: int) -> list[dict]:
    rig = sim.make_rig(6, 4.0, size=(658, 492), dist=BASLER_658x492_DIST, seed=seed)
    truth = sim.wand_motion(frames, 100.0, 4.0, (0.0, 0.2, 0.5), seed=seed)
    obs = sim.observe(rig, truth, noise_px=0.1, seed=seed)
    bare = Rig(tuple(c.replace(rvec=np.zeros(3), t=np.zeros(3)) for c in rig),
               meta={"volume_m": 4.0})
    off = off_intrinsics(bare, 0.005, 2.0, 0.005, np.random.default_rng(seed + 1000))
    truth_rig = Rig(tuple(rig.cameras), meta={"volume_m": 4.0})  # the scorer's grid volume
    out = []
    cases = [("exact", bare, mode) for mode in ("default", "fix", "refine")]
    cases += [("0.5%/2px", off, mode) for mode in ("default", "fix", "refine")]
    for given, intr, mode in cases:
        refine = {"default": None, "fix": False, "refine": True}[mode]
        t0 = time.process_time()
        cal = calibrate(obs, intr, (0.0, 0.2, 0.5), refine_intrinsics=refine, seed=seed)
        cpu = time.process_time() - t0
        out.append({"seed": seed, "given": given, "mode": mode,
                    "grid_mm": compare_rigs(rig, cal.rig)["grid_rms_mm"],
                    "best_fit_mm": best_fit_grid_mm(truth_rig, cal.rig),
                    "predicted_mm": _shape(cal.report)[0],
                    "if_refined_mm": _shape(cal.report)[1],
                    "refined": sum(c["chosen"] == "refined"
                                   for c in cal.report["intrinsics"]["cameras"]),
                    "grade": cal.report["grade"], "cpu_s": cpu})
        print(out[-1], file=sys.stderr, flush=True)
    monitor, views = _monitor_intrinsics(rig, seed)
    t0 = time.process_time()
    cal = calibrate(obs, monitor, (0.0, 0.2, 0.5), seed=seed, target_views=views)
    cpu = time.process_time() - t0
    out.append({"seed": seed, "given": "monitor", "mode": "views",
                "grid_mm": compare_rigs(rig, cal.rig)["grid_rms_mm"],
                "best_fit_mm": best_fit_grid_mm(truth_rig, cal.rig),
                "predicted_mm": _shape(cal.report)[0], "if_refined_mm": float("nan"),
                "refined": sum(c["chosen"] == "refined"
                               for c in cal.report["intrinsics"]["cameras"]),
                "grade": cal.report["grade"], "cpu_s": cpu})
    print(out[-1], file=sys.stderr, flush=True)
    return out


def intrinsics_table(runs: list[dict]) -> None:
    rows = []
    for given, mode in (("exact", "fix"), ("exact", "default"), ("exact", "refine"),
                        ("0.5%/2px", "fix"), ("0.5%/2px", "default"), ("0.5%/2px", "refine"),
                        ("monitor", "views")):
        g = [r for r in runs if r["given"] == given and r["mode"] == mode]
        if not g:
            continue
        grid = np.array([r["grid_mm"] for r in g])

        def med(key, g=g):
            return float(np.median([r[key] for r in g]))
        rows.append([given, mode, float(np.median(grid)), float(grid.max()),
                     med("best_fit_mm"), med("predicted_mm"), med("if_refined_mm"),
                     med("refined"), " ".join(sorted({r["grade"] for r in g})), med("cpu_s")])
    print_table(rows, ["intrinsics given", "solve", "grid mm median", "grid mm worst",
                       "grid mm best fit", "predicted mm", "if refined mm",
                       "cameras refined", "grades", "cpu s"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default=None)
    ap.add_argument("--noise", default="0.5,1.0")
    ap.add_argument("--intrinsics", action="store_true")
    ap.add_argument("--frames", type=int, default=1500)
    ap.add_argument("--json")
    args = ap.parse_args()
    runs: list[dict] = []
    if args.intrinsics:
        for seed in [int(s) for s in (args.seeds or "0,1,2").split(",")]:
            runs += run_intrinsics(seed, args.frames)
        intrinsics_table(runs)
    else:
        for noise in [float(v) for v in args.noise.split(",")]:
            for seed in [int(s) for s in (args.seeds or "0,1,2,3,4").split(",")]:
                runs.append(run_small(seed, noise))
                print(runs[-1], file=sys.stderr, flush=True)
        small_table(runs)
    print(f"load average at the end: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    if args.json:
        write_json(args.json, runs)


if __name__ == "__main__":
    main()
