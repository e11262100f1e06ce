"""Frames of a simulated camera: rendered images of markers, for the detector and its tests.

What a real camera gives (an image, an index, a time) plus the true marker centres, which
only scorers read.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from calibkit.cameras import Frame, FrameSource
from calibkit.core.camera import Camera
from calibkit.core.errors import UserError
from calibkit.synthetic import sim
from calibkit.synthetic.reflections import make_reflections
from calibkit.synthetic.sim import render_frame


class SimSource(FrameSource):
    """Frames of one simulated camera looking at markers (calibkit.synthetic.sim).

    The frames are what a camera gives; the true centres of the visible markers stay here,
    in `truth_uv[frame index]`, for scorers only.

    xyz: (F, N, 3) marker positions per frame, or (N, 3) for static markers shown for
    `n_frames` frames. Extra keyword arguments go to calibkit.synthetic.sim.render_frame.
    """

    def __init__(self, camera, xyz: np.ndarray, n_frames: int | None = None,
                 fps: float = 100.0, seed: int = 0, **render_kwargs) -> None:
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.ndim == 2:
            xyz = np.broadcast_to(xyz, (n_frames or 1, *xyz.shape))
        elif n_frames is not None:
            xyz = xyz[:n_frames]
        self.cam = camera
        self.camera = camera.name
        self.xyz = xyz
        self.fps = fps
        self.seed = seed
        self.render_kwargs = render_kwargs
        self.truth_uv: dict[int, np.ndarray] = {}

    def __iter__(self) -> Iterator[Frame]:
        for i, pts in enumerate(self.xyz):
            image, uv, visible = render_frame(self.cam, pts, seed=self.seed + i,
                                              **self.render_kwargs)
            self.truth_uv[i] = np.asarray(uv)[np.asarray(visible, dtype=bool)]
            yield Frame(self.camera, i, round(i * 1e9 / self.fps), image)


def sim_camera(camera: int | str = 0, seed: int = 0) -> Camera:
    """A camera of the default simulated rig (by index or name)."""
    rig = sim.make_rig(seed=seed)
    try:
        return rig[camera]
    except (IndexError, KeyError) as exc:
        raise UserError(f"the simulated rig has no camera {camera!r}; it has "
                        f"{', '.join(rig.names)}") from exc


def sim_source(n_markers: int = 40, n_frames: int = 1, camera: int | str = 0,
               seed: int = 0, reflections: int = 0, **render_kwargs) -> SimSource:
    """The default simulated scene: static markers in the sim rig's volume, seen by one
    camera; with `reflections`, that camera also sees that many static reflections
    (calibkit.synthetic.reflections), the same ones for a camera and seed."""
    cam = sim_camera(camera, seed)
    if reflections:
        render_kwargs["stray"] = make_reflections(cam, reflections, seed).as_stray()
    truth = sim.static_markers(n_markers, n_frames=n_frames, seed=seed)
    frames = np.unique(truth.frame)
    xyz = np.stack([truth.at_frame(int(f))[1] for f in frames])
    return SimSource(cam, xyz, seed=seed, **render_kwargs)


def empty_volume(n_frames: int, camera: int | str = 0, seed: int = 0, reflections: int = 8,
                 **render_kwargs) -> SimSource:
    """The same camera with every marker taken out of the volume: background, noise and its
    reflections, each frame with its own noise, as a user records frames for `calibkit
    mask`."""
    cam = sim_camera(camera, seed)
    stray = make_reflections(cam, reflections, seed).as_stray()
    return SimSource(cam, np.zeros((n_frames, 0, 3)), seed=seed + 7000, stray=stray,
                     **render_kwargs)
