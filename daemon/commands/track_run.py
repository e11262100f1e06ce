"""`mocapd track`'s run: the bodies' definitions and settings, the markers read (a points
CSV in windows when it can be), tracked, written, and its figures.

Apart from daemon/commands/track_cmd.py, whose handler reads the options and checks them,
so that a handler stays a page of options and a few checks.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import typer

from calibkit.clitools import Progress, print_table, write_json
from calibkit.core.errors import UserError
from daemon.commands.points_input import (
    bad_rows_json,
    read_points_for_command,
    spool_points_for_command,
)


def run_track(out: Path, markers: Path, bodies: Path | None, from_file: bool,
              rate: float | None, gate_mm: float, distance_tol_mm: float | None,
              max_error_mm: float | None, gross_mm: float, motive_out: Path | None,
              json_path: Path | None, refine_bodies: str, up_axis: str | None,
              strict: bool) -> None:
    """`mocapd track`'s run once its options are checked: definitions loaded, the markers
    read, tracked (in windows for an ordered points CSV), written, the figures said."""
    from daemon.analysis.track_file import (
        axes_note,
        bodies_from_motive,
        load_markers,
        track_file,
        write_motive,
    )
    from daemon.config.mocapd import load_config
    from daemon.formats.trajectory_io import write_poses_csv
    from daemon.tracking.rigid import RigidConfig

    rigid_cfg, defs = RigidConfig(), []
    if bodies is not None:
        cfg = load_config(bodies)
        if not cfg.bodies:
            raise UserError(f"{bodies} defines no [[rigid_body]]; nothing to track")
        defs, rigid_cfg = list(cfg.bodies), cfg.rigid
    if distance_tol_mm is not None:
        rigid_cfg = replace(rigid_cfg, distance_tol_m=distance_tol_mm / 1000.0)
    if max_error_mm is not None:
        rigid_cfg = replace(rigid_cfg, max_error_m=max_error_mm / 1000.0)
    points, bad = None, None
    rate = _points_rate(markers, rate)  # None: not a points CSV
    if rate is not None and out.suffix.lower() == ".csv" and motive_out is None:
        # a points CSV to a poses CSV: in windows, in memory bounded whatever its size
        if from_file:
            bodies_from_motive(None, markers)  # the one-line refusal
        spool, bad = spool_points_for_command(markers, _folder(out), strict)
        with spool:
            if spool.ordered:
                _track_in_windows(spool, markers, out, rate, defs, rigid_cfg, gate_mm,
                                  gross_mm, refine_bodies, up_axis, bad, json_path)
                return
            typer.echo(f"note: {markers}: its frame numbers go back somewhere, so it "
                       "is tracked whole, in memory (sort it by frame for windows)",
                       err=True)
            points = spool.points()
    elif rate is not None:
        points, bad = read_points_for_command(markers, strict)
    cloud, motive, kind, up = load_markers(markers, rate,
                                           up_axis.lower() if up_axis else None, points)
    del points  # packed into the cloud: not held through the tracking
    if from_file:
        defs = bodies_from_motive(motive, markers)
    progress = Progress("track", len(cloud))
    table, figs, used = track_file(cloud, motive, defs, rigid_cfg, gate_mm, gross_mm,
                                   progress.update, refine_bodies)
    progress.finish(f"{figs['poses']} poses")
    figs["input"] = {"file": str(markers), "kind": kind, "up_axis": up}
    if bad is not None:
        figs["input"]["bad_rows"] = bad_rows_json(bad)
    if out.suffix.lower() == ".mcap":
        from daemon.publish.mcap_poses import write_poses_mcap

        write_poses_mcap(out, table, cloud.xyz, metadata={
            "source": f"mocapd track {markers.name} ({kind})", "source_up_axis": up,
            "note": axes_note(up)})
    else:
        write_poses_csv(out, table, f"mocapd track {markers.name} ({kind}); "
                        f"{axes_note(up)}")
    if motive_out is not None:
        write_motive(motive_out, cloud, table, used, up)
    _report(figs, out, len(cloud), len(defs), json_path)


def _report(figs: dict, out: Path, n_frames: int, n_bodies: int, json_path: Path | None):
    """The table, the notes and warnings on stderr, the last line, the JSON."""
    _print_figures(figs)
    for name, b in figs["bodies"].items():
        if b["refine"]["applied"]:
            moved = ", ".join(f"{v:.1f}" for v in b["refine"]["marker_shift_mm"])
            typer.echo(f"note: body {name!r}: definition fitted to the take's markers "
                       f"(markers moved {moved} mm; --refine-bodies off keeps it)", err=True)
    for line in figs["hints"]:
        typer.echo(f"warning: {line}", err=True)
    typer.echo(f"wrote {out}: {n_frames} frames, {n_bodies} bodies, "
               f"{figs['poses']} poses ({100 * figs['valid_fraction']:.1f}% valid)")
    if json_path is not None:
        write_json(json_path, figs)


def _track_in_windows(spool, markers: Path, out: Path, rate: float, defs, rigid_cfg,
                      gate_mm: float, gross_mm: float, refine: str, up_axis: str | None,
                      bad, json_path: Path | None) -> None:
    """A spooled points CSV tracked and written a window of frames at a time."""
    from daemon.analysis.track_file import axes_note
    from daemon.analysis.track_stream import track_spool
    from daemon.formats.motive_take import Y_UP_TO_Z_UP

    up = (up_axis or "z").lower()
    kind = f"points CSV, {rate:g} Hz"
    progress = Progress("track", len(spool.frames))
    figs, _ = track_spool(spool, rate, defs, rigid_cfg, gate_mm, gross_mm, out,
                          f"mocapd track {markers.name} ({kind}); {axes_note(up)}",
                          progress.update, refine, Y_UP_TO_Z_UP if up == "y" else None)
    progress.finish(f"{figs['poses']} poses")
    figs["input"] = {"file": str(markers), "kind": kind, "up_axis": up,
                     "bad_rows": bad_rows_json(bad)}
    _report(figs, out, len(spool.frames), len(defs), json_path)


def _folder(out: Path) -> Path:
    """Where the spool goes: the output's folder (made, as the output's writing would)."""
    folder = out.resolve().parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot write in {folder}: {exc.strerror}") from None
    return folder


def _points_rate(markers: Path, rate: float | None) -> float | None:
    """The frame rate of a points CSV (--rate, else its '# rate_hz=' line), asked for
    before the long read; None for other files (load_markers reads those)."""
    from daemon.formats.motive_csv import sniff
    from daemon.formats.points_csv import points_header

    if markers.suffix.lower() != ".csv" or not markers.is_file() or sniff(markers):
        return None
    rate = rate or points_header(markers).rate_hz
    if rate is None:
        raise UserError(f"{markers} has no frame rate: give --rate HZ (the cameras' rate)")
    return rate


def _print_figures(figs: dict) -> None:
    rows = []
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

