"""`mocapd track`: rigid-body poses from a file of 3D markers (points CSV, C3D, Motive CSV).

The work is in daemon.analysis.track_file, imported by the handler so that other commands
start without it."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer

from calibkit.clitools import Progress, print_table, write_json
from calibkit.core.errors import UserError
from daemon.commands.points_input import (
    bad_rows_json,
    read_points_for_command,
    spool_points_for_command,
)


def register(app: typer.Typer) -> None:
    @app.command("track")
    def track_cmd(
        out: Annotated[Path, typer.Option(
            "--out", help="Poses to write: a CSV, or an MCAP (.mcap: Foxglove's schemas, "
                          "the markers too).")],
        markers: Annotated[Path | None, typer.Argument(
            help="3D markers: a points CSV (calibkit triangulate --out), a C3D or a Motive "
                 "CSV export.")] = None,
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
        refine_bodies: Annotated[str, typer.Option(
            "--refine-bodies", help="Fit each definition to the take's markers first: auto "
                                    "(when a marker sits over half --distance-tol-mm off), "
                                    "on, off.")] = "auto",
        up_axis: Annotated[str | None, typer.Option(
            "--up-axis", help="The input's up axis, y or z (default: Motive's y for a "
                              "Motive CSV, z for C3D and points CSV); outputs are "
                              "z-up.")] = None,
        strict: Annotated[bool, typer.Option(
            "--strict", help="Refuse a points CSV with bad rows (text, NaN, inf, wrong "
                             "column count) instead of skipping and counting them.")] = False,
        sim: Annotated[bool, typer.Option(
            "--sim", help="Instead of MARKERS: a simulated take of four rigid bodies (one "
                          "definition 4 mm off its markers, 2 % of marker-frames hidden, "
                          "two strays a frame) written beside --out as NAME.sim-take.csv, a "
                          "Motive 1.0 export whose poses are the simulator's truth; its own "
                          "bodies are tracked and the vs_motive figures are against the "
                          "truth.")] = False,
        frames: Annotated[int, typer.Option(help="--sim: frames (120 a second).")] = 752,
        seed: Annotated[int, typer.Option(help="--sim: random seed.")] = 21,
    ) -> None:
        """Find and pose rigid bodies in a file of 3D markers with the daemon's own rigid
        tracker; one CSV row per frame and body (see docs/track.md)."""
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

        if sim:
            markers, from_file = _sim_take(markers, bodies, out, frames, seed), True
        elif markers is None:
            raise UserError("give MARKERS (a points CSV, a C3D or a Motive CSV), or --sim for "
                            "a simulated take")
        if (bodies is None) == (not from_file):
            raise UserError("give the bodies to track: --bodies mocapd.toml or "
                            "--bodies-from-file (a Motive CSV's own definitions)")
        for name, value in (("--rate", rate), ("--gate-mm", gate_mm),
                            ("--gross-mm", gross_mm), ("--distance-tol-mm", distance_tol_mm),
                            ("--max-error-mm", max_error_mm)):
            if value is not None and not value > 0:
                raise UserError(f"{name} must be positive, got {value}")
        _check_outputs(markers, out, motive_out)
        if refine_bodies not in ("auto", "on", "off"):
            raise UserError(f"--refine-bodies is auto, on or off, got {refine_bodies!r}")
        if up_axis is not None and up_axis.lower() not in ("y", "z"):
            raise UserError(f"--up-axis is y or z, got {up_axis!r}")
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


def _check_outputs(markers: Path, out: Path, motive_out: Path | None) -> None:
    """Refuse outputs of the wrong kind, or that would overwrite the input or each other."""
    if out.suffix.lower() not in (".csv", ".mcap"):
        raise UserError(f"{out}: poses are written as CSV or MCAP; give a .csv or .mcap path")
    if motive_out is not None and motive_out.suffix.lower() != ".csv":
        raise UserError(f"{motive_out}: a Motive export is a CSV; give a .csv path")
    for p in (out, motive_out):
        if p is not None and markers.exists() and p.resolve() == markers.resolve():
            raise UserError(f"{p} is the input file; write to another path")
    if motive_out is not None and motive_out.resolve() == out.resolve():
        raise UserError("--out and --motive-out name the same file")


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


def _sim_take(markers: Path | None, bodies: Path | None, out: Path, frames: int,
              seed: int) -> Path:
    """--sim: the take to track, written beside --out (daemon.synthetic.motive_export): a
    Motive 1.0 export whose bodies' poses are the simulator's truth, so what the tracker
    makes of its markers is scored by the comparison with Motive that any such file gets."""
    from daemon.synthetic.motive_export import write_motive_1_0

    if markers is not None:
        raise UserError(f"give MARKERS or --sim, not both (got {markers} and --sim)")
    if bodies is not None:
        raise UserError("--sim tracks the simulated take's own bodies; --bodies is for a "
                        "file of markers")
    if frames < 10:
        raise UserError(f"--frames must be at least 10, got {frames}")
    path = out.with_name(out.stem + ".sim-take.csv")
    write_motive_1_0(path, n_frames=frames, seed=seed)
    typer.echo(f"simulated take: {path} ({frames} frames, 4 bodies; its Motive poses are "
               "the simulator's truth, so the vs_motive figures score the tracking)", err=True)
    return path
