"""The scale of a wand solve of unknown length from an L-frame on the floor: its arms'
lengths in metres against the same arms reconstructed in the solve's units.

Why the L-frame's proportions and not its lengths: calibkit.calibrate.floor finds the
L-frame by its arms in metres, which a rig in units of an unmeasured wand does not have.
The arms' ratio and the right angle at the corner hold at any scale, so the L is found by
its shape and the scale read from its size.
"""

from __future__ import annotations

import itertools

import numpy as np

from calibkit.calibrate.floor import LFrame, static_markers
from calibkit.core.camera import Rig
from calibkit.core.errors import UserError

SHAPE_TOL = 0.03  # the sides' lengths fit the L's proportions within this share


def lframe_scale(rig: Rig, obs, lframe: LFrame | None = None) -> float:
    """Metres per unit of `rig`: the L-frame's arms (long_m + short_m) over the same arms
    among the markers standing still in `obs` (a recording made with the rig's cameras)."""
    lframe = lframe or LFrame()
    xyz = static_markers(rig, obs)
    hyp = float(np.hypot(lframe.long_m, lframe.short_m))
    found = []
    for i, j, k in itertools.permutations(range(len(xyz)), 3):
        a = np.linalg.norm(xyz[j] - xyz[i])  # corner to the long arm's end
        b = np.linalg.norm(xyz[k] - xyz[i])  # corner to the short arm's end
        c = np.linalg.norm(xyz[k] - xyz[j])
        if not a > 0:
            continue
        unit = a / lframe.long_m
        if abs(b / unit - lframe.short_m) <= SHAPE_TOL * lframe.short_m and \
                abs(c / unit - hyp) <= SHAPE_TOL * hyp:
            found.append((a + b) / (lframe.long_m + lframe.short_m))
    if not found:
        raise UserError(f"no L-frame (arms {lframe.long_m:g} : {lframe.short_m:g}) among the "
                        f"{len(xyz)} markers standing still in the floor recording: it cannot "
                        "set the scale; give --wand-length")
    if len(found) > 1:
        raise UserError("more than one set of markers in the floor recording has the "
                        "L-frame's shape: take other markers out of the volume, or give "
                        "--wand-length")
    return 1.0 / found[0]
