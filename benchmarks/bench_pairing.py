"""Frame pairing: sets that mix instants and samples lost, pairing by capture time against
pairing by each camera's frame counter, on the simulator's cameras run in virtual time.

Scenes (4 cameras at 60 fps unless said; the simulated cameras stamp frames on their own
clocks and count from their own start): cameras opening up to 2 s apart; a camera away for
0.5 s that comes back counting from 0 on a new clock epoch; 3 cameras at 120 fps whose
clocks gain or lose up to 50 ppm, for two minutes. Each set is checked against the
simulator's truth (the instants its cameras really took their frames).

Pairings, all through the same multiplexer: `counter` groups by each camera's own frame
counter (what mocapd did before pairing by time); `offset only` maps each camera's clock
with an offset but no drift; `time` is mocapd's (offset and drift learned online).

Wand captures (calibkit's side, calibkit.core.pairing): a wand dance of
`--wand-frames` frames at 100 fps seen by 6 cameras (0.1 px noise, 0.2 stray blobs per
camera and frame), each camera opening within 0.5 s, stamping on a clock +-1 ms off and
+-30 ppm fast or slow with 50 us jitter (calibkit.synthetic.camclocks); cam2 loses 1 % of
its frames or none. Pairings: `shared index` is the old simulator's perfect clocks (one
frame number for every camera: the baseline), `counter` groups by each camera's own
counter, `time` is calibkit's. Each capture is solved from the true intrinsics (refined)
and scored against the true rig: grid RMS (compare_rigs), and the sets mixing instants
scored from the simulator's truth; medians over `--wand-seeds` seeds.

The cost of pairing on `mocapd start --sim --fast` (`--fast-sets`): ms per frame set to
make the sets of the default simulated scene (8 cameras at 240 fps, 4 bodies) by the old
way (every camera's sample of trigger i in set i: SimScene.sample) and by the fast path's
(daemon.synthetic.virtual.frame_sets: the cameras in virtual time through the
multiplexer), alternately, median of 5 runs each, in one process. The tracker's own cost
per set is what bench_tracking measures; the difference here is what a fast run loses.

    python benchmarks/bench_pairing.py [--seconds-scale 1.0] [--wand-frames 1500]
                                       [--wand-seeds 3] [--fast-sets 2400] [--json out.json]
"""

from __future__ import annotations

import argparse
import itertools
import time
from pathlib import Path

import numpy as np

import daemon.capture.clocks as clocks
from calibkit.calibrate.compare import compare_rigs
from calibkit.calibrate.wand_solve import calibrate
from calibkit.clitools import print_table, write_json
from calibkit.core.errors import UserError
from calibkit.core.pairing import pair_frames
from calibkit.synthetic import camclocks, sim
from daemon.capture.multiplexer import Multiplexer
from daemon.config.mocapd import SimConfig
from daemon.synthetic.scene import SimScene
from daemon.synthetic.virtual import START_NS, capture, frame_sets, spread_ns


class CounterMultiplexer(Multiplexer):
    """Sets by frame counter: a sample's time is its camera's counter times the period,
    as if every camera had started at once."""

    def capture_ns(self, sample):
        return START_NS + round(sample.index * self.period_ns)


SCENES = {
    "open up to 2 s apart": (dict(open_spread_s=2.0), 4.0),
    "cam1 away 0.5 s, new counter and epoch": (dict(drop_camera="cam1", drop_from_s=1.0,
                                                     drop_for_s=0.5, clock_drift_ppm=50.0),
                                                3.0),
    "3 cameras 120 fps, 50 ppm": (dict(cameras=3, fps=120.0, clock_drift_ppm=50.0, seed=6),
                                  120.0),
}


def scene(**kw) -> SimScene:
    cfg = SimConfig(**{**dict(cameras=4, bodies=1, fps=60.0, seed=3, noise_px=0.0,
                              open_spread_s=0.0, clock_drift_ppm=0.0), **kw})
    return SimScene(cfg, n_frames=int(20 * cfg.fps))


def run(name: str, pairing: str, scale: float) -> dict:
    kw, seconds = SCENES[name]
    sc = scene(**kw)
    fit = clocks.MIN_FIT
    if pairing == "offset only":
        clocks.MIN_FIT = 10**9  # never fit a drift: the lowest point's offset only
    try:
        sets, mux, _ = capture(sc, seconds * scale, make_mux=(
            CounterMultiplexer if pairing == "counter" else Multiplexer))
    finally:
        clocks.MIN_FIT = fit
    spreads = np.array([spread_ns(sc, fs) for fs in sets], dtype=float)
    half = 0.5e9 / sc.fps
    return {"sets": len(sets), "mixing_instants": int(np.sum(spreads > half)),
            "worst_spread_ms": float(np.nanmax(spreads)) * 1e-6 if len(sets) else None,
            "late_samples": mux.late, "settling_samples": mux.settling,
            "incomplete_sets": mux.incomplete}


WAND_CASES = (("perfect clocks", "shared index"), ("+-30 ppm, none lost", "time"),
              ("+-30 ppm, cam2 loses 1 %", "time"), ("+-30 ppm, cam2 loses 1 %", "counter"))


def wand_case(case: str, pairing: str, frames: int, seed: int) -> dict:
    """One wand capture paired one way, solved and scored against the truth."""
    spacing = (0.0, 0.2, 0.5)
    rig = sim.make_rig(6, 4.0, seed=seed)
    truth = sim.wand_motion(frames, 100.0, 4.0, spacing, seed=seed)
    obs = sim.observe(rig, truth, noise_px=0.1, ghosts_per_camera=0.2, fps=100.0, seed=seed)
    mixing, n_sets, pair_ms = 0, len(obs.frames()), 0.0
    if pairing != "shared index":
        drop = {2: 0.01} if "loses" in case else None
        raw, ftruth = camclocks.per_camera(obs, camclocks.make_clocks(6, seed, drop=drop),
                                           frames, 100.0, seed)
        t0 = time.perf_counter()
        obs = pair_frames(raw).obs if pairing == "time" else raw
        pair_ms = (time.perf_counter() - t0) * 1e3
        score = camclocks.sets_mixing_instants(obs, ftruth, 100.0)
        mixing, n_sets = score["mixing"], score["sets"]
    try:
        cal = calibrate(obs, rig, spacing, holdout=0.1, seed=1)
        grid = compare_rigs(rig, cal.rig)["grid_rms_mm"]
    except UserError:  # the solve gave up: no figure to give
        grid = float("nan")
    return {"grid_mm": grid, "sets": n_sets, "mixing_instants": mixing, "pair_ms": pair_ms}


def wand_table(frames: int, seeds: int) -> tuple[list, dict]:
    rows, out = [], {}
    for case, pairing in WAND_CASES:
        runs = [wand_case(case, pairing, frames, seed) for seed in range(seeds)]
        med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
        med["grid_mm_worst"] = float(np.max([r["grid_mm"] for r in runs]))
        out[f"wand / {case} / {pairing}"] = {"median": med, "runs": runs}
        rows.append([case, pairing, round(med["grid_mm"], 3), round(med["grid_mm_worst"], 3),
                     int(med["sets"]), int(med["mixing_instants"]), round(med["pair_ms"], 1)])
    return rows, out


def fast_sets_cost(n_sets: int, repeats: int = 5) -> dict:
    """ms per set: trigger-indexed sets (the old fast path) against the multiplexer's."""
    from daemon.capture.multiplexer import FrameSet

    cfg = SimConfig(realtime=False)
    old, new = [], []
    for _ in range(repeats):
        sc = SimScene(cfg, n_frames=n_sets)
        t0 = time.perf_counter()
        for i in range(n_sets):
            t = round(i * 1e9 / sc.fps)
            FrameSet(i, t, t, [sc.sample(c, i, t) for c in range(len(sc.rig))
                               if not sc.dropped(c, i)])
        old.append((time.perf_counter() - t0) * 1e3 / n_sets)
        sc = SimScene(cfg, n_frames=n_sets)
        t0 = time.perf_counter()
        got = sum(1 for _ in itertools.islice(frame_sets(sc), n_sets))
        new.append((time.perf_counter() - t0) * 1e3 / got)
    return {"trigger_index_ms_per_set": float(np.median(old)),
            "multiplexer_ms_per_set": float(np.median(new)), "sets": n_sets,
            "cameras": cfg.cameras, "fps": cfg.fps}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds-scale", type=float, default=1.0,
                    help="run each scene this many times as long (0: no scenes)")
    ap.add_argument("--wand-frames", type=int, default=1500,
                    help="wand frames per capture (0: no wand table)")
    ap.add_argument("--wand-seeds", type=int, default=3, help="wand captures per case")
    ap.add_argument("--fast-sets", type=int, default=2400,
                    help="frame sets for the fast path's cost (0: none)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    out, rows = {}, []
    for name in SCENES if args.seconds_scale > 0 else ():
        for pairing in ("counter", "offset only", "time"):
            r = run(name, pairing, args.seconds_scale)
            out[f"{name} / {pairing}"] = r
            rows.append([name, pairing, r["sets"], r["mixing_instants"],
                         round(r["worst_spread_ms"], 1), r["late_samples"],
                         r["settling_samples"], r["incomplete_sets"]])
    if rows:
        print_table(rows, ["scene", "pairing", "sets", "mixing_instants", "worst_ms", "late",
                           "settling", "incomplete"])
    if args.fast_sets > 0:
        f = fast_sets_cost(args.fast_sets)
        out["fast_path_sets"] = f
        print(f"\nmocapd --sim --fast, making {f['sets']} frame sets ({f['cameras']} cameras, "
              f"{f['fps']:g} fps), median of 5")
        print_table([["trigger index (before)", round(f["trigger_index_ms_per_set"], 4)],
                     ["multiplexer, virtual time (now)", round(f["multiplexer_ms_per_set"], 4)],
                     ["difference", round(f["multiplexer_ms_per_set"]
                                          - f["trigger_index_ms_per_set"], 4)]],
                    ["sets made by", "ms_per_set"])
    if args.wand_frames > 0:
        wrows, wout = wand_table(args.wand_frames, args.wand_seeds)
        out.update(wout)
        print(f"\nwand captures: {args.wand_frames} frames, 6 cameras, median of "
              f"{args.wand_seeds} seeds")
        print_table(wrows, ["clocks", "pairing", "grid_mm", "grid_mm_worst", "sets",
                            "mixing_instants", "pair_ms"])
    if args.json:
        write_json(args.json, out)


if __name__ == "__main__":
    main()
