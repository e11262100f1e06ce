"""Tracking rigid bodies in a file of 3D markers, as `mocapd track` runs it: reading the file
(points CSV, C3D, Motive CSV) into mocapd's z-up world, the bodies a Motive export defines,
their definitions fitted to the take's markers, the track, its figures (against Motive's own
poses when the file has them, and a hint per body never found) and the Motive CSV written
back.

Why everything is turned to z-up on reading: mocapd's world is z-up (docs/formats.md), and
so are its poses CSV and MCAP; Motive's is y-up. Turning the take once, markers and
Motive's poses together, keeps every comparison in one world; each output says which."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from calibkit.core.errors import UserError
from daemon.analysis.body_refine import closest_fit, hint, refine_bodies
from daemon.analysis.offline_track import (
    cloud_from_arrays,
    cloud_from_points,
    compare_poses,
    figures,
    track_cloud,
)
from daemon.analysis.point_tracks import PointTrackConfig
from daemon.formats.c3dio import csv_rate, read_c3d, read_points_csv
from daemon.formats.motive_csv import (
    MotiveBody,
    MotivePoses,
    MotiveTake,
    read_motive_csv,
    sniff,
    write_motive_csv,
)
from daemon.formats.motive_take import Y_UP_TO_Z_UP, from_z_up, to_z_up
from daemon.formats.trajectory_io import PoseTable
from daemon.tracking.rigid import BodyDef, RigidConfig


def load_markers(path: Path, rate_hz: float | None, up_axis: str | None = None,
                 points=None):
    """(MarkerCloud, MotiveTake or None, what the file is, the file's up axis) from any 3D
    marker file, in mocapd's z-up world. `up_axis` overrides the file's own: Motive's
    world is y-up (a table export made with a z-up axis convention needs 'z'); C3D and our
    points CSV are taken as z-up (a y-up C3D needs 'y')."""
    if not path.is_file():
        raise UserError(f"{path} not found")
    suffix = path.suffix.lower()
    if suffix == ".c3d":
        take = read_c3d(path)
        idx = np.arange(take.n_frames)
        up = up_axis or "z"
        cloud = cloud_from_arrays(_z_up(take.xyz_m, up), idx / take.rate_hz,
                                  take.first_frame + idx)
        return cloud, None, f"C3D, {take.rate_hz:g} Hz", up
    if suffix != ".csv":
        raise UserError(f"{path}: markers are read from .csv (ours or Motive's) or .c3d "
                        f"files, got {suffix or 'no suffix'}")
    if sniff(path) is not None:
        motive = read_motive_csv(path, up_axis)
        up = motive.up_axis
        motive = to_z_up(motive)
        return (cloud_from_arrays(motive.all_markers(), motive.t_s, motive.frame), motive,
                f"Motive CSV {motive.meta.get('format_version', '')}", up)
    points = read_points_csv(path) if points is None else points  # given: read by the caller
    rate = rate_hz or csv_rate(path)
    if rate is None:
        raise UserError(f"{path} has no frame rate: give --rate HZ (the cameras' rate)")
    if not len(points.frame):
        raise UserError(f"{path}: holds no points")
    up = up_axis or "z"
    if up == "y":
        points = replace(points, xyz_m=_z_up(np.asarray(points.xyz_m, dtype=np.float64), up))
    return cloud_from_points(points, rate), None, f"points CSV, {rate:g} Hz", up


def _z_up(xyz: np.ndarray, up_axis: str) -> np.ndarray:
    return xyz @ Y_UP_TO_Z_UP.T if up_axis == "y" else xyz


def axes_note(up_axis: str) -> str:
    """What every output of `mocapd track` says about its world and units."""
    note = "world z-up, metres, quaternions x y z w body to world"
    if up_axis == "y":
        note += "; the input was y-up, turned to z-up: (x, y, z) -> (x, -z, y)"
    return note


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


HINT_BELOW = 0.05  # a body posed in fewer than this share of the frames gets a hint


def track_file(cloud, motive, defs, rigid_cfg: RigidConfig, gate_mm: float, gross_mm: float,
               progress=None, refine: str = "auto") -> tuple[PoseTable, dict, list]:
    """The daemon's rigid tracker over the whole take: the poses as a table, the figures
    (per body, and against Motive's own poses where the file has them) and the definitions
    the poses were made with. First each definition is fitted to the take's markers
    (daemon.analysis.body_refine; `refine` auto, on or off); a body posed in almost no frame
    gets a hint (figs['hints']): its closest fit and what to change."""
    start = time.perf_counter()
    tol_m = rigid_cfg.distance_tol_m
    used, refits = refine_bodies(cloud.xyz, list(defs), tol_m, refine)
    result = track_cloud(cloud, used, replace(rigid_cfg, refine=False),
                         PointTrackConfig(gate_m=gate_mm / 1000.0), progress=progress)
    elapsed = time.perf_counter() - start
    figs = figures(result, gross_mm)
    figs["frames_per_s"] = len(cloud) / elapsed if elapsed > 0 else None
    add_hints(figs, cloud.xyz, defs, used, refits, tol_m)
    if motive is not None:
        against = {}
        for name in result.names:
            theirs = motive.poses.get(name)
            if theirs is not None:
                against[name] = compare_poses(result, name, motive.frame, theirs.valid,
                                              theirs.xyz_m, theirs.quat_xyzw)
        if against:
            figs["against_motive"] = against
    return pose_table(result), figs, used


def add_hints(figs: dict, xyz, defs, used, refits, tol_m: float) -> None:
    """Into the figures: what refining did to each definition, and for a body posed in
    almost no frame its closest fit in the take's frames `xyz` (F, P, 3; only a few of
    them are looked at) and a hint saying what to change (figs['hints'])."""
    figs["hints"] = []
    for b, (body, refit) in enumerate(zip(used, refits, strict=True)):
        share = figs["bodies"][body.name]["valid_fraction"]
        figs["bodies"][body.name]["refine"] = refit.summary()
        if share < HINT_BELOW and len(xyz):
            fit = closest_fit(xyz, defs[b])
            figs["bodies"][body.name]["closest_fit_mm"] = (
                None if fit.residual_m is None else round(fit.residual_m * 1000.0, 3))
            figs["hints"].append(hint(defs[b], fit, tol_m, refit, share))


def pose_table(result) -> PoseTable:
    """A TrackResult's poses as the poses CSV and MCAP writers take them (error in mm)."""
    return PoseTable(result.frame, result.t_s, result.names, result.ids, result.valid,
                     result.position, result.quaternion, result.error_m * 1000.0,
                     result.n_markers)


def write_motive(path: Path, cloud, table: PoseTable, defs, up_axis: str = "z") -> None:
    """Our markers (unlabelled) and poses in Motive's table layout, in the input's world
    (`up_axis` 'y' turns them back into Motive's y-up one), its Up Axis recorded."""
    bodies = [MotiveBody(b.name, b.id, b.markers - b.pivot) for b in defs]
    poses = {b.name: MotivePoses(table.valid[:, i], table.xyz[:, i],
                                 table.quat[:, i], table.error_mm[:, i] / 1000.0)
             for i, b in enumerate(defs)}
    dt = np.diff(cloud.t_s)
    rate = float(1.0 / np.median(dt)) if len(dt) and np.median(dt) > 0 else 0.0
    take = MotiveTake(cloud.frame, cloud.t_s, rate, [], np.zeros((len(cloud), 0, 3)),
                      cloud.xyz, bodies, poses, {"up_axis": "z"})
    write_motive_csv(path, from_z_up(take, up_axis), path.stem)
