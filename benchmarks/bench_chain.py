"""The whole calibration chain as a user runs it on the simulator, scored against the truth.

Per rig (sim.make_rig ring, 4 m volume, 640x480 webcams, the seed's own lenses) the very
commands `calibkit demo` runs, each a separate process reading only the previous step's
files:

  calibkit sim rig        the hardware (world.truth.toml), read only by the simulator and compare
  calibkit intrinsic      --sim --sim-rig world --camera all --no-render  -> intr.toml
  calibkit extrinsic      --projector --sim --sim-rig world --intrinsics intr.toml -> ext.toml
  calibkit wand           --sim --sim-rig world --rig ext.toml --dots ext.dots.npz -> rig.toml
                          (once per --modes: refine = the default, fix = --fix-intrinsics)
  calibkit compare        world.truth.toml rig.toml  (similarity-aligned)

Figures per run: the monitor step's worst focal (%) and principal point (px) error; the
extrinsic step's worst camera position (mm, in the tape-measured frame, not aligned); after
the wand: worst camera position (mm), grid RMS (mm) over every grid point two cameras see
and the count of those over 10 mm (gross), the wand's grade; and each step's wall time.
Then per (cameras, mode): the median and the worst over the seeds.

    python benchmarks/bench_chain.py [--cameras 6,8] [--seeds 0,1,2] [--frames 3000]
                                     [--noise-px 0.1] [--modes refine,fix] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from calibkit.clitools import print_table, write_json

CALIBKIT = [sys.executable, "-m", "calibkit.cli"]


def _run(args: list[str]) -> float:
    """One command; its wall time. A failure stops the benchmark with its last line."""
    start = time.monotonic()
    proc = subprocess.run(CALIBKIT + [str(a) for a in args], capture_output=True, text=True,
                          check=False)
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["(no message)"])[-1]
        raise SystemExit(f"failed: calibkit {' '.join(map(str, args))}: {last}")
    return time.monotonic() - start


def _load(path: Path) -> dict:
    return json.loads(path.read_text(encoding="utf-8"))


def run_chain(folder: Path, cameras: int, seed: int, frames: int, noise_px: float,
              modes: list[str]) -> list[dict]:
    world, intr, ext = folder / "world.truth.toml", folder / "intr.toml", folder / "ext.toml"
    t = {"rig": _run(["sim", "rig", "--cameras", cameras, "--seed", seed, "--out", world])}
    t["intrinsic"] = _run(["intrinsic", "--sim", "--sim-rig", world, "--camera", "all",
                           "--no-render", "--seed", seed, "--rig", intr, "--json",
                           folder / "intr.json"])
    t["extrinsic"] = _run(["extrinsic", "--projector", "--sim", "--sim-rig", world,
                           "--intrinsics", intr, "--seed", seed, "--out", ext, "--json",
                           folder / "ext.json"])
    cams = _load(folder / "intr.json")["cameras"]
    base = {
        "cameras": cameras, "seed": seed,
        "intr_focal_pct_max": max(100 * max(abs(c["error"]["fx_rel"]),
                                            abs(c["error"]["fy_rel"])) for c in cams),
        "intr_pp_px_max": max(max(abs(c["error"]["cx_px"]), abs(c["error"]["cy_px"]))
                              for c in cams),
        "ext_pos_mm_max": _load(folder / "ext.json")["truth"]["position_error_max_mm"],
        "intrinsic_s": t["intrinsic"], "extrinsic_s": t["extrinsic"],
    }
    rows = []
    for mode in modes:
        rig = folder / f"rig-{mode}.toml"
        wand_s = _run(["wand", "--sim", "--sim-rig", world, "--rig", ext, "--dots",
                       folder / "ext.dots.npz", "--frames", frames, "--noise-px", noise_px,
                       "--seed", seed, "--no-plots", "--out", rig, "--json",
                       folder / f"wand-{mode}.json",
                       "--refine-intrinsics" if mode == "refine" else "--fix-intrinsics"])
        _run(["compare", world, rig, "--json", folder / f"cmp-{mode}.json"])
        cmp, wand = _load(folder / f"cmp-{mode}.json"), _load(folder / f"wand-{mode}.json")
        rows.append({**base, "mode": mode,
                     "pos_mm_max": max(c["position_mm"] for c in cmp["cameras"]),
                     "grid_rms_mm": cmp["grid_rms_mm"], "grid_points": cmp["grid_points"],
                     "grid_gross": cmp["grid_gross_points"],
                     "focal_pct_max": max(abs(c["focal_pct"]) for c in cmp["cameras"]),
                     "pp_px_max": max(c["principal_px"] for c in cmp["cameras"]),
                     "grade": wand["grade"], "wand_s": wand_s})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", default="6,8")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--noise-px", type=float, default=0.1)
    ap.add_argument("--modes", default="refine,fix")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    modes = [m for m in a.modes.split(",") if m]
    if not set(modes) <= {"refine", "fix"}:
        raise SystemExit("--modes takes refine and/or fix")
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in (int(v) for v in a.cameras.split(",")):
            for seed in (int(v) for v in a.seeds.split(",")):
                folder = Path(tmp) / f"c{n}s{seed}"
                folder.mkdir()
                rows += run_chain(folder, n, seed, a.frames, a.noise_px, modes)
                r = rows[-1]
                print(f"{n} cameras, seed {seed}: done ({r['intrinsic_s']:.0f} + "
                      f"{r['extrinsic_s']:.0f} + {r['wand_s']:.0f} s)", file=sys.stderr)
    keys = ["cameras", "seed", "mode", "intr_focal_pct_max", "intr_pp_px_max",
            "ext_pos_mm_max", "pos_mm_max", "grid_rms_mm", "grid_gross", "focal_pct_max",
            "pp_px_max", "grade", "intrinsic_s", "extrinsic_s", "wand_s"]
    print_table([[r[k] for k in keys] for r in rows], keys)
    summary = []
    for n in sorted({r["cameras"] for r in rows}):
        for mode in modes:
            sel = [r for r in rows if r["cameras"] == n and r["mode"] == mode]
            pos = np.array([r["pos_mm_max"] for r in sel])
            grid = np.array([r["grid_rms_mm"] for r in sel])
            summary.append([n, mode, len(sel), float(np.median(pos)), float(pos.max()),
                            float(np.median(grid)), float(grid.max()),
                            sum(r["grid_gross"] for r in sel),
                            sum(r["pos_mm_max"] <= 0.5 and r["grid_rms_mm"] <= 0.3
                                for r in sel)])
    print()
    print_table(summary, ["cameras", "mode", "runs", "pos_mm_max median", "worst",
                          "grid_rms_mm median", "worst", "grid gross", "runs on target"])
    print(f"\ntargets: camera positions within 0.5 mm and grid RMS <= 0.3 mm "
          f"({a.noise_px} px noise, {a.frames} wand frames)")
    if a.json is not None:
        write_json(a.json, {"runs": rows, "frames": a.frames, "noise_px": a.noise_px})


if __name__ == "__main__":
    main()
