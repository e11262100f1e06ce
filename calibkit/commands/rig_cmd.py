"""`calibkit rig`: show a rig file, and move rigs to and from other tools' calibration files."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from calibkit.clitools import HELP_MARKUP, print_table, write_json
from calibkit.core.errors import UserError

rig_app = typer.Typer(help="Show rig files; import and export other tools' calibrations.",
                      no_args_is_help=True, rich_markup_mode=HELP_MARKUP)


def _distinct(src: Path, out: Path) -> None:
    if out.resolve() == src.resolve():
        raise UserError(f"--out {out} is the input file; give another path (inputs are never "
                        "overwritten)")


def _suffix(path: Path, allowed: tuple[str, ...], option: str) -> None:
    if path.suffix.lower() not in allowed:
        raise UserError(f"{option} {path}: expected a {' or '.join(allowed)} file")


@rig_app.command("show")
def show(rig_path: Annotated[Path, typer.Argument(help="rig.toml or OpenCV YAML.")],
         json_path: Annotated[Path | None, typer.Option("--json", help="Write as JSON.")]
         = None) -> None:
    """Print each camera's size, intrinsics, distortion and centre.

    Reads a rig file; `calibkit sim rig` writes a simulated one."""
    import numpy as np

    from calibkit.core.camera import Rig

    rig = Rig.load(rig_path)
    rows = []
    for cam in rig:
        c = cam.centre
        rows.append([cam.name, f"{cam.width}x{cam.height}", cam.fx, cam.fy, cam.cx, cam.cy,
                     " ".join(f"{v:.4g}" for v in cam.dist),
                     f"({c[0]:.3f}, {c[1]:.3f}, {c[2]:.3f})"])
    print_table(rows, ["camera", "size", "fx", "fy", "cx", "cy", "dist k1 k2 p1 p2 k3",
                       "centre_m"])
    for key, value in rig.quality.items():
        typer.echo(f"{key}: {value}")
    if json_path is not None:
        write_json(json_path, {"cameras": [
            {"name": c.name, "size": list(c.size), "K": c.K, "dist": c.dist, "R": c.R,
             "t": c.t, "centre": c.centre} for c in rig], "quality": rig.quality,
            "meta": {k: v for k, v in rig.meta.items() if not isinstance(v, np.ndarray)}})


# anipose's own default unit (calibkit.core.rigformats.anipose.DEFAULT_UNIT, which
# tests/test_cli_startup.py checks), spelled here so that `calibkit rig --help` loads no numpy.
DEFAULT_UNIT = "mm"
FORMAT_HELP = ("caliscope (camera_array.toml), pose2sim (Calib.toml), anipose "
               "(calibration.toml), qca (Qualisys QTM), opencv (FileStorage YAML)")
UNIT_OPTION = typer.Option("--unit", help="Length unit of anipose files' translations, which "
                           "do not say it: the unit the board was measured in (mm, cm or m).")


@rig_app.command("export")
def export(rig_path: Annotated[Path, typer.Argument(help="The rig.toml to export.")],
           out: Annotated[Path, typer.Option("--out", help="File to write.")],
           fmt: Annotated[str | None, typer.Option(
               "--format", help="opencv, caliscope, pose2sim or anipose; default opencv for "
               "a .yaml/.yml --out.")] = None,
           unit: Annotated[str, UNIT_OPTION] = DEFAULT_UNIT) -> None:
    """Write the rig for another tool: OpenCV FileStorage YAML, caliscope's
    camera_array.toml, Pose2Sim's or anipose's calibration TOML (docs/formats.md).

    Reads a rig file; `calibkit sim rig` writes a simulated one."""
    from calibkit.core.camera import Rig
    from calibkit.core.rigformats import WRITABLE, write_rig_file

    if fmt is None:
        if out.suffix.lower() not in (".yaml", ".yml"):
            raise UserError(f"--out {out}: expected a .yaml or .yml file for OpenCV YAML, or "
                            "give --format caliscope, pose2sim or anipose for their TOML")
        fmt = "opencv"
    if fmt not in WRITABLE:
        raise UserError(f"--format {fmt!r}: export writes one of {', '.join(WRITABLE)} (QTM "
                        "files come from QTM)")
    _suffix(out, (".yaml", ".yml") if fmt == "opencv" else (".toml",), "--out")
    _distinct(rig_path, out)
    rig = Rig.load(rig_path)
    write_rig_file(rig, out, fmt, unit)
    extra = f", translations in {unit}" if fmt == "anipose" else ""
    typer.echo(f"wrote {out}: {len(rig)} cameras ({fmt}{extra})")


@rig_app.command("import")
def import_(in_path: Annotated[Path, typer.Argument(help="Calibration file to read: "
                                                    + FORMAT_HELP + ".")],
            out: Annotated[Path, typer.Option("--out", help="rig.toml to write.")],
            fmt: Annotated[str, typer.Option(
                "--format", help="auto (by content), opencv, caliscope, pose2sim, anipose "
                "or qca.")] = "auto",
            unit: Annotated[str, UNIT_OPTION] = DEFAULT_UNIT) -> None:
    """Read another tool's calibration and write it as rig.toml (conventions converted:
    poses world-to-camera, metres, OpenCV distortion).

    Reads another tool's calibration file (a simulated rig exported with `calibkit rig
    export` makes one)."""
    from calibkit.core.rigformats import READABLE, read_rig_file

    if fmt != "auto" and fmt not in READABLE:
        raise UserError(f"--format {fmt!r}: use auto or one of {', '.join(READABLE)}")
    _suffix(out, (".toml",), "--out")
    _distinct(in_path, out)
    rig, found = read_rig_file(in_path, fmt, unit)
    rig.save(out)
    extra = f", translations read as {unit}" if found == "anipose" else ""
    typer.echo(f"wrote {out}: {len(rig)} cameras from {found}{extra}")
    for note in rig.meta.get("skipped_cameras", []):
        typer.echo(f"skipped {note}")


def register(app: typer.Typer) -> None:
    app.add_typer(rig_app, name="rig")
