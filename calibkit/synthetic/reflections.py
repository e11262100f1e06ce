"""Static reflections a simulated camera sees (lamps, glints on fittings, other cameras'
LEDs), the frames `calibkit mask --sim` builds a mask from, and that mask scored against
the truth.

A reflection belongs to the room, not to the markers: it stays at one place in the image
while markers come and go. Each has its own size and brightness, from a glint of a pixel or
two to a lamp a dozen pixels across, and some are dim, a few DN above the detection
threshold at their centre and below it at their edge, so that sensor noise makes their
outline flicker from frame to frame: what a mask made from one frame misses and a few
frames plus a small dilation catch. The same camera (`calibkit detect --sim --reflections
N`) sees them with the markers in view, which is where a mask earns its keep.

The estimate (the mask builder) gets only the frames; `Reflections` and the markers' true
images stay here, for `score_mask`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibkit.core.camera import Camera
from calibkit.core.errors import UserError
from calibkit.synthetic.sim import MARKER_RADIUS_M

MAX_REFLECTIONS = 200


@dataclass(frozen=True, eq=False)
class Reflections:
    """One camera's reflections: centres (S, 2) px, radii (S,) px, brightness (S,) DN (what a
    fully lit pixel gains above the background)."""

    uv: np.ndarray
    radius_px: np.ndarray
    peak_dn: np.ndarray

    def __len__(self) -> int:
        return len(self.uv)

    def as_stray(self) -> np.ndarray:
        """Rows (u, v, radius_px, peak) as calibkit.synthetic.sim.render_frame draws them."""
        return np.column_stack([self.uv, self.radius_px, self.peak_dn])


def make_reflections(camera: Camera, n: int, seed: int = 0) -> Reflections:
    """`n` reflections fixed in `camera`'s image, the same for a camera and seed: a third
    small glints (1-2.5 px), a third medium (2.5-6 px), a third lamps (6-12 px); brightness
    from dim (25 DN above the background) to saturating."""
    if not 0 <= n <= MAX_REFLECTIONS:
        raise UserError(f"--reflections must be between 0 and {MAX_REFLECTIONS}, got {n}")
    rng = np.random.default_rng([seed, 0x5EF1EC7])
    kind = np.arange(n) % 3
    low, high = np.array([1.0, 2.5, 6.0]), np.array([2.5, 6.0, 12.0])
    radius = rng.uniform(low[kind], high[kind])
    w, h = camera.size
    uv = np.column_stack([rng.uniform(radius, w - 1 - radius), rng.uniform(radius,
                                                                           h - 1 - radius)])
    peak = np.exp(rng.uniform(np.log(25.0), np.log(250.0), n))
    return Reflections(uv, radius, peak)


def marker_discs(camera: Camera, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where markers at `xyz` (N, 3) image in `camera`, as render_frame draws them: centres
    (M, 2) and radii (M,) px of those in front of it and in the image."""
    uv, front = camera.project(xyz)
    seen = front & camera.in_image(uv)
    depth = camera.to_camera(xyz[seen])[:, 2]
    return uv[seen], MARKER_RADIUS_M * camera.fx / depth


def _disc_pixels(shape: tuple[int, int], uv: np.ndarray, radius: np.ndarray
                 ) -> list[np.ndarray]:
    """Flat indices of the pixels whose centre lies in each disc (at least the nearest)."""
    h, w = shape
    out = []
    for (u, v), r in zip(uv, radius, strict=True):  # one small window per disc, not per pixel
        x0, x1 = max(int(np.floor(u - r)), 0), min(int(np.ceil(u + r)), w - 1)
        y0, y1 = max(int(np.floor(v - r)), 0), min(int(np.ceil(v + r)), h - 1)
        yy, xx = np.mgrid[y0:y1 + 1, x0:x1 + 1]
        inside = (xx - u) ** 2 + (yy - v) ** 2 <= max(r, 0.5) ** 2
        flat = (yy * w + xx)[inside]
        if not len(flat):
            flat = np.array([min(max(round(v), 0), h - 1) * w + min(max(round(u), 0), w - 1)])
        out.append(flat)
    return out


def score_mask(mask: np.ndarray, reflections: Reflections, marker_uv: np.ndarray,
               marker_radius_px: np.ndarray) -> dict:
    """A mask (bool (h, w), True = ignored) against the truth: how much of each reflection's
    disc it covers, and how many markers' images it touches (any pixel of the disc) or
    hides (the centre)."""
    flat = np.asarray(mask, dtype=bool).ravel()
    cover = np.array([flat[p].mean() for p in _disc_pixels(mask.shape, reflections.uv,
                                                           reflections.radius_px)])
    marks = _disc_pixels(mask.shape, marker_uv, marker_radius_px)
    touched = np.array([flat[p].any() for p in marks], dtype=bool)
    h, w = mask.shape
    centre = np.clip(np.rint(marker_uv).astype(np.int64), 0, [w - 1, h - 1])
    hidden = mask[centre[:, 1], centre[:, 0]] if len(centre) else np.zeros(0, bool)
    return {"reflections": len(reflections),
            "reflections_covered": int((cover >= 1.0).sum()),
            "reflection_pixels_covered": float(cover.mean()) if len(cover) else 1.0,
            "markers": len(marks), "markers_touched": int(touched.sum()),
            "markers_hidden": int(np.asarray(hidden).sum()),
            "masked_fraction": float(flat.mean())}
