"""`mocapd track`: rigid-body poses from a file of 3D markers (points CSV, C3D, Motive CSV).

The handler checks the options; the run is daemon/commands/track_run.py (the work itself in
daemon.analysis.track_file), imported by the handler so that other commands start without it."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from calibkit.core.errors import UserError


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
        from daemon.commands.track_run import run_track

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
        run_track(out, markers, bodies, from_file, rate, gate_mm, distance_tol_mm, max_error_mm,
                  gross_mm, motive_out, json_path, refine_bodies, up_axis, strict)


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
