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

    python benchmarks/bench_pairing.py [--seconds-scale 1.0] [--json out.json]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import daemon.clocks as clocks
from calibkit.clitools import print_table, write_json
from daemon.config import SimConfig
from daemon.multiplexer import Multiplexer
from daemon.synthetic.scene import SimScene
from daemon.synthetic.virtual import START_NS, capture, spread_ns


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds-scale", type=float, default=1.0,
                    help="run each scene this many times as long")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    out, rows = {}, []
    for name in SCENES:
        for pairing in ("counter", "offset only", "time"):
            r = run(name, pairing, args.seconds_scale)
            out[f"{name} / {pairing}"] = r
            rows.append([name, pairing, r["sets"], r["mixing_instants"],
                         round(r["worst_spread_ms"], 1), r["late_samples"],
                         r["settling_samples"], r["incomplete_sets"]])
    print_table(rows, ["scene", "pairing", "sets", "mixing_instants", "worst_ms", "late",
                       "settling", "incomplete"])
    if args.json:
        write_json(args.json, out)


if __name__ == "__main__":
    main()
