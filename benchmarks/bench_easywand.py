"""DLTdv/easyWand xypts files: how fast they read, and that a wand solve from one loses nothing.

Part 1, speed (`--part speed`): a simulated 2-end wand capture (4 cameras, `--frames`
frames, 10 % of the points not digitised) written in DLTdv's layout (header
pt1_cam1_X..., 1-based pixels, y up, NaN where not digitised). Median of `--repeats` runs,
single-threaded, of
- calibkit.core.easywand.read_xypts (parse, convert, check, build the observations);
- baselines on the same data in the same process: numpy's genfromtxt on the xypts file
  (parsing only, nothing converted or checked) and our own plain CSV reader
  (calibkit.core.recording.load_observations on the observations saved as our CSV).

Part 2, accuracy (`--part accuracy`): a 3-camera 2-end wand capture (0.1 px noise, 0.5 m
wand, `--wand-frames` frames) solved with the intrinsics held, from
- the observations in hand with the simulator's intrinsics (the baseline), and with the
  easyWand profile's (it holds one focal length; the simulator's fy is 0.1-0.2 % off fx);
- the same written as xypts + easyWand profile and read back (y from the bottom, as written):
  equal to the row before if the reader loses nothing;
- the same read as if y counted from the top (the DLTdv 8 option on a DLTdv 1-7 file).
Reported: reprojection RMS, the worst camera-pair relative-rotation error against the
truth (free of the world frame; a mirrored read shows here and nowhere else), the worst
camera-baseline ratio error (scale from the wand).

    python benchmarks/bench_easywand.py [--part both] [--frames 20000] [--repeats 5]
                                        [--wand-frames 400] [--json out.json]
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from calibkit.clitools import print_table, write_json
from calibkit.core.camera import Rig, rotation_from_rvec
from calibkit.core.easywand import read_easywand_profile, read_xypts
from calibkit.core.recording import load_observations, save_observations
from calibkit.synthetic import sim


def capture(n_cameras: int, n_frames: int, dropout: float, seed: int = 4):
    rig = sim.make_rig(n_cameras, volume_m=3.0, seed=seed)
    truth = sim.wand_motion(n_frames, volume_m=3.0, spacing_m=(0.0, 0.5), seed=seed)
    obs = sim.observe(rig, truth, noise_px=0.1, dropout=dropout, blobs="ideal", seed=seed)
    return rig, obs


def write_xypts(path: Path, obs, n_frames: int) -> None:
    """DLTdv's layout: per point, per camera X and Y; 1-based, y up; NaN not digitised."""
    n_cams = len(obs.camera_names)
    table = np.full((n_frames, 2, n_cams, 2), np.nan)
    height = np.array([s[1] for s in obs.camera_sizes], dtype=float)[obs.camera]
    table[obs.frame, obs.marker, obs.camera, 0] = obs.uv[:, 0] + 1
    table[obs.frame, obs.marker, obs.camera, 1] = height - obs.uv[:, 1]
    cols = [f"pt{p + 1}_cam{c + 1}_{a}" for p in range(2) for c in range(n_cams) for a in "XY"]
    np.savetxt(path, table.reshape(n_frames, -1), delimiter=",", fmt="%.6f",
               header=",".join(cols), comments="")


def write_profile(path: Path, rig: Rig) -> None:
    rows = [f"{i + 1} {c.fx:.6f} {c.width} {c.height} {c.cx + 1:.6f} {c.height - c.cy:.6f} "
            f"1 {c.dist[0]} {c.dist[1]} {-c.dist[2]} {c.dist[3]} {c.dist[4]}"
            for i, c in enumerate(rig)]
    path.write_text("\n".join(rows) + "\n")


def median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def part_speed(args, folder: Path) -> list[dict]:
    rig, obs = capture(4, args.frames, 0.1)
    xy, prof, ours = folder / "x-xypts.csv", folder / "profile.txt", folder / "ours.csv"
    write_xypts(xy, obs, args.frames)
    write_profile(prof, rig)
    save_observations(ours, obs)
    cams = read_easywand_profile(prof)
    got = read_xypts(xy, cams)
    assert len(got) == len(obs)
    err = float(np.max(np.abs(got.uv - obs.uv)))
    runs = [("read_xypts", lambda: read_xypts(xy, cams)),
            ("baseline: np.genfromtxt (parse only)",
             lambda: np.genfromtxt(xy, delimiter=",", skip_header=1)),
            ("baseline: our plain CSV reader", lambda: load_observations(ours))]
    rows = []
    for name, fn in runs:
        t = median_time(fn, args.repeats)
        rows.append({"run": name, "median_s": t, "frames_per_s": args.frames / t,
                     "points": len(obs), "max_uv_error_px": err if name == "read_xypts"
                     else None})
    return rows


def rotation_error_deg(est: Rig, true: Rig) -> float:
    worst = 0.0
    for i in range(len(true)):
        for j in range(i + 1, len(true)):
            a = rotation_from_rvec(est[j].rvec) @ rotation_from_rvec(est[i].rvec).T
            b = rotation_from_rvec(true[j].rvec) @ rotation_from_rvec(true[i].rvec).T
            cos = np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1)
            worst = max(worst, math.degrees(math.acos(cos)))
    return worst


def baseline_error(est: Rig, true: Rig) -> float:
    n = len(true)
    return max(abs(np.linalg.norm(est[i].centre - est[j].centre)
                   / np.linalg.norm(true[i].centre - true[j].centre) - 1)
               for i in range(n) for j in range(i + 1, n))


def part_accuracy(args, folder: Path) -> list[dict]:
    from calibkit.calibrate.wand_solve import calibrate  # GTSAM: only for this part

    rig, obs = capture(3, args.wand_frames, 0.0)
    xy, prof = folder / "w-xypts.csv", folder / "wprofile.txt"
    write_xypts(xy, obs, args.wand_frames)
    write_profile(prof, rig)
    inputs = []
    hand = obs.select(np.ones(len(obs), dtype=bool))
    hand.marker = None
    intr = Rig(tuple(c.replace(rvec=np.zeros(3), t=np.zeros(3)) for c in rig))
    inputs.append(("baseline: observations in hand, true intrinsics", hand, intr))
    # the same observations numbered as the xypts file numbers them (frame 1 first, cam1...)
    # with the profile's intrinsics (one focal length: the true fy is 0.1-0.2 % off fx)
    cams = read_easywand_profile(prof)
    same = obs.select(np.ones(len(obs), dtype=bool))
    same.marker, same.frame, same.camera_names = None, same.frame + 1, tuple(cams.names)
    inputs.append(("observations in hand, the profile's intrinsics", same, cams))
    for origin, label in (("bottom", "xypts + profile, y from the bottom"),
                          ("top", "xypts + profile read as y from the top (mirrored)")):
        cams = read_easywand_profile(prof, origin)
        got = read_xypts(xy, cams, origin)
        inputs.append((label, got, cams))
    rows = []
    for label, o, cams in inputs:
        cal = calibrate(o, cams, (0.0, 0.5), refine_intrinsics=False, holdout=0.1, seed=0)
        est = Rig(tuple(cal.rig[n] for n in cal.rig.names))
        rows.append({"run": label, "reprojection_rms_px": cal.report["solve"][
            "reprojection_rms_px"], "rotation_error_deg": rotation_error_deg(est, rig),
            "baseline_error_pct": 100 * baseline_error(est, rig)})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("speed", "accuracy", "both"), default="both")
    parser.add_argument("--frames", type=int, default=20000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--wand-frames", type=int, default=400)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    print(f"load: {os.getloadavg()[0]:.2f} (1 min), {os.cpu_count()} cores")
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        if args.part in ("speed", "both"):
            rows = part_speed(args, folder)
            out["speed"] = rows
            print(f"\nreading {args.frames} frames x 4 cameras x 2 points "
                  f"({rows[0]['points']} digitised), median of {args.repeats}:")
            print_table([[r["run"], round(1000 * r["median_s"], 1), round(r["frames_per_s"]),
                          r["max_uv_error_px"]] for r in rows],
                        ["run", "median_ms", "frames/s", "max |uv error| px"])
        if args.part in ("accuracy", "both"):
            rows = part_accuracy(args, folder)
            out["accuracy"] = rows
            print(f"\n3 cameras, 2-end 0.5 m wand, {args.wand_frames} frames, 0.1 px noise, "
                  "intrinsics held:")
            print_table([[r["run"], round(r["reprojection_rms_px"], 4),
                          round(r["rotation_error_deg"], 3),
                          round(r["baseline_error_pct"], 3)] for r in rows],
                        ["input", "rms_px", "worst pair rotation error deg",
                         "worst baseline error %"])
    if args.json is not None:
        write_json(args.json, out)


if __name__ == "__main__":
    main()
