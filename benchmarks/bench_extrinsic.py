"""Projector extrinsics: camera pose errors, ray distances and capture time on the simulator.

Scene (the one docs/extrinsic.md sets its targets on): 6 cameras round a 4 x 4 m floor, a
ceiling projector (1280 x 800, 60 degrees, k1 = 0.02), a 1.6 x 0.9 m table at 0.75 m; 0.2 px
centroid noise, 5 mm (per axis) error in the tape-measured reference points (16 on the
floor, 5 on the table) and 2 mm (SD) in the tape's table height, as `extrinsic --sim` draws
them. Each variant runs on `--seeds` scenes (different rigs, projector placements and tape
errors); the table gives the median and the worst camera of each run, the median over runs
of the mean ray distance at the floor and at 1.7 m (points seen exactly by the true cameras,
cast back by the calibrated ones), the median |scale error| `calibkit compare` finds (ppm),
and the median solve time. Ratios are against the baseline run in the same process: floor
dots only, each camera on its own (PnP), the way a projector-only calibration without the
table would. A second table follows the table height per variant: the tape's error, the
dots' own measure of it (extrinsic_solve.measure_table_height), the two weighted (what the
dots file carries) and the height the poses used, RMS over scenes against the truth, and
the dots' error over their stated sigma. `--wand N` joins a wand dance to the plane dots
as the file passes them on, and again with the table at the tape's height (the baseline).

The estimate starts from estimated intrinsics, as a user's does: each camera calibrated by
the intrinsic step on its own simulated monitor views (calibkit.calibrate.intrinsic.calibrate on the
captured dots, as `calibkit intrinsic --sim --no-render` with its defaults: 6 views, dots
every 80 screen px shifted twice, 0.035 px centroid noise), poses unknown. One row,
labelled as such, repeats the default variant from the simulator's true intrinsics: the
baseline that shows what the intrinsics' errors cost, never what a user gets.

The 2D path (dots projected with noise) is used for the error figures; `--render` adds a
run that renders every camera frame and detects and decodes the dots (slow), and reports
its camera frames, i.e. the capture time at 30 fps.

    python benchmarks/bench_extrinsic.py [--seeds 10] [--render] [--json out.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np

from calibkit.calibrate import extrinsic_capture as exc
from calibkit.calibrate import extrinsic_reference as exr
from calibkit.calibrate import extrinsic_solve as exs
from calibkit.calibrate.compare import compare_rigs
from calibkit.clitools import print_table, write_json
from calibkit.synthetic import projector as sp
from calibkit.synthetic.extrinsic_sim import TAPE_HEIGHT_ERROR_MM
from projector.patterns import coded_schedule

PROJ = (1280, 800)
VOLUME = 4.0


@dataclasses.dataclass(frozen=True)
class Variant:
    name: str
    table: bool = True
    joint: bool = True
    n_refs: int = 4  # n x n floor reference points
    height_error_m: float = TAPE_HEIGHT_ERROR_MM / 1000.0  # the tape's table height, SD
    ref_error_m: float = 0.005
    height_misread_m: float = 0.0  # added to the tape's table height (a misreading)
    refine_height: bool = True  # the solve checks the tape's height against the dots


@dataclasses.dataclass(frozen=True)
class TrueIntrinsics(Variant):
    """The default variant given the simulator's intrinsics (a baseline only)."""


VARIANTS = [
    Variant("floor only, PnP per camera (baseline)", table=False, joint=False),
    Variant("floor only, joint", table=False),
    Variant("floor + table, PnP per camera", joint=False),
    Variant("floor + table, joint (default)"),
    Variant("floor + table, joint, 3x3 floor refs", n_refs=3),
    Variant("floor + table, joint, exact table height", height_error_m=0.0),
    Variant("floor + table, joint, height misread +10 mm", height_misread_m=0.010),
    Variant("floor + table, joint, height misread +10 mm, not checked", height_misread_m=0.010,
            refine_height=False),
    Variant("floor + table, joint, exact tape", ref_error_m=0.0, height_error_m=0.0),
    TrueIntrinsics("BASELINE: floor + table, joint, from the TRUE intrinsics"),
]
_INTRINSICS: dict[int, object] = {}


def monitor_intrinsics(rig, seed: int):
    """Every camera's intrinsics as the monitor step estimates them (no poses), and the
    worst focal (%) and principal point (px) error against the truth; cached per seed."""
    if seed not in _INTRINSICS:
        from calibkit.calibrate.intrinsic import calibrate, monitor_plane_view
        from calibkit.core.camera import Rig
        from calibkit.synthetic.monitor import MonitorSimConfig, make_monitor_sim, projected_dots

        cams, focal, centre = [], 0.0, 0.0
        for k, truth in enumerate(rig):
            cfg = MonitorSimConfig(seed=seed + 1000 * k)
            sch = coded_schedule(cfg.screen_px, 80.0, 2, 6.0)
            rng = np.random.default_rng(cfg.seed + 101)
            pitch = cfg.pixel_pitch_mm
            with make_monitor_sim(6, truth.size, cfg.seed, cfg, camera=truth,
                                  fill=0.8) as monitor:
                views = [monitor_plane_view(projected_dots(truth, view, sch.points_xy,
                                                           sch.radius_px, pitch, 0.035, rng),
                                            sch, pitch) for view in monitor.views]
            est = calibrate(views, truth.size, truth.name,
                            dot_radius_m=sch.radius_px * pitch / 1000.0).camera
            cams.append(est)
            focal = max(focal, 100 * abs(est.fx / truth.fx - 1), 100 * abs(est.fy / truth.fy - 1))
            centre = max(centre, abs(est.cx - truth.cx), abs(est.cy - truth.cy))
        _INTRINSICS[seed] = (Rig(tuple(cams)), focal, centre)
    return _INTRINSICS[seed]


def run(v: Variant, seed: int, noise_px: float = 0.2) -> dict:
    scene = sp.make_scene(6, VOLUME, 0.75, seed=seed)
    m = sp.measured_references(scene, exr.reference_layout_px(PROJ, v.n_refs),
                               sp.table_reference_px(scene), v.ref_error_m, v.height_error_m,
                               seed=seed)
    refs = exr.References(m["floor_px"], m["floor_xy_m"],
                         m["table_px"] if v.table else np.zeros((0, 2)),
                         m["table_xy_m"] if v.table else np.zeros((0, 2)),
                         m["table_height_m"] + v.height_misread_m if v.table else None)
    floor, table = exr.plane_maps(refs)
    sch = coded_schedule(PROJ, 64, 2, 8)
    fd = sp.simulated_dots(scene, sch.points_xy, False, noise_px, seed=seed)
    td = None
    if table is not None:
        tsch = exr.table_schedule(sch, table)
        td = sp.simulated_dots(scene, sch.points_xy, True, noise_px, seed=seed + 1,
                               shown=np.concatenate(tsch.layers))
    dots = exc.assemble(scene.rig.names, fd, td, sch, floor, table)
    intrinsics = scene.rig if isinstance(v, TrueIntrinsics) else \
        monitor_intrinsics(scene.rig, seed)[0]
    t0 = time.perf_counter()
    res = exs.calibrate(intrinsics, dots, floor, table,
                        exs.SolveOptions(joint=v.joint, refine_height=v.refine_height))
    dt = time.perf_counter() - t0
    cmp = compare_rigs(scene.rig, res.rig, align=False)
    pos = [c["position_mm"] for c in cmp["cameras"]]
    rot = [c["rotation_deg"] for c in cmp["cameras"]]
    h = res.report.get("table_height")
    true_m = scene.table.height_m
    height = None if not v.table else {
        "tape_mm": 1000 * (refs.table_height_m - true_m),
        "dots_mm": 1000 * (h["dots_m"] - true_m) if h else float("nan"),
        "dots_sigma_mm": h["dots_sigma_mm"] if h else float("nan"),
        "best_mm": 1000 * ((h["best_m"] if h else refs.table_height_m) - true_m),
        "used_mm": 1000 * ((h["used_m"] if h else refs.table_height_m) - true_m)}
    return {"pos": pos, "rot": rot, "time_s": dt, "height": height,
            "scale_ppm": cmp["scale"]["error_ppm"],
            "ray0": sp.ray_distance_at_height(res.rig, scene.rig, 0.0, VOLUME),
            "ray17": sp.ray_distance_at_height(res.rig, scene.rig, 1.7, VOLUME),
            "calibrated": len(res.rig)}


def with_wand(seed: int, n_frames: int) -> dict:
    """The default calibration, then a wand dance (true labels, 0.2 px) solved together
    with the plane dots (extrinsic.bundle_data + join_bundle_data), no world transform:
    the dots held on their planes and near their mapped places ("near maps"), or on their
    planes only as `calibkit wand --dots` does ("planes only"); each with the dots as the
    calibration passes them on (the table at the tape's and the dots' heights weighted)
    and, as a baseline, with the table at the tape's height."""
    from calibkit.calibrate import bundle
    from calibkit.calibrate.wand_solve import labelled_wand_data
    from calibkit.synthetic import sim

    v = Variant("default")
    scene = sp.make_scene(6, VOLUME, 0.75, seed=seed)
    m = sp.measured_references(scene, exr.reference_layout_px(PROJ), sp.table_reference_px(scene),
                               v.ref_error_m, v.height_error_m, seed=seed)
    refs = exr.References(m["floor_px"], m["floor_xy_m"], m["table_px"], m["table_xy_m"],
                         m["table_height_m"])
    floor, table = exr.plane_maps(refs)
    sch = coded_schedule(PROJ, 64, 2, 8)
    tsch = exr.table_schedule(sch, table)
    fd = sp.simulated_dots(scene, sch.points_xy, False, 0.2, seed=seed)
    td = sp.simulated_dots(scene, sch.points_xy, True, 0.2, seed=seed + 1,
                           shown=np.concatenate(tsch.layers))
    res = exs.calibrate(monitor_intrinsics(scene.rig, seed)[0],
                       exc.assemble(scene.rig.names, fd, td, sch, floor, table), floor, table)
    spacing = (0.0, 0.2, 0.5)
    obs = sim.observe(scene.rig, sim.wand_motion(n_frames, 100.0, VOLUME, spacing, seed=seed),
                      noise_px=0.2, seed=seed)
    wand = labelled_wand_data(res.rig, obs, spacing)
    opts = bundle.BundleOptions(known_sigma_m=0.005, plane_sigma_m=0.002, noise_px=0.3)
    tape_dots = exs.at_height(res.dots, res.report["table_height"]["tape_m"])
    rigs, times = [("extrinsic", res.rig)], []
    for known in (True, False):
        for height, dots in (("", res.dots), (", table at the tape's height", tape_dots)):
            t0 = time.perf_counter()
            out = bundle.solve(exs.join_bundle_data(wand, exs.bundle_data(
                res.rig, dots.select(res.inlier), known=known)), opts)
            times.append(time.perf_counter() - t0)
            rigs.append((f"wand+planes{' near maps' if known else ' only'}{height}", out.rig))
    dt = float(np.median(times))
    figs = {}
    for name, rig in rigs:
        cmp = compare_rigs(scene.rig, rig, align=False)
        figs[name] = (max(c["position_mm"] for c in cmp["cameras"]),
                      max(c["rotation_deg"] for c in cmp["cameras"]),
                      sp.ray_distance_at_height(rig, scene.rig, 1.7, VOLUME),
                      abs(cmp["scale"]["error_ppm"]), cmp["grid_rms_mm"])
    figs["time_s"] = dt
    return figs


def rendered(seed: int) -> dict:
    """One full capture through rendered images: frames per session and wall time."""
    scene = sp.make_scene(6, VOLUME, 0.75, seed=seed)
    m = sp.measured_references(scene, exr.reference_layout_px(PROJ), sp.table_reference_px(scene),
                               0.005, TAPE_HEIGHT_ERROR_MM / 1000.0, seed=seed)
    refs = exr.References(m["floor_px"], m["floor_xy_m"], m["table_px"], m["table_xy_m"],
                         m["table_height_m"])
    floor, table = exr.plane_maps(refs)
    sch = coded_schedule(PROJ, 64, 2, 8)
    tsch = exr.table_schedule(sch, table)
    t0 = time.perf_counter()
    with sp.ProjectorRigSim(scene, sp.ProjectorSimConfig(seed=seed)) as dev:
        fcap = exc.capture_session(dev, sch, 6)
        dev.set_table(True)
        tcap = exc.capture_session(dev, tsch, 6, latency_frames=fcap.latency_frames)
    wall = time.perf_counter() - t0
    dots = exc.assemble(scene.rig.names, fcap.cameras, tcap.cameras, sch, floor, table)
    res = exs.calibrate(monitor_intrinsics(scene.rig, seed)[0], dots, floor, table)
    cmp = compare_rigs(scene.rig, res.rig, align=False)
    return {"floor_frames": fcap.frames, "table_frames": tcap.frames,
            "capture_s_at_30fps": (fcap.frames + tcap.frames) / 30.0,
            "latency_frames": fcap.latency_frames, "simulation_wall_s": wall,
            "pos_max_mm": max(c["position_mm"] for c in cmp["cameras"]),
            "rot_max_deg": max(c["rotation_deg"] for c in cmp["cameras"]),
            "dots_per_camera": [len(f) + len(t) for f, t in
                                zip(fcap.cameras, tcap.cameras, strict=True)]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--render", action="store_true")
    ap.add_argument("--wand", type=int, default=0,
                    help="also join a wand dance of this many frames to the plane dots")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    results = {}
    rows, hrows = [], []
    base17 = base0 = None
    for v in VARIANTS:
        runs = [run(v, s) for s in range(args.seeds)]
        pos_max = [max(r["pos"]) for r in runs]
        rot_max = [max(r["rot"]) for r in runs]
        fig = {
            "position_median_mm": float(np.median([np.median(r["pos"]) for r in runs])),
            "position_worst_mm": float(np.max(pos_max)),
            "rotation_median_deg": float(np.median([np.median(r["rot"]) for r in runs])),
            "rotation_worst_deg": float(np.max(rot_max)),
            "runs_within_target": int(sum(p <= 10 and r <= 0.1
                                          for p, r in zip(pos_max, rot_max, strict=True))),
            "ray_floor_mm": float(np.median([r["ray0"] for r in runs])),
            "ray_1p7_mm": float(np.median([r["ray17"] for r in runs])),
            "scale_ppm_median_abs": float(np.median([abs(r["scale_ppm"]) for r in runs])),
            "solve_s": float(np.median([r["time_s"] for r in runs]))}
        if v.table:
            hs = {k: np.array([r["height"][k] for r in runs])
                  for k in ("tape_mm", "dots_mm", "dots_sigma_mm", "best_mm", "used_mm")}
            rms = {k: float(np.sqrt(np.mean(hs[k] ** 2))) for k in ("tape_mm", "dots_mm",
                                                                      "best_mm", "used_mm")}
            fig["table_height"] = {**{f"{k}_rms": val for k, val in rms.items()},
                                   "dots_sigma_mm_median": float(np.median(hs["dots_sigma_mm"])),
                                   "dots_error_over_sigma_rms": float(np.sqrt(np.mean(
                                       (hs["dots_mm"] / hs["dots_sigma_mm"]) ** 2)))}
            hrows.append([v.name, rms["tape_mm"], rms["dots_mm"],
                          fig["table_height"]["dots_sigma_mm_median"],
                          fig["table_height"]["dots_error_over_sigma_rms"], rms["best_mm"],
                          rms["used_mm"]])
        if base17 is None:
            base0, base17 = fig["ray_floor_mm"], fig["ray_1p7_mm"]
        fig["ray_1p7_ratio"] = fig["ray_1p7_mm"] / base17
        fig["ray_floor_ratio"] = fig["ray_floor_mm"] / base0
        results[v.name] = fig
        rows.append([v.name, fig["position_median_mm"], fig["position_worst_mm"],
                     fig["rotation_median_deg"], fig["rotation_worst_deg"],
                     f"{fig['runs_within_target']}/{args.seeds}", fig["ray_floor_mm"],
                     fig["ray_1p7_mm"], fig["ray_1p7_ratio"], fig["scale_ppm_median_abs"],
                     fig["solve_s"]])
        print(f"{v.name}: done", file=sys.stderr)
    intr = [monitor_intrinsics(sp.make_scene(6, VOLUME, 0.75, seed=s).rig, s)
            for s in range(args.seeds)]
    results["intrinsics_in"] = {"focal_pct_worst": max(i[1] for i in intr),
                                "principal_px_worst": max(i[2] for i in intr)}
    print(f"6 cameras, 4 x 4 m, table 0.75 m, 0.2 px noise; {args.seeds} scenes per row; "
          "worst = worst camera of the worst scene; intrinsics from the monitor step (worst "
          f"focal error {results['intrinsics_in']['focal_pct_worst']:.4f} %, principal point "
          f"{results['intrinsics_in']['principal_px_worst']:.3f} px) except the BASELINE row")
    print_table(rows, ["variant", "pos_med_mm", "pos_worst_mm", "rot_med_deg",
                       "rot_worst_deg", "in target", "ray@0_mm", "ray@1.7_mm",
                       "ray@1.7 ratio", "|scale|_ppm", "solve_s"])
    print("\ntable height against the truth, RMS over scenes (mm); dots: the solve's own "
          "measure; best: tape and dots weighted (the dots file's); used: the poses' (the "
          "tape's unless they disagree beyond 3 sigma)")
    print_table(hrows, ["variant", "tape_mm", "dots_mm", "dots_sigma_mm", "dots err/sigma",
                        "best_mm", "used_mm"])
    sch = coded_schedule(PROJ, 64, 2, 8)
    cfg = sp.ProjectorSimConfig()
    lat = sp.latency_frames(cfg, 6)
    scene = sp.make_scene(6, VOLUME, 0.75, seed=0)
    m = sp.measured_references(scene, exr.reference_layout_px(PROJ), sp.table_reference_px(scene),
                               0.0)
    _, table = exr.plane_maps(exr.References(m["floor_px"], m["floor_xy_m"], m["table_px"],
                                           m["table_xy_m"], m["table_height_m"]))
    tsch = exr.table_schedule(sch, table)
    est = exc.capture_frames_estimate(sch, lat) + exc.capture_frames_estimate(tsch, lat)
    results["capture_estimate"] = {"latency_frames": lat, "frames": est,
                                   "seconds_at_30fps": est / 30.0,
                                   "patterns": [len(sch.frames), len(tsch.frames)]}
    print(f"\ncapture (estimated from the camera latencies {lat} frames): "
          f"{len(sch.frames)} + {len(tsch.frames)} patterns, {est} frames = "
          f"{est / 30.0:.1f} s at 30 fps")
    if args.wand:
        runs = [with_wand(s, args.wand) for s in range(args.seeds)]
        wrows = []
        for name in (n for n in runs[0] if n != "time_s"):
            w = np.array([r[name] for r in runs])
            wrows.append([name, float(np.median(w[:, 0])), float(w[:, 0].max()),
                          float(np.median(w[:, 1])), float(w[:, 1].max()),
                          float(np.median(w[:, 2])), float(np.median(w[:, 3])),
                          float(np.median(w[:, 4]))])
            results[f"wand_{name}"] = dict(zip(["pos_worst_median_mm", "pos_worst_mm",
                                                "rot_worst_median_deg", "rot_worst_deg",
                                                "ray_1p7_mm", "scale_ppm_median_abs",
                                                "grid_rms_mm_median"], wrows[-1][1:],
                                               strict=True))
        print(f"\nwand dance of {args.wand} frames joined to the plane dots "
              f"({args.seeds} scenes; per scene its worst camera; solve "
              f"{np.median([r['time_s'] for r in runs]):.1f} s median):")
        print_table(wrows, ["rig", "pos_worst_med_mm", "pos_worst_mm", "rot_worst_med_deg",
                            "rot_worst_deg", "ray@1.7_mm", "|scale|_ppm", "grid_mm (unaligned)"])
    if args.render:
        r = rendered(0)
        results["rendered"] = r
        print(f"rendered capture, 6 cameras 640x480: {r['floor_frames']} + "
              f"{r['table_frames']} frames = {r['capture_s_at_30fps']:.1f} s at 30 fps "
              f"(latencies seen {r['latency_frames']}); position error up to "
              f"{r['pos_max_mm']:.1f} mm, orientation up to {r['rot_max_deg']:.3f} deg; dots "
              f"per camera {r['dots_per_camera']}; simulation took "
              f"{r['simulation_wall_s']:.0f} s")
    if args.json:
        write_json(args.json, results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
