"""`calibkit convert`: recordings to plain CSV and back, so data moves to and from other tools."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.recording import load_observations, save_observations, truth_path_for


def register(app: typer.Typer) -> None:
    @app.command("convert")
    def convert(
        src: Annotated[Path, typer.Argument(help="A recording (.mcrec) or a plain CSV.")],
        out: Annotated[Path, typer.Option(
            "--out", help="What to write; the suffix decides: .csv plain CSV, else a recording.")],
        rig: Annotated[Path | None, typer.Option(
            "--rig", help="Check camera names against this rig and take image sizes from it "
                          "(a CSV carries no sizes).")] = None,
    ) -> None:
        """Convert observations between our recording format and the plain CSV
        (frame,camera,t_ns,u,v,area,peak); ground truth travels along."""
        if out.resolve() == src.resolve():
            raise UserError(f"--out {out} is the input file; give another path")
        rig_obj = Rig.load(rig) if rig is not None else None
        obs, truth = load_observations(src, rig_obj)
        if rig_obj is not None:
            obs.camera_sizes = tuple(rig_obj[n].size for n in obs.camera_names)
        save_observations(out, obs, truth)
        extra = ""
        if truth is not None:
            extra = (f", truth in {truth_path_for(out)}" if out.suffix.lower() == ".csv"
                     else ", with its truth")
        typer.echo(f"wrote {out}: {len(obs.frames())} frames, {len(obs)} blobs from "
                   f"{len(obs.camera_names)} cameras{extra}")
