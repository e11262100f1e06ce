"""`calibkit convert`: recordings to plain CSV and back, and other tools' point files in, so data
moves to and from other tools."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from calibkit.core.errors import UserError

if TYPE_CHECKING:
    from calibkit.core.camera import Rig


def _read_xypts(src: Path, rig_obj: Rig | None, profile: Path | None, y_origin: str,
                fps: float | None, rig_out: Path | None):
    """A DLTdv/easyWand xypts file with its cameras from the profile (or the rig)."""
    from calibkit.core import easywand

    cams = easywand.read_easywand_profile(profile, y_origin) if profile is not None else rig_obj
    obs = easywand.read_xypts(src, cams, y_origin, fps)
    if rig_out is not None:
        if cams is None:
            raise UserError("--rig-out writes the profile's intrinsics: give --profile")
        cams.save(rig_out)
    return obs


def register(app: typer.Typer) -> None:
    @app.command("convert")
    def convert(
        src: Annotated[Path, typer.Argument(
            help="A recording (.mcrec), a plain CSV, or a DLTdv/easyWand xypts.csv.")],
        out: Annotated[Path, typer.Option(
            "--out", help="What to write; the suffix decides: .csv plain CSV, else a recording.")],
        rig: Annotated[Path | None, typer.Option(
            "--rig", help="Check camera names against this rig and take image sizes from it "
                          "(a CSV carries no sizes).")] = None,
        profile: Annotated[Path | None, typer.Option(
            "--profile", help="xypts input: the easyWand camera profile (image sizes, and the "
                              "camera count of a file without a header).")] = None,
        y_origin: Annotated[str, typer.Option(
            "--y-origin", help="xypts input: where its y counts from: bottom (DLTdv 1-7, "
                               "Argus) or top (DLTdv 8).")] = "bottom",
        fps: Annotated[float | None, typer.Option(
            "--fps", help="xypts input: the capture rate (the file has no times).")] = None,
        rig_out: Annotated[Path | None, typer.Option(
            "--rig-out", help="xypts input: also write the profile's intrinsics as a rig "
                              "file, converted the same way (for calibkit wand --intrinsics)."
        )] = None,
    ) -> None:
        """Convert observations between our recording format and the plain CSV
        (frame,camera,t_ns,u,v,area,peak), or read a DLTdv/easyWand xypts file into either
        (docs/easywand.md); ground truth travels along.

        Reads a capture file (a recording, a plain CSV or an xypts file); `calibkit sim
        static`, `sim wand` or `sim rigid` write simulated ones."""
        from calibkit.core import easywand
        from calibkit.core.camera import Rig
        from calibkit.core.recording import load_observations, save_observations, truth_path_for

        if out.resolve() == src.resolve():
            raise UserError(f"--out {out} is the input file; give another path")
        if profile is not None and rig is not None:
            raise UserError("give --profile or --rig, not both: each names the cameras")
        for given, name in ((rig_out, "--rig-out"), (profile, "--profile")):
            if given is not None and given.resolve() in (src.resolve(), out.resolve()):
                raise UserError(f"{name} {given} is another file of this command; give "
                                "another path")
        rig_obj = Rig.load(rig) if rig is not None else None
        if src.is_file() and easywand.looks_like_xypts(src):
            obs, truth = _read_xypts(src, rig_obj, profile, y_origin, fps, rig_out), None
        else:
            extra = [n for n, v in (("--profile", profile), ("--fps", fps),
                                    ("--rig-out", rig_out)) if v is not None]
            if y_origin != "bottom":
                extra.append("--y-origin")
            if extra:
                raise UserError(f"{', '.join(extra)} only apply to a DLTdv/easyWand xypts "
                                f"file; {src} is not one")
            obs, truth = load_observations(src, rig_obj)
        if rig_obj is not None:
            obs.camera_sizes = tuple(rig_obj[n].size for n in obs.camera_names)
        save_observations(out, obs, truth)
        extra = ""
        if truth is not None:
            extra = (f", truth in {truth_path_for(out)}" if out.suffix.lower() == ".csv"
                     else ", with its truth")
        if rig_out is not None:
            extra += f"; the profile's intrinsics in {rig_out}"
        typer.echo(f"wrote {out}: {len(obs.frames())} frames, {len(obs)} blobs from "
                   f"{len(obs.camera_names)} cameras{extra}")
