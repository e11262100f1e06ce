"""How well a wand capture alone determines intrinsics, measured: the same scene and dance
solved over several draws of the image noise, intrinsics held or refined from the exact
values, against calibkit.calibrate.wand_shape's prediction from the solve's covariance.

The scene is bench_wand_small's part 2 (6 machine-vision cameras with strong distortion,
658x492, a 3-marker wand, 0.1 px) with the solver given the exact intrinsics without
uncertainties, so any error of the refined rig is what the capture leaves, not where the
solve started. Each draw re-simulates only the noise (sim.observe's seed); the scene and the
dance stay. Scored against the truth (the scorer may read it, the solve never does):

  grid mm       calibkit compare's grid RMS (the whole 4 m volume, aligned by camera centres)
  best fit mm   the same grid aligned by the similarity that best maps it (bench_wand_small)
  wand box mm   the grid over the box the wand went through, best-fit aligned: what
                wand_shape predicts
  predicted mm  wand_shape.shape_uncertainty from each solve's own covariance (RMS over
                the draws; the others are RMS over the draws too); beside it the same had
                all intrinsics, or only the focal lengths, the principal points or the
                distortion terms of every camera been known (other views of the cameras)

If the error scales with the noise (--noise 0.01) and matches the prediction, it is the
capture's information, not a bias: no choice of solve reaches below it.

    python benchmarks/bench_wand_shape.py [--draws 0,101,102,103] [--frames 1500]
        [--noise 0.1] [--seed 0] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
from bench_wand_small import best_fit_grid_mm

from calibkit.calibrate import wand_shape
from calibkit.calibrate.compare import compare_rigs
from calibkit.calibrate.wand_solve import calibrate
from calibkit.clitools import print_table, write_json
from calibkit.core.camera import BASLER_658x492_DIST, Rig
from calibkit.synthetic import sim

SPACING_M = (0.0, 0.2, 0.5)


def run(seed: int, draws: list[int], frames: int, noise_px: float) -> list[dict]:
    rig = sim.make_rig(6, 4.0, size=(658, 492), dist=BASLER_658x492_DIST, seed=seed)
    truth = sim.wand_motion(frames, 100.0, 4.0, SPACING_M, seed=seed)
    bare = Rig(tuple(c.replace(rvec=np.zeros(3), t=np.zeros(3)) for c in rig),
               meta={"volume_m": 4.0})
    box = wand_shape.wand_grid(rig, truth.xyz)  # the box the wand went through, true
    out = []
    for draw in draws:
        obs = sim.observe(rig, truth, noise_px=noise_px, seed=draw)
        for mode, refine in (("held", False), ("refined", True)):
            t0 = time.process_time()
            cal = calibrate(obs, bare, SPACING_M, refine_intrinsics=refine, seed=seed)
            cpu = time.process_time() - t0
            shape = cal.report["shape_uncertainty"]
            out.append({"seed": seed, "draw": draw, "mode": mode, "noise_px": noise_px,
                        "frames": frames,
                        "grid_mm": compare_rigs(rig, cal.rig)["grid_rms_mm"],
                        "best_fit_mm": best_fit_grid_mm(rig, cal.rig),
                        "wand_box_mm": best_fit_grid_mm(rig, cal.rig, box),
                        "predicted_mm": shape["grid_rms_mm"],
                        "intrinsics_known_mm": shape.get("intrinsics_known_mm", np.nan),
                        **{f"known_{k}_mm": v for k, v in shape.get("if_known_mm", {}).items()},
                        "cpu_s": cpu})
            print(out[-1], file=sys.stderr, flush=True)
    return out


def table(runs: list[dict]) -> None:
    rows = []
    for mode in ("held", "refined"):
        g = [r for r in runs if r["mode"] == mode]

        def rms(key, g=g):
            return float(np.sqrt(np.mean(np.square([r[key] for r in g]))))
        known = [rms(f"known_{k}_mm") if f"known_{k}_mm" in g[0] else np.nan
                 for k in wand_shape.GROUPS]
        rows.append([mode, len(g), rms("grid_mm"), rms("best_fit_mm"), rms("wand_box_mm"),
                     rms("predicted_mm"), rms("intrinsics_known_mm"), *known,
                     float(np.median([r["cpu_s"] for r in g]))])
    print_table(rows, ["intrinsics", "draws", "grid mm", "best fit mm", "wand box mm",
                       "predicted mm", "predicted, all known",
                       *[f"predicted, {k.replace('_', ' ')} known" for k in wand_shape.GROUPS],
                       "cpu s median"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--draws", default="0,101,102,103")
    ap.add_argument("--frames", type=int, default=1500)
    ap.add_argument("--noise", type=float, default=0.1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json")
    args = ap.parse_args()
    runs = run(args.seed, [int(d) for d in args.draws.split(",")], args.frames, args.noise)
    table(runs)
    print(f"load average at the end: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    if args.json:
        write_json(args.json, runs)


if __name__ == "__main__":
    main()
