"""3D painting: a tracked wand's tip draws strokes in the air, saved as a PLY file.

    python examples/paint3d.py --port 9870 --body 2 --tip 0,0,0.12 --seconds 30 \
        --out painting.ply

The pen is down while the wand is tracked; a stroke ends when the wand is lost for longer
than `--gap-s` or its tip jumps further than `--jump-m` between frames (a re-acquired body
should not draw a line across the room). Points closer than `--spacing-m` to the last one
are dropped, so a wand held still does not pile up points. The PLY holds the points
(coloured per stroke) and the edges joining them in drawing order; MeshLab and Blender
open it. `--tip`: the pen's tip in the wand body's frame (metres).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class Painting:
    """Strokes built from a stream of poses."""

    tip: np.ndarray
    gap_s: float = 0.1
    jump_m: float = 0.1
    spacing_m: float = 0.002
    strokes: list[list[np.ndarray]] = field(default_factory=list)
    _last_seen_ns: int | None = None
    _pen_down: bool = False

    def add(self, t_ns: int, valid: bool, position, rotation) -> None:
        """One frame's pose of the wand (rotation body to world; ignored when not valid)."""
        if not valid:
            if self._last_seen_ns is not None and t_ns - self._last_seen_ns > self.gap_s * 1e9:
                self._pen_down = False
            return
        point = np.asarray(position, float) + np.asarray(rotation, float) @ self.tip
        gone = self._last_seen_ns is not None and t_ns - self._last_seen_ns > self.gap_s * 1e9
        self._last_seen_ns = t_ns
        if not self._pen_down or gone or np.linalg.norm(point - self.strokes[-1][-1]) \
                > self.jump_m:
            self.strokes.append([point])
            self._pen_down = True
        elif np.linalg.norm(point - self.strokes[-1][-1]) >= self.spacing_m:
            self.strokes[-1].append(point)

    def points(self) -> list[np.ndarray]:
        """Each stroke as an (N, 3) array; single-point strokes left out (a flicker)."""
        return [np.array(s) for s in self.strokes if len(s) > 1]


def stroke_colours(n: int) -> np.ndarray:
    """Distinct colours (uint8 RGB) along the hue circle."""
    import colorsys

    return np.array([[round(255 * c) for c in colorsys.hsv_to_rgb(i / max(n, 1) * 0.9, 0.8, 1)]
                     for i in range(n)], dtype=np.uint8)


def write_ply(path: Path, strokes: list[np.ndarray]) -> None:
    """ASCII PLY: vertices (x y z, metres; red green blue) and the edges of each stroke;
    written whole or not at all."""
    from calibkit.core.fileio import write_text_atomic

    colours = stroke_colours(len(strokes))
    vertices, edges, start = [], [], 0
    for stroke, colour in zip(strokes, colours, strict=True):
        vertices += [f"{x:.6f} {y:.6f} {z:.6f} {colour[0]} {colour[1]} {colour[2]}"
                     for x, y, z in stroke]
        edges += [f"{start + i} {start + i + 1}" for i in range(len(stroke) - 1)]
        start += len(stroke)
    header = ["ply", "format ascii 1.0", "comment mocapd paint3d: metres, world frame",
              f"element vertex {len(vertices)}", "property float x", "property float y",
              "property float z", "property uchar red", "property uchar green",
              "property uchar blue", f"element edge {len(edges)}", "property int vertex1",
              "property int vertex2", "end_header"]
    write_text_atomic(path, "\n".join(header + vertices + edges) + "\n")


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N, 3), edges (E, 2)) of a PLY this program wrote."""
    lines = Path(path).read_text().splitlines()
    n_v = int(next(ln for ln in lines if ln.startswith("element vertex")).split()[2])
    n_e = int(next(ln for ln in lines if ln.startswith("element edge")).split()[2])
    body = lines[lines.index("end_header") + 1:]
    v = np.array([[float(x) for x in ln.split()[:3]] for ln in body[:n_v]]).reshape(-1, 3)
    e = np.array([[int(x) for x in ln.split()] for ln in body[n_v:n_v + n_e]]).reshape(-1, 2)
    return v, e


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--port", type=int, required=True, help="mocapd's [[udp]] port")
    ap.add_argument("--body", type=int, required=True, help="the wand's rigid-body id")
    ap.add_argument("--tip", default="0,0,0", help="the pen's tip in the wand's frame, m")
    ap.add_argument("--seconds", type=float, default=30.0,
                    help="how long to paint, from the first pose received")
    ap.add_argument("--timeout", type=float, default=10.0,
                    help="give up after this long without a packet")
    ap.add_argument("--gap-s", type=float, default=0.1)
    ap.add_argument("--jump-m", type=float, default=0.1)
    ap.add_argument("--spacing-m", type=float, default=0.002)
    ap.add_argument("--out", type=Path, required=True, help="the PLY to write")
    args = ap.parse_args(argv)
    try:
        tip = np.array([float(v) for v in args.tip.split(",")])
    except ValueError:
        tip = np.zeros(0)
    if tip.shape != (3,):
        print(f"paint3d: --tip needs x,y,z in metres, got {args.tip!r}", file=sys.stderr)
        return 2
    if args.out.suffix.lower() != ".ply":
        print(f"paint3d: --out is a PLY file (.ply), got {args.out}", file=sys.stderr)
        return 2

    import time

    from mocap_udp import PoseReceiver

    painting = Painting(tip, args.gap_s, args.jump_m, args.spacing_m)
    rx = PoseReceiver(args.port)
    end = None
    frames = 0
    try:
        for _frame, t_ns, valid, position, rotation in rx.every(args.body, args.timeout):
            painting.add(t_ns, valid, position, rotation)
            frames += 1
            end = end or time.monotonic() + args.seconds
            if time.monotonic() > end:
                break
    finally:
        rx.close()
    strokes = painting.points()
    if not strokes:
        print(f"paint3d: body {args.body} drew nothing in {frames} frames (is it tracked, "
              "and is the port mocapd's [[udp]] output?)", file=sys.stderr)
        return 1
    write_ply(args.out, strokes)
    print(f"wrote {args.out}: {len(strokes)} strokes, {sum(map(len, strokes))} points "
          f"from {frames} frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())
