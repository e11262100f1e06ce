"""What a display shows: dots at sub-pixel screen positions (no OpenGL here).

Captures and calibration build `Dots` and hand them to whatever display they were given
(a window, the simulator's off-screen renderer, a test double), so they never import the
renderer itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Dots:
    """What one frame shows: dot centres (N, 2) in screen pixels, radii (N,) and levels (N,)."""

    xy: np.ndarray
    radius_px: np.ndarray
    level: np.ndarray

    @classmethod
    def make(cls, xy, radius_px: float | np.ndarray = 4.0, level: float | np.ndarray = 1.0
             ) -> Dots:
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        n = len(xy)
        return cls(xy, np.broadcast_to(np.asarray(radius_px, np.float64), (n,)).copy(),
                   np.broadcast_to(np.asarray(level, np.float64), (n,)).copy())
