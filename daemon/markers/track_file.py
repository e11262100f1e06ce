"""Tracking rigid bodies in a file of 3D markers, as `mocapd track` runs it: reading the file
(points CSV, C3D, Motive CSV), the bodies a Motive export defines, the track, its figures
(against Motive's own poses when the file has them) and the Motive CSV written back."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from calibkit.core.errors import UserError
from daemon.markers.c3dio import csv_rate, read_c3d, read_points_csv
from daemon.markers.motive_csv import (
    MotiveBody,
    MotivePoses,
    MotiveTake,
    read_motive_csv,
    sniff,
    write_motive_csv,
)
from daemon.markers.offline_track import (
    cloud_from_arrays,
    cloud_from_points,
    compare_poses,
    figures,
    track_cloud,
)
from daemon.markers.point_tracks import PointTrackConfig
from daemon.markers.trajectory_io import PoseTable
from daemon.rigid import BodyDef, RigidConfig


def load_markers(path: Path, rate_hz: float | None):
    """(MarkerCloud, MotiveTake or None, what the file is) from any 3D marker file."""
    if not path.is_file():
        raise UserError(f"{path} not found")
    suffix = path.suffix.lower()
    if suffix == ".c3d":
        take = read_c3d(path)
        idx = np.arange(take.n_frames)
        return (cloud_from_arrays(take.xyz_m, idx / take.rate_hz, take.first_frame + idx),
                None, f"C3D, {take.rate_hz:g} Hz")
    if suffix != ".csv":
        raise UserError(f"{path}: markers are read from .csv (ours or Motive's) or .c3d "
                        f"files, got {suffix or 'no suffix'}")
    if sniff(path) is not None:
        motive = read_motive_csv(path)
        return (cloud_from_arrays(motive.all_markers(), motive.t_s, motive.frame), motive,
                f"Motive CSV {motive.meta.get('format_version', '')}")
    points = read_points_csv(path)
    rate = rate_hz or csv_rate(path)
    if rate is None:
        raise UserError(f"{path} has no frame rate: give --rate HZ (the cameras' rate)")
    if not len(points.frame):
        raise UserError(f"{path}: holds no points")
    return cloud_from_points(points, rate), None, f"points CSV, {rate:g} Hz"


def bodies_from_motive(motive, path: Path) -> list:
    """Motive's rigid-body definitions as the daemon's BodyDefs (pivot at the origin of
    the template, which is where Motive reports the body)."""
    if motive is None:
        raise UserError(f"{path} is not a Motive CSV: --bodies-from-file takes the bodies "
                        "of a Motive export; give --bodies mocapd.toml instead")
    out = []
    for b in motive.bodies:
        k = len(b.offsets_m)
        if k < 3:
            raise UserError(f"{path}: rigid body {b.name!r} has {k} template markers in the "
                            "file (export its Rigid Body Markers too); 3 are needed")
        out.append(BodyDef(b.name, b.id, b.offsets_m.copy(), np.zeros(3),
                           min(k, 4) if k >= 4 else 3, 3, 0.0))
    if not out:
        raise UserError(f"{path} defines no rigid bodies; give --bodies mocapd.toml")
    return out


def track_file(cloud, motive, defs, rigid_cfg: RigidConfig, gate_mm: float, gross_mm: float,
               progress=None) -> tuple[PoseTable, dict]:
    """The daemon's rigid tracker over the whole take: the poses as a table and the figures
    (per body, and against Motive's own poses where the file has them)."""
    start = time.perf_counter()
    result = track_cloud(cloud, defs, replace(rigid_cfg, refine=False),
                         PointTrackConfig(gate_m=gate_mm / 1000.0), progress=progress)
    elapsed = time.perf_counter() - start
    figs = figures(result, gross_mm)
    figs["frames_per_s"] = len(cloud) / elapsed if elapsed > 0 else None
    if motive is not None:
        against = {}
        for name in result.names:
            theirs = motive.poses.get(name)
            if theirs is not None:
                against[name] = compare_poses(result, name, motive.frame, theirs.valid,
                                              theirs.xyz_m, theirs.quat_xyzw)
        if against:
            figs["against_motive"] = against
    table = PoseTable(result.frame, result.t_s, result.names, result.ids, result.valid,
                      result.position, result.quaternion, result.error_m * 1000.0,
                      result.n_markers)
    return table, figs


def write_motive(path: Path, cloud, table: PoseTable, defs) -> None:
    """Our markers (unlabelled) and poses in Motive's modern layout."""
    bodies = [MotiveBody(b.name, b.id, b.markers - b.pivot) for b in defs]
    poses = {b.name: MotivePoses(table.valid[:, i], table.xyz[:, i],
                                 table.quat[:, i], table.error_mm[:, i] / 1000.0)
             for i, b in enumerate(defs)}
    dt = np.diff(cloud.t_s)
    rate = float(1.0 / np.median(dt)) if len(dt) and np.median(dt) > 0 else 0.0
    take = MotiveTake(cloud.frame, cloud.t_s, rate, [], np.zeros((len(cloud), 0, 3)),
                      cloud.xyz, bodies, poses)
    write_motive_csv(path, take, path.stem)
