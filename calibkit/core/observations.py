"""2D observations (one row per blob) and 3D ground truth: the tables every stage passes on.

Columnar numpy arrays rather than objects per blob, so that filtering by camera or frame,
undistorting and triangulating stay vectorised.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(eq=False)
class Observations:
    """Blobs seen by the cameras of a rig, one row per blob.

    `camera` indexes `camera_names`; `marker` is the simulator's true marker id (-1 for a
    ghost/stray blob), or the label a file gives (a DLTdv xypts point index, see
    calibkit.core.easywand; meta says which), and is None for unlabelled real data.
    """

    camera_names: tuple[str, ...]
    camera_sizes: tuple[tuple[int, int], ...]
    frame: np.ndarray  # int64 (N,)
    camera: np.ndarray  # int32 (N,)
    t_ns: np.ndarray  # int64 (N,) capture time of the blob's frame
    uv: np.ndarray  # float64 (N, 2) pixels, centres at integer coordinates
    area: np.ndarray  # float32 (N,) pixels
    peak: np.ndarray  # float32 (N,) brightest pixel value
    marker: np.ndarray | None = None  # int32 (N,) truth, simulated data only
    fps: float | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.frame)
        self.frame = np.asarray(self.frame, dtype=np.int64).reshape(n)
        self.camera = np.asarray(self.camera, dtype=np.int32).reshape(n)
        self.t_ns = np.asarray(self.t_ns, dtype=np.int64).reshape(n)
        self.uv = np.asarray(self.uv, dtype=np.float64).reshape(n, 2)
        self.area = np.asarray(self.area, dtype=np.float32).reshape(n)
        self.peak = np.asarray(self.peak, dtype=np.float32).reshape(n)
        if self.marker is not None:
            self.marker = np.asarray(self.marker, dtype=np.int32).reshape(n)
        self.camera_names = tuple(self.camera_names)
        self.camera_sizes = tuple((int(w), int(h)) for w, h in self.camera_sizes)

    def __len__(self) -> int:
        return len(self.frame)

    @classmethod
    def empty(cls, camera_names, camera_sizes) -> Observations:
        z = np.zeros(0)
        return cls(camera_names, camera_sizes, z, z, z, np.zeros((0, 2)), z, z)

    def select(self, mask: np.ndarray) -> Observations:
        """The rows where `mask` (bool or index array) holds."""
        return Observations(
            self.camera_names, self.camera_sizes, self.frame[mask], self.camera[mask],
            self.t_ns[mask], self.uv[mask], self.area[mask], self.peak[mask],
            None if self.marker is None else self.marker[mask], self.fps, dict(self.meta))

    def frames(self) -> np.ndarray:
        """The distinct frame numbers, sorted."""
        return np.unique(self.frame)

    def sorted(self) -> Observations:
        """Rows ordered by frame, then camera (stable), as files store them."""
        order = np.lexsort((self.camera, self.frame))
        return self.select(order)

    @staticmethod
    def concatenate(parts: list[Observations]) -> Observations:
        first = parts[0]
        cat = np.concatenate
        marker = None
        if all(p.marker is not None for p in parts):
            marker = cat([p.marker for p in parts])
        return Observations(first.camera_names, first.camera_sizes,
                            cat([p.frame for p in parts]), cat([p.camera for p in parts]),
                            cat([p.t_ns for p in parts]), cat([p.uv for p in parts]),
                            cat([p.area for p in parts]), cat([p.peak for p in parts]),
                            marker, first.fps, dict(first.meta))


@dataclass(eq=False)
class Truth:
    """Ground-truth 3D marker positions, one row per (frame, marker), metres, world frame."""

    frame: np.ndarray  # int64 (M,)
    marker: np.ndarray  # int32 (M,)
    xyz: np.ndarray  # float64 (M, 3)

    def __post_init__(self) -> None:
        m = len(self.frame)
        self.frame = np.asarray(self.frame, dtype=np.int64).reshape(m)
        self.marker = np.asarray(self.marker, dtype=np.int32).reshape(m)
        self.xyz = np.asarray(self.xyz, dtype=np.float64).reshape(m, 3)

    def __len__(self) -> int:
        return len(self.frame)

    def select(self, mask: np.ndarray) -> Truth:
        return Truth(self.frame[mask], self.marker[mask], self.xyz[mask])

    def at_frame(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """(marker ids, positions) of one frame."""
        m = self.frame == frame
        return self.marker[m], self.xyz[m]
