"""Wand calibration from nothing: solve time and accuracy against the simulator's truth, and a
scipy least_squares baseline on the same model.

Scenes (sim.make_rig, 4 m volume, 640x480 webcams): 3000 wand frames in the solve (3333
simulated, 10 % held out), from nothing (essential matrix, PnP, wand scale, then the GTSAM
bundle adjustment with outlier rejection):

  A  8 cameras, 0.1 px noise
  B  8 cameras, 0.5 px noise, 5 % outlier blobs: stray blobs (5 % of all blobs) and 5 % of
     the wand's own blobs thrown 1-4 px off (a merged reflection), which often still pass
     identification and must be caught by the solve
  C  16 cameras, 0.1 px noise

Figures, each the median over `--repeats` runs with different seeds:
  solve_s       the bundle adjustment (graph building, LM, re-solve), wall clock; and
                solve_cpu_s, its CPU time (one thread: the wall time on a quiet core, the
                figure to hold against the target when the machine is shared)
  total_s       everything: identification, initialisation, solve, evaluation, marginals;
                total_cpu_s its CPU time
  iterations    Levenberg-Marquardt iterations over both rounds
  rms/noise     per-axis RMS of the solve's inlier residuals over the injected noise
  rms/true      the same RMS over the one the true rig gives on the same frames
  len_bias_mm   mean wand-length error on held-out frames (what the scale got wrong)
  len_rms_mm    per-frame wand-length error RMS on held-out frames, and /true: over the
                same figure with the true rig (the noise floor of single-frame triangulation)
  marker_mm     held-out markers triangulated with the solved rig (mapped into the true frame
                by the aligning similarity) vs their true positions, RMS; marker/true: over
                the same with the true rig (the design asks <= 1.2)
  grid_mm       calibkit.calibrate.compare.compare_rigs(true, solved)["grid_rms_mm"]
                (similarity-aligned)
  scale_ppm     the aligning similarity's scale error

Scenes A-C hold the intrinsics at the simulator's (refine_intrinsics=False): they measure
the solver (its speed, and how close it gets to the best possible on a known model).

Baseline (scene A, same seed, same start and same model: poses and points, Huber loss, the
wand's distances, the reference camera held): scipy.optimize.least_squares, method 'trf',
Jacobian by finite differences with its sparsity given, as open projects do.

Intrinsics as a calibration leaves them (`--intrinsics`): 8 cameras (and `--cameras`), 0.1
px, 3333 frames (3000 solved), from nothing. The solver gets the intrinsics perturbed, never
the truth: every camera's focal lengths off by the given share (random sign), its principal
point by the given pixels (random direction), k1 by 0.005 (random sign); the truth goes to
the scorer only. Each perturbation is solved with the intrinsics held and refined (the
default; the rig carries no standard deviations, so the priors are the defaults of
calibkit.calibrate.intrinsic_prior), beside the true intrinsics as the baseline, all in one process.
Figures, median and worst over `--repeats` seeds:
  pos_mm     the largest camera position error after the similarity alignment
  grid_mm    compare_rigs grid RMS vs the truth
  held_mm    held-out wand length error RMS (every marker pair of every held-out frame)
  gross      held-out frames whose end-to-end length is off by more than 10 mm (counted,
             not dropped: held_mm includes them)
  grade      the report's grade (the worst over seeds)
  solve_s    the bundle adjustment, wall clock; cpu_s: the whole calibration's CPU time

    python benchmarks/bench_wand.py [--repeats 3] [--scenes ABC] [--no-baseline] [--json out.json]
    python benchmarks/bench_wand.py --intrinsics [--repeats 3] [--cameras 8] [--json out.json]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from calibkit.calibrate import bundle
from calibkit.calibrate.compare import compare_rigs
from calibkit.calibrate.wand_report import evaluate
from calibkit.calibrate.wand_solve import calibrate
from calibkit.clitools import print_table, write_json
from calibkit.core.camera import Rig
from calibkit.core.geometry import RigArrays
from calibkit.synthetic import sim
from calibkit.synthetic.miscalibrate import off_intrinsics

SPACING = (0.0, 0.2, 0.5)
SCENES = {
    "A": dict(cameras=8, noise=0.1, outliers=0.0),
    "B": dict(cameras=8, noise=0.5, outliers=0.05),
    "C": dict(cameras=16, noise=0.1, outliers=0.0),
}


def make_scene(cameras: int, noise: float, outliers: float, seed: int, frames: int = 3333):
    rig = sim.make_rig(cameras, 4.0, seed=seed)
    truth = sim.wand_motion(frames, 100.0, 4.0, SPACING, seed)
    ghosts = outliers * 3.0 / max(1e-9, 1.0 - outliers)  # 5 % of blobs are strays
    obs = sim.observe(rig, truth, noise_px=noise, ghosts_per_camera=ghosts, seed=seed)
    if outliers > 0:
        rng = np.random.default_rng(seed + 99)
        hit = (obs.marker >= 0) & (rng.random(len(obs)) < outliers)
        angle = rng.uniform(0, 2 * np.pi, hit.sum())
        obs.uv[hit] += rng.uniform(1, 4, hit.sum())[:, None] * np.stack(
            [np.cos(angle), np.sin(angle)], axis=1)
    return rig, obs, truth


def run(scene: str, seed: int) -> tuple[dict, object]:
    cfg = SCENES[scene]
    rig, obs, truth = make_scene(cfg["cameras"], cfg["noise"], cfg["outliers"], seed)
    start, start_cpu = time.perf_counter(), time.process_time()
    cal = calibrate(obs, rig, SPACING, holdout=0.1, seed=seed, refine_intrinsics=False,
                    options=bundle.BundleOptions(noise_px=max(0.5, cfg["noise"])))
    total, total_cpu = time.perf_counter() - start, time.process_time() - start_cpu
    res = cal.bundle
    inl = res.residual_px[res.inlier]
    rms = float(np.sqrt(np.mean(inl**2)))
    # the same frames and observations with the true rig (the best any calibration can do)
    camera_of = np.array([rig.index(n) for n in obs.camera_names])
    held_frames = cal.held_frames
    true_held = evaluate(rig, cal.wand, _spec(), held_frames, camera_of)
    true_rms = _true_rms(rig, res)
    cmp = compare_rigs(rig, cal.rig, align=True)
    s = float(cmp["alignment"]["scale"]) if "scale" in cmp.get("alignment", {}) else np.nan
    h = cal.report["held_out"]
    return {
        "scene": scene, "seed": seed, "cameras": cfg["cameras"], "noise_px": cfg["noise"],
        "solve_s": res.time_s, "solve_cpu_s": res.cpu_s, "total_s": total,
        "total_cpu_s": total_cpu, "iterations": res.iterations,
        "rms_px": rms, "rms_over_noise": rms / cfg["noise"], "rms_over_true": rms / true_rms,
        "len_bias_mm": h["wand_length_error_mean_mm"], "len_rms_mm": h["wand_length_error_rms_mm"],
        "len_rms_over_true": h["wand_length_error_rms_mm"] / true_held["wand_length_error_rms_mm"],
        **_marker_errors(rig, cal, truth, held_frames, camera_of),
        "grid_mm": cmp["grid_rms_mm"], "scale_ppm": (s - 1.0) * 1e6,
        "max_camera_mm": max(c["position_mm"] for c in cmp["cameras"]),
        "outliers_dropped": int(np.sum(~res.inlier)), "grade": cal.report["grade"],
    }, (rig, cal)


def _marker_errors(rig: Rig, cal, truth, frames: np.ndarray, camera_of: np.ndarray) -> dict:
    """Held-out markers triangulated with the solved rig (mapped into the true frame by the
    similarity of compare_rigs) and with the true rig, against the true positions: RMS mm
    and their ratio (the design's "within 1.2x of the error with the true cameras")."""
    from calibkit.calibrate.compare import similarity_from_rigs
    from calibkit.calibrate.wand import point_index
    from calibkit.core.geometry import triangulate

    w = cal.wand.select(np.isin(cal.wand.frame, frames))
    pidx, pinfo = point_index(w, 3)
    names = [c.name for c in cal.rig]
    est_of = np.array([names.index(n) if n in names else -1 for n in w.camera_names])
    keep = est_of[w.camera] >= 0
    R, t, s = similarity_from_rigs([rig[n] for n in names], list(cal.rig))
    tkey = truth.frame * 3 + truth.marker
    order = np.argsort(tkey)
    true_xyz = truth.xyz[order[np.searchsorted(tkey[order], pinfo[:, 0] * 3 + pinfo[:, 1])]]
    out = {}
    for label, r, cams in (("est", cal.rig, est_of), ("true", rig, camera_of)):
        tri = triangulate(r, pidx[keep], cams[w.camera[keep]], w.uv[keep],
                          n_points=len(pinfo), ray_distance=False).xyz
        if label == "est":
            tri = s * tri @ R.T + t
        d = np.linalg.norm(tri - true_xyz, axis=1)
        out[f"marker_{label}_mm"] = float(np.sqrt(np.nanmean(d**2)) * 1000)
    out["marker_over_true"] = out["marker_est_mm"] / out["marker_true_mm"]
    return out


def _spec():
    from calibkit.calibrate.wand import WandSpec

    return WandSpec(SPACING)


def _true_rms(rig: Rig, res) -> float:
    """Per-axis RMS of the same inlier observations, points re-triangulated with the true rig
    (k3-free measurements, as the solve saw them)."""
    from calibkit.core.geometry import triangulate

    data = res.data
    names = [c.name for c in res.rig]
    true = Rig(tuple(rig[n].replace(dist=rig[n].dist * [1, 1, 1, 1, 0]) for n in names))
    m = res.inlier
    tri = triangulate(true, data.obs_point[m], data.obs_camera[m], data.obs_uv[m],
                      n_points=len(data.xyz), ray_distance=False)
    proj, _ = RigArrays.from_rig(true).project(data.obs_camera[m], tri.xyz[data.obs_point[m]])
    r = data.obs_uv[m] - proj
    return float(np.sqrt(np.nanmean(r**2)))


# ---- intrinsics as a calibration leaves them ------------------------------------------------

LEVELS = {  # name: (focal share, principal point px, k1)
    "true": (0.0, 0.0, 0.0),
    "0.1%/0.5px": (0.001, 0.5, 0.005),
    "0.5%/2px": (0.005, 2.0, 0.005),
}


def perturbed(rig: Rig, focal_rel: float, centre_px: float, k1: float, seed: int) -> Rig:
    """The rig's intrinsics as an intrinsic calibration might leave them; the poses are
    dropped (the solve starts from nothing)."""
    off = off_intrinsics(rig, focal_rel, centre_px, k1, np.random.default_rng(seed + 1000))
    return Rig(tuple(c.replace(rvec=np.zeros(3), t=np.zeros(3)) for c in off),
               meta={"volume_m": rig.meta.get("volume_m")})


def run_intrinsics(cameras: int, seed: int) -> list[dict]:
    rig, obs, _truth = make_scene(cameras, 0.1, 0.0, seed)
    out = []
    for level, (f, c, k) in LEVELS.items():
        given = perturbed(rig, f, c, k, seed)
        for refine in ((False,) if level == "true" else (False, True)):
            t0 = time.process_time()
            cal = calibrate(obs, given, SPACING, refine_intrinsics=refine, seed=seed)
            cpu = time.process_time() - t0
            cmp = compare_rigs(rig, cal.rig, align=True)
            end_to_end = np.asarray(cal.held["frame_length_error_mm"])
            out.append({"level": level, "refine": refine, "seed": seed, "cameras": cameras,
                        "pos_mm": max(r["position_mm"] for r in cmp["cameras"]),
                        "grid_mm": cmp["grid_rms_mm"],
                        "held_mm": cal.report["held_out"]["wand_length_error_rms_mm"],
                        "gross": int(np.sum(~(np.abs(end_to_end) <= 10.0))),
                        "held_frames": int(len(end_to_end)),
                        "grade": cal.report["grade"], "solve_s": cal.bundle.time_s,
                        "cpu_s": cpu, **{f"syst_{k}": v for k, v in
                                         cal.report["systematic"].items()}})
            print(f"{cameras} cams seed {seed} {level} {'refined' if refine else 'held'}: "
                  + ", ".join(f"{key}={val:.4g}" if isinstance(val, float) else f"{key}={val}"
                              for key, val in out[-1].items()), file=sys.stderr, flush=True)
    return out


def intrinsics_table(runs: list[dict]) -> None:
    order = ["excellent", "good", "usable", "poor", "failed"]
    rows = []
    for cams in sorted({r["cameras"] for r in runs}):
        for level in LEVELS:
            for refine in (False, True):
                g = [r for r in runs if r["cameras"] == cams and r["level"] == level
                     and r["refine"] == refine]
                if not g:
                    continue

                def mw(key, g=g):
                    v = np.array([r[key] for r in g], dtype=float)
                    return f"{np.median(v):.3f} / {v.max():.3f}"
                rows.append([cams, level, "refined" if refine else "held", mw("pos_mm"),
                             mw("grid_mm"), mw("held_mm"),
                             f"{sum(r['gross'] for r in g)} of "
                             f"{sum(r['held_frames'] for r in g)}",
                             max((r["grade"] for r in g), key=order.index),
                             f"{np.median([r['solve_s'] for r in g]):.1f}",
                             f"{np.median([r['cpu_s'] for r in g]):.1f}"])
    print_table(rows, ["cams", "intrinsics in", "intrinsics", "pos_mm med/worst",
                       "grid_mm med/worst", "held_mm med/worst", "gross (>10 mm)",
                       "grade (worst)", "solve_s", "cpu_s"])


# ---- the scipy baseline ----------------------------------------------------------------------

def scipy_baseline(data: bundle.BundleData, options: bundle.BundleOptions,
                   use: np.ndarray, max_nfev: int | None = 500) -> tuple[Rig, bool, int]:
    """least_squares on the same model as the GTSAM graph (fixed intrinsics)."""
    rig = data.rig
    n_cams = len(rig)
    ref = options.reference_camera
    free = [c for c in range(n_cams) if c != ref]
    pt, cam, uv = data.obs_point[use], data.obs_camera[use], data.obs_uv[use]
    n_seen = np.bincount(pt, minlength=len(data.xyz))
    active = np.flatnonzero(n_seen >= 2)
    local = np.full(len(data.xyz), -1)
    local[active] = np.arange(len(active))
    keep = local[pt] >= 0
    pt, cam, uv = local[pt[keep]], cam[keep], uv[keep]
    ek = (local[data.edge[:, 0]] >= 0) & (local[data.edge[:, 1]] >= 0)
    e0, e1 = local[data.edge[ek, 0]], local[data.edge[ek, 1]]
    elen = data.edge_length_m[ek]
    arrays = RigArrays.from_rig(rig)
    n_free = len(free)
    slot = np.full(n_cams, -1)
    slot[free] = np.arange(n_free)
    x0 = np.concatenate([np.concatenate([[*rig[c].rvec, *rig[c].t] for c in free]),
                         data.xyz[active].ravel()])
    sigma_px, sigma_len = options.noise_px, options.length_sigma_m

    def unpack(x):
        R = arrays.R.copy()
        t = arrays.t.copy()
        p = x[: 6 * n_free].reshape(-1, 6)
        R[free] = Rotation.from_rotvec(p[:, :3]).as_matrix()
        t[free] = p[:, 3:]
        return R, t, x[6 * n_free:].reshape(-1, 3)

    def fun(x):
        R, t, xyz = unpack(x)
        ra = RigArrays(R, t, arrays.centre, arrays.fx, arrays.fy, arrays.cx, arrays.cy,
                       arrays.skew, arrays.dist)
        proj, _ = ra.project(cam, xyz[pt])
        r_px = ((proj - uv) / sigma_px).ravel()
        r_len = (np.linalg.norm(xyz[e0] - xyz[e1], axis=1) - elen) / sigma_len
        return np.concatenate([r_px, r_len])

    m_px, m_len = 2 * len(pt), len(e0)
    sparsity = lil_matrix((m_px + m_len, len(x0)), dtype=np.int8)
    rows = np.arange(len(pt))
    for k in range(2):
        r = 2 * rows + k
        has = slot[cam] >= 0
        for j in range(6):
            sparsity[r[has], 6 * slot[cam[has]] + j] = 1
        for j in range(3):
            sparsity[r, 6 * n_free + 3 * pt + j] = 1
    er = m_px + np.arange(m_len)
    for j in range(3):
        sparsity[er, 6 * n_free + 3 * e0 + j] = 1
        sparsity[er, 6 * n_free + 3 * e1 + j] = 1
    sol = least_squares(fun, x0, jac_sparsity=sparsity.tocsr(), method="trf", loss="huber",
                        f_scale=options.huber_k, x_scale="jac", max_nfev=max_nfev)
    R, t, _ = unpack(sol.x)
    cams = tuple(c.replace(R=R[k], t=t[k]) for k, c in enumerate(rig))
    return Rig(cams, meta=dict(rig.meta)), bool(sol.status > 0), int(sol.nfev)


def _sse(rig: Rig, data: bundle.BundleData) -> float:
    """Sum of squared reprojection errors with every point re-triangulated by `rig`: the
    same yardstick for both solvers (lower is a better optimum of the same model)."""
    from calibkit.core.geometry import triangulate

    tri = triangulate(rig, data.obs_point, data.obs_camera, data.obs_uv,
                      n_points=len(data.xyz), ray_distance=False)
    proj, _ = RigArrays.from_rig(rig).project(data.obs_camera, tri.xyz[data.obs_point])
    return float(np.nansum((proj - data.obs_uv) ** 2))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scenes", default="ABC")
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument("--baseline-frames", type=int, default=150,
                    help="wand frames in the baseline comparison (scipy is slow)")
    ap.add_argument("--json")
    ap.add_argument("--intrinsics", action="store_true",
                    help="the intrinsics table instead of scenes A-C")
    ap.add_argument("--cameras", default="8", help="--intrinsics: cameras, e.g. 6,8")
    args = ap.parse_args()
    if args.intrinsics:
        runs = [r for cams in (int(c) for c in args.cameras.split(","))
                for k in range(args.repeats) for r in run_intrinsics(cams, seed=k)]
        intrinsics_table(runs)
        if args.json:
            write_json(args.json, {"runs": runs})
        return
    rows, results = [], []
    baseline = None
    for scene in args.scenes:
        runs = []
        for k in range(args.repeats):
            fig, (rig, cal) = run(scene, seed=k)
            print(f"scene {scene} seed {k}: " + ", ".join(
                f"{key}={val:.4g}" if isinstance(val, float) else f"{key}={val}"
                for key, val in fig.items()), file=sys.stderr, flush=True)
            runs.append(fig)
            results.append(fig)
            if scene == "A" and k == 0 and not args.no_baseline:
                baseline = _baseline(rig, cal, args.baseline_frames)
        med = {key: float(np.median([r[key] for r in runs])) for key in runs[0]
               if isinstance(runs[0][key], (int, float)) and key not in ("seed",)}
        rows.append([scene, int(med["cameras"]), med["noise_px"], med["solve_s"],
                     med["solve_cpu_s"], med["total_s"], med["total_cpu_s"],
                     int(med["iterations"]), med["rms_over_noise"], med["rms_over_true"],
                     med["len_bias_mm"], med["len_rms_mm"], med["len_rms_over_true"],
                     med["marker_est_mm"], med["marker_over_true"],
                     med["grid_mm"], med["scale_ppm"], int(med["outliers_dropped"])])
    print_table(rows, ["scene", "cams", "noise_px", "solve_s", "solve_cpu_s", "total_s",
                       "total_cpu_s", "iterations", "rms/noise",
                       "rms/true", "len_bias_mm", "len_rms_mm", "len/true", "marker_mm",
                       "marker/true", "grid_mm", "scale_ppm", "dropped"])
    if baseline is not None:
        print()
        b = baseline
        print_table([["gtsam LM", b["gtsam_s"], b["gtsam_grid_mm"], b["gtsam_sse_px2"], 1.0,
                      1.0, "yes"],
                     ["scipy least_squares", b["scipy_s"], b["scipy_grid_mm"],
                      b["scipy_sse_px2"], b["scipy_s"] / b["gtsam_s"],
                      b["scipy_grid_mm"] / b["gtsam_grid_mm"],
                      f"{'yes' if b['scipy_converged'] else 'no'} ({b['scipy_nfev']} evals)"]],
                    [f"scene A, seed 0, {b['frames']} frames", "solve_s", "grid_mm", "sse_px2",
                     "time ratio", "grid ratio", "converged"])
    if args.json:
        write_json(args.json, {"runs": results, "baseline": baseline})


def _baseline(rig: Rig, cal, n_frames: int) -> dict:
    """The same problem (same start, same inlier rows of the first `n_frames` frames, one
    round) solved by GTSAM and by scipy."""
    from calibkit.calibrate.wand import point_index

    data = cal.bundle.data
    opts = bundle.BundleOptions(noise_px=cal.bundle.noise_px, rounds=1,
                                reference_camera=cal.bundle.options.reference_camera)
    solved = cal.wand.select(~np.isin(cal.wand.frame, cal.held_frames))
    _, pinfo = point_index(solved.select(np.isin(solved.camera, np.flatnonzero(
        np.isin(cal.wand.camera_names, [c.name for c in cal.bundle.rig])))), 3)
    frames = np.unique(pinfo[:, 0])[:n_frames]
    use = cal.bundle.inlier & np.isin(pinfo[data.obs_point, 0], frames)
    clean = bundle.BundleData(**{**data.__dict__, "obs_point": data.obs_point[use],
                                 "obs_camera": data.obs_camera[use],
                                 "obs_uv": data.obs_uv[use]})
    t0 = time.perf_counter()
    g = bundle.solve(clean, opts)
    gtsam_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    s_rig, converged, nfev = scipy_baseline(clean, opts,
                                            np.ones(len(clean.obs_point), dtype=bool))
    scipy_s = time.perf_counter() - t0
    names = [c.name for c in g.rig]
    true = Rig(tuple(rig[n] for n in names), meta=dict(rig.meta))
    s_rig = Rig(tuple(c.replace(dist=t.dist) for c, t in zip(s_rig, true, strict=True)),
                meta=dict(rig.meta))
    return {"frames": int(len(frames)), "gtsam_s": gtsam_s, "scipy_s": scipy_s,
            "scipy_nfev": nfev, "scipy_converged": converged,
            "gtsam_sse_px2": _sse(g.rig, clean), "scipy_sse_px2": _sse(s_rig, clean),
            "gtsam_grid_mm": compare_rigs(true, g.rig)["grid_rms_mm"],
            "scipy_grid_mm": compare_rigs(true, s_rig)["grid_rms_mm"]}


if __name__ == "__main__":
    main()
