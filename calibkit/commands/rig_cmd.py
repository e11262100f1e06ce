"""`calibkit rig`: show a rig file, and move rigs to and from OpenCV's FileStorage YAML."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from calibkit.clitools import print_table, write_json
from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.rigfile import export_opencv_yaml

rig_app = typer.Typer(help="Show rig files; export to and import from OpenCV YAML.",
                      no_args_is_help=True)


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
    """Print each camera's size, intrinsics, distortion and centre."""
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


@rig_app.command("export")
def export(rig_path: Annotated[Path, typer.Argument(help="The rig.toml to export.")],
           out: Annotated[Path, typer.Option("--out", help="OpenCV YAML file to write.")]
           ) -> None:
    """Write the rig as OpenCV FileStorage YAML (cameras: name, size, K, dist, R, t)."""
    _suffix(out, (".yaml", ".yml"), "--out")
    _distinct(rig_path, out)
    rig = Rig.load(rig_path)
    export_opencv_yaml(rig, out)
    typer.echo(f"wrote {out}: {len(rig)} cameras (OpenCV FileStorage YAML)")


@rig_app.command("import")
def import_(yaml_path: Annotated[Path, typer.Argument(help="OpenCV YAML rig to read.")],
            out: Annotated[Path, typer.Option("--out", help="rig.toml to write.")]) -> None:
    """Read an OpenCV FileStorage YAML rig and write it as rig.toml."""
    _suffix(yaml_path, (".yaml", ".yml"), "the input")
    _suffix(out, (".toml",), "--out")
    _distinct(yaml_path, out)
    rig = Rig.load(yaml_path)
    rig.save(out)
    typer.echo(f"wrote {out}: {len(rig)} cameras")


def register(app: typer.Typer) -> None:
    app.add_typer(rig_app, name="rig")
