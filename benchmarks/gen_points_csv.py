"""Write a big points CSV (frame,x,y,z) of rigid bodies moving: track's memory and speed.

The scene is bench_track's (10 bodies of 4-5 markers at 120 Hz, 0.5 mm noise, 5 % of
markers hidden in spans, 2 stray points a frame, points shuffled within each frame),
one minute of it played forwards then backwards again and again (so the motion stays
continuous) until the file reaches --mb megabytes. Written a block of frames at a time,
so this script's own memory stays small; the bodies go beside it as PATH.bodies.toml.
Not for the repository: write it under /tmp and delete it afterwards.

    python benchmarks/gen_points_csv.py --mb 1000 --out /tmp/points_1g.csv
"""

from __future__ import annotations

import argparse
import io
import sys
from pathlib import Path

import numpy as np
import tomli_w

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_track import RATE, scene  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mb", type=float, required=True, help="size to reach, MB")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    pts, bodies, _ = scene(1.0, args.seed)
    order = np.argsort(pts.frame, kind="stable")
    frame, xyz = pts.frame[order], pts.xyz_m[order]
    n = int(frame.max()) + 1
    starts = np.searchsorted(frame, np.arange(n + 1))
    target = int(args.mb * 1e6)
    written, done, lap = 0, 0, 0
    with open(args.out, "w", encoding="utf-8") as handle:
        handle.write(f"# rate_hz={RATE:g}\nframe,x,y,z\n")
        while written < target:
            seq = np.arange(n) if lap % 2 == 0 else np.arange(n - 1, -1, -1)
            for block in np.array_split(seq, 30):  # two seconds at a time
                rows = np.concatenate([np.arange(starts[f], starts[f + 1]) for f in block])
                out_frame = done + np.repeat(np.arange(len(block)),
                                             np.diff(starts)[block])
                text = io.StringIO()
                np.savetxt(text, np.column_stack([out_frame, xyz[rows]]),
                           fmt="%d,%.6f,%.6f,%.6f")
                handle.write(text.getvalue())
                written += len(text.getvalue())
                done += len(block)
                if written >= target:
                    break
            lap += 1
    (args.out.parent / f"{args.out.name}.bodies.toml").write_text(tomli_w.dumps(
        {"rigid_body": [{"name": b.name, "id": int(b.id), "markers": b.markers_body.tolist()}
                        for b in bodies]}))
    print(f"wrote {args.out}: {written / 1e6:.0f} MB, {done} frames "
          f"({done / RATE / 60:.1f} min at {RATE:g} Hz)")


if __name__ == "__main__":
    main()
