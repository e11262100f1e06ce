"""A rigid body defined from the markers a running daemon tracks, appended to mocapd.toml.

Shared by `mocapd rigid-body add --from-live` and the live view's body editor (daemon.view
.bodies): the view sits below the commands, so this work lives below both. The daemon is
asked through a callable (`ask()` returns one answer of its `markers` control request), so
the caller chooses the socket and the test a fake.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

import tomli_w
import tomllib

from calibkit.core.fileio import write_text_atomic

if TYPE_CHECKING:
    import numpy as np

# daemon.config.mocapd (the tracker, rigid bodies and their numba kernels) is imported where
# it is used, deferred on purpose: every mocapd command imports this module (through
# daemon/commands/rigid_cmd.py) to register its commands.


def body_from_markers(xyz: np.ndarray) -> np.ndarray:
    """Marker positions in a new body frame: origin at their centroid, axes the world's
    (the body's orientation is zero where it was defined)."""
    return xyz - xyz.mean(axis=0)


def free_markers(markers: list[dict], near: np.ndarray | None,
                 radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(track ids, positions) of the daemon's `markers` answer that belong to no body,
    within `radius` of `near` when given."""
    import numpy as np

    free = [m for m in markers if not m["body"]]
    ids = np.array([m["id"] for m in free], dtype=np.int64)
    xyz = np.array([m["xyz"] for m in free], dtype=np.float64).reshape(-1, 3)
    if near is not None:
        sel = np.linalg.norm(xyz - near, axis=1) <= radius
        ids, xyz = ids[sel], xyz[sel]
    return ids, xyz


def capture_snapshots(ask, n_frames: int, near: np.ndarray | None, radius: float,
                      interval_s: float = 0.01) -> list[tuple[np.ndarray, np.ndarray]]:
    """`n_frames` answers of the daemon's `markers` request (`ask()` returns one), a frame
    or so apart: the free markers it tracked in each."""
    out = []
    for k in range(n_frames):
        if k:
            time.sleep(interval_s)
        out.append(free_markers(ask()["markers"], near, radius))
    return out


def append_body(config_path: Path, name: str, body_id: int, markers: np.ndarray) -> None:
    """Add a [[rigid_body]] table at the end of the file (its comments stay), after checking
    that the whole file still validates."""
    import numpy as np

    from daemon.config.mocapd import parse_config  # deferred: see above

    text = config_path.read_text(encoding="utf-8") if config_path.exists() else ""
    table = {"rigid_body": [{"name": name, "id": body_id,
                             "markers": np.round(markers, 6).tolist()}]}
    new_text = text.rstrip("\n") + ("\n\n" if text.strip() else "") + tomli_w.dumps(table)
    parse_config(tomllib.loads(new_text), config_path, config_path.parent)
    write_text_atomic(config_path, new_text)
