"""BVH motion files: a skeleton's hierarchy and per-frame joint rotations written and read
back, with the Z-X-Y Euler angles BVH channels carry.

Apart from daemon/formats/c3dio.py (marker takes and points), since a BVH holds joints, not
markers: only the skeleton writes it (daemon/analysis/skeleton.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibkit.core.fileio import atomic_write


def write_bvh(path: str | Path, names: list[str], parents: list[int], offsets_m: np.ndarray,
              root_pos_m: np.ndarray, rotations: np.ndarray, rate_hz: float) -> None:
    """Write a BVH motion: joints `names` with `parents` (-1 for the root), rest offsets
    from the parent (metres; written in centimetres, as most BVH readers expect), the root's
    position per frame and every joint's local rotation per frame (frames, joints, 3, 3).

    Channels are Zrotation Xrotation Yrotation (intrinsic, the common BVH order): the Euler
    angles are extracted so that R = Rz @ Rx @ Ry.
    """
    children: dict[int, list[int]] = {i: [] for i in range(len(names))}
    for i, p in enumerate(parents):
        if p >= 0:
            children[p].append(i)
    order: list[int] = []
    lines: list[str] = ["HIERARCHY"]
    offsets_cm = np.asarray(offsets_m) * 100.0

    def emit(j: int, depth: int) -> None:
        pad = "  " * depth
        order.append(j)
        kind = "ROOT" if parents[j] < 0 else "JOINT"
        lines.append(f"{pad}{kind} {names[j]}")
        lines.append(f"{pad}{{")
        ox, oy, oz = offsets_cm[j]
        lines.append(f"{pad}  OFFSET {ox:.4f} {oy:.4f} {oz:.4f}")
        if parents[j] < 0:
            lines.append(f"{pad}  CHANNELS 6 Xposition Yposition Zposition "
                         "Zrotation Xrotation Yrotation")
        else:
            lines.append(f"{pad}  CHANNELS 3 Zrotation Xrotation Yrotation")
        if children[j]:
            for c in children[j]:
                emit(c, depth + 1)
        else:
            lines.append(f"{pad}  End Site")
            lines.append(f"{pad}  {{")
            lines.append(f"{pad}    OFFSET 0.0000 0.0000 0.0000")
            lines.append(f"{pad}  }}")
        lines.append(f"{pad}}}")

    roots = [i for i, p in enumerate(parents) if p < 0]
    if len(roots) != 1:
        raise ValueError("a BVH hierarchy has exactly one root")
    emit(roots[0], 0)
    n_frames = rotations.shape[0]
    eul = zxy_euler_deg(rotations[:, order])          # (frames, joints, 3)
    cols = [root_pos_m * 100.0, eul.reshape(n_frames, -1)]
    motion = np.concatenate(cols, axis=1)
    lines += ["MOTION", f"Frames: {n_frames}", f"Frame Time: {1.0 / rate_hz:.8f}"]
    body = "\n".join(" ".join(f"{v:.4f}" for v in row) for row in motion)
    with atomic_write(path, "w", encoding="utf-8") as handle:
        handle.write("\n".join(lines) + "\n" + body + "\n")


def zxy_euler_deg(R: np.ndarray) -> np.ndarray:
    """Angles (z, x, y) in degrees with R = Rz(z) @ Rx(x) @ Ry(y), vectorised."""
    # R = Rz Rx Ry: R[2,1] = sin x; R[0,1] = -sin z cos x; R[1,1] = cos z cos x;
    # R[2,0] = -cos x sin y; R[2,2] = cos x cos y
    x = np.arcsin(np.clip(R[..., 2, 1], -1.0, 1.0))
    z = np.arctan2(-R[..., 0, 1], R[..., 1, 1])
    y = np.arctan2(-R[..., 2, 0], R[..., 2, 2])
    return np.degrees(np.stack([z, x, y], axis=-1))


def euler_zxy_matrix(deg: np.ndarray) -> np.ndarray:
    """Inverse of zxy_euler_deg: (..., 3) degrees -> (..., 3, 3)."""
    z, x, y = np.radians(deg[..., 0]), np.radians(deg[..., 1]), np.radians(deg[..., 2])
    cz, sz, cx, sx, cy, sy = np.cos(z), np.sin(z), np.cos(x), np.sin(x), np.cos(y), np.sin(y)
    one, zero = np.ones_like(z), np.zeros_like(z)
    Rz = np.stack([np.stack([cz, -sz, zero], -1), np.stack([sz, cz, zero], -1),
                   np.stack([zero, zero, one], -1)], -2)
    Rx = np.stack([np.stack([one, zero, zero], -1), np.stack([zero, cx, -sx], -1),
                   np.stack([zero, sx, cx], -1)], -2)
    Ry = np.stack([np.stack([cy, zero, sy], -1), np.stack([zero, one, zero], -1),
                   np.stack([-sy, zero, cy], -1)], -2)
    return Rz @ Rx @ Ry


def read_bvh(path: str | Path) -> tuple[list[str], list[int], np.ndarray, np.ndarray]:
    """Read back what write_bvh writes: names, parents, offsets (m), motion (frames, cols)."""
    text = Path(path).read_text(encoding="utf-8").split("\n")
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    stack: list[int] = []
    i = 0
    pending_end = False
    while i < len(text) and text[i].strip() != "MOTION":
        tok = text[i].split()
        if tok and tok[0] in ("ROOT", "JOINT"):
            names.append(tok[1])
            parents.append(stack[-1] if stack else -1)
            stack.append(len(names) - 1)
        elif tok and tok[0] == "End":
            pending_end = True
        elif tok and tok[0] == "OFFSET" and not pending_end:
            offsets.append([float(v) / 100.0 for v in tok[1:4]])
        elif tok and tok[0] == "}":
            if pending_end:
                pending_end = False
            else:
                stack.pop()
        i += 1
    rows = [line.split() for line in text[i + 3:] if line.strip()]
    motion = np.array(rows, dtype=np.float64)
    return names, parents, np.array(offsets), motion
