"""`mocapd track`: rigid-body poses from a file of 3D markers (points CSV, C3D, Motive CSV)."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from calibkit.clitools import Progress, print_table, write_json
from calibkit.core.errors import UserError


def load_markers(path: Path, rate_hz: float | None):
    """(MarkerCloud, MotiveTake or None, what the file is) from any 3D marker file."""
    from daemon.markers.c3dio import csv_rate, read_c3d, read_points_csv
    from daemon.markers.motive_csv import read_motive_csv, sniff
    from daemon.markers.offline_track import cloud_from_arrays, cloud_from_points

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
    from daemon.rigid import BodyDef

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


def register(app: typer.Typer) -> None:
    @app.command("track")
    def track_cmd(
        markers: Annotated[Path, typer.Argument(
            help="3D markers: a points CSV (calibkit triangulate --out), a C3D or a Motive "
                 "CSV export.")],
        out: Annotated[Path, typer.Option(
            "--out", help="Poses to write: a CSV, or an MCAP (.mcap: Foxglove's schemas, "
                          "the markers too).")],
        bodies: Annotated[Path | None, typer.Option(
            "--bodies", help="mocapd.toml whose [[rigid_body]] tables (and [rigid] "
                             "settings) to track.")] = None,
        from_file: Annotated[bool, typer.Option(
            "--bodies-from-file", "--from-motive",
            help="Track the rigid bodies a Motive CSV defines.")] = False,
        rate: Annotated[float | None, typer.Option(
            "--rate", help="Frame rate, Hz, of a points CSV (it carries none).")] = None,
        gate_mm: Annotated[float, typer.Option(
            "--gate-mm", help="A point this far from a marker's predicted place is not "
                              "that marker (frame to frame).")] = 30.0,
        distance_tol_mm: Annotated[float | None, typer.Option(
            "--distance-tol-mm", help="Identification: a pair of points matches a pair of "
                                      "a body's markers this closely (default: the "
                                      "configuration's [rigid], else 4).")] = None,
        max_error_mm: Annotated[float | None, typer.Option(
            "--max-error-mm", help="A marker this far from its fitted place is released "
                                   "(default: [rigid], else 6).")] = None,
        gross_mm: Annotated[float, typer.Option(
            "--gross-mm", help="Fit errors above this are counted as gross.")] = 20.0,
        motive_out: Annotated[Path | None, typer.Option(
            "--motive-out", help="Also write the markers and poses as a Motive CSV.")] = None,
        json_path: Annotated[Path | None, typer.Option(
            "--json", help="Write the figures as JSON.")] = None,
    ) -> None:
        """Find and pose rigid bodies in a file of 3D markers with the daemon's own rigid
        tracker; one CSV row per frame and body (see docs/track.md)."""
        from daemon.config import load_config
        from daemon.markers.offline_track import compare_poses, figures, track_cloud
        from daemon.markers.point_tracks import PointTrackConfig
        from daemon.markers.trajectory_io import PoseTable, write_poses_csv
        from daemon.rigid import RigidConfig

        if (bodies is None) == (not from_file):
            raise UserError("give the bodies to track: --bodies mocapd.toml or "
                            "--bodies-from-file (a Motive CSV's own definitions)")
        for name, value in (("--rate", rate), ("--gate-mm", gate_mm),
                            ("--gross-mm", gross_mm), ("--distance-tol-mm", distance_tol_mm),
                            ("--max-error-mm", max_error_mm)):
            if value is not None and not value > 0:
                raise UserError(f"{name} must be positive, got {value}")
        outputs = [p for p in (out, motive_out) if p is not None]
        if out.suffix.lower() not in (".csv", ".mcap"):
            raise UserError(f"{out}: poses are written as CSV or MCAP; give a .csv or .mcap "
                            "path")
        if motive_out is not None and motive_out.suffix.lower() != ".csv":
            raise UserError(f"{motive_out}: a Motive export is a CSV; give a .csv path")
        for p in outputs:
            if markers.exists() and p.resolve() == markers.resolve():
                raise UserError(f"{p} is the input file; write to another path")
        if motive_out is not None and motive_out.resolve() == out.resolve():
            raise UserError("--out and --motive-out name the same file")
        rigid_cfg = RigidConfig()
        defs = []
        if bodies is not None:
            cfg = load_config(bodies)
            if not cfg.bodies:
                raise UserError(f"{bodies} defines no [[rigid_body]]; nothing to track")
            defs, rigid_cfg = list(cfg.bodies), cfg.rigid
        if distance_tol_mm is not None:
            rigid_cfg = replace(rigid_cfg, distance_tol_m=distance_tol_mm / 1000.0)
        if max_error_mm is not None:
            rigid_cfg = replace(rigid_cfg, max_error_m=max_error_mm / 1000.0)
        cloud, motive, kind = load_markers(markers, rate)
        if from_file:
            defs = bodies_from_motive(motive, markers)
        progress = Progress("track", len(cloud))
        start = time.perf_counter()
        result = track_cloud(cloud, defs, replace(rigid_cfg, refine=False),
                             PointTrackConfig(gate_m=gate_mm / 1000.0),
                             progress=progress.update)
        elapsed = time.perf_counter() - start
        figs = figures(result, gross_mm)
        progress.finish(f"{figs['poses']} poses")
        figs["input"] = {"file": str(markers), "kind": kind}
        figs["frames_per_s"] = len(cloud) / elapsed if elapsed > 0 else None
        rows = []
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
        if out.suffix.lower() == ".mcap":
            from daemon.publish.mcap_poses import write_poses_mcap

            write_poses_mcap(out, table, cloud.xyz)
        else:
            write_poses_csv(out, table, f"mocapd track {markers.name} ({kind})")
        if motive_out is not None:
            _write_motive(motive_out, cloud, result, defs)
        for name, b in figs["bodies"].items():
            row = [name, b["id"], b["poses"], round(100 * b["valid_fraction"], 1),
                   b["fit_error_mm"]["rms"] if b["fit_error_mm"]["rms"] is not None
                   else float("nan"), b["gross_fit_errors"]]
            vs = figs.get("against_motive", {}).get(name)
            if vs is not None:
                row += [vs["position_mm"]["median"] or float("nan"),
                        vs["orientation_deg"]["median"] or float("nan"), vs["gross"]]
            rows.append(row)
        header = ["body", "id", "poses", "valid_%", "fit_err_mm_rms", "gross"]
        if "against_motive" in figs:
            header += ["vs_motive_mm_med", "vs_motive_deg_med", "vs_motive_gross"]
        print_table(rows, header)
        typer.echo(f"wrote {out}: {len(cloud)} frames, {len(defs)} bodies, "
                   f"{figs['poses']} poses ({100 * figs['valid_fraction']:.1f}% valid)")
        if json_path is not None:
            write_json(json_path, figs)


def _write_motive(path: Path, cloud, result, defs) -> None:
    """Our markers (unlabelled) and poses in Motive's modern layout."""
    from daemon.markers.motive_csv import MotiveBody, MotivePoses, MotiveTake, write_motive_csv

    bodies = [MotiveBody(b.name, b.id, b.markers - b.pivot) for b in defs]
    poses = {b.name: MotivePoses(result.valid[:, i], result.position[:, i],
                                 result.quaternion[:, i], result.error_m[:, i])
             for i, b in enumerate(defs)}
    dt = np.diff(cloud.t_s)
    rate = float(1.0 / np.median(dt)) if len(dt) and np.median(dt) > 0 else 0.0
    take = MotiveTake(cloud.frame, cloud.t_s, rate, [], np.zeros((len(cloud), 0, 3)),
                      cloud.xyz, bodies, poses)
    write_motive_csv(path, take, path.stem)
