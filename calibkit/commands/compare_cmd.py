"""`calibkit compare`: how far one calibration is from another (or from the simulator's truth)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from calibkit.clitools import print_table, write_json


def register(app: typer.Typer) -> None:
    @app.command("compare")
    def compare(
        a: Annotated[Path, typer.Argument(help="The reference rig (e.g. NAME.truth.toml).")],
        b: Annotated[Path, typer.Argument(help="The rig to measure against it.")],
        align: Annotated[bool, typer.Option(
            "--align/--no-align",
            help="First align B to A by the similarity that best maps its camera centres.")]
        = True,
        scale: Annotated[bool, typer.Option(
            "--scale/--no-scale",
            help="Let the alignment scale B (--no-scale: rotation and translation only, so a "
                 "scale error shows in the grid RMS). The scale is reported either way.")]
        = True,
        json_path: Annotated[Path | None, typer.Option("--json", help="Write the figures.")]
        = None,
    ) -> None:
        """Per camera: position (mm), orientation (deg), focal length (%) and principal point
        (px) differences; the RMS 3D difference of a grid of points filling the volume; how
        much longer B measures lengths than A (the alignment's scale); and a verdict.

        Reads two rig files. To score a simulated calibration, compare the true rig a --sim
        run writes beside its result (NAME.truth.toml) with the result itself."""
        from calibkit.calibrate.compare import GROSS_MM, compare_rigs
        from calibkit.core.camera import Rig

        rig_a, rig_b = Rig.load(a), Rig.load(b)
        result = compare_rigs(rig_a, rig_b, align=align, scale=scale)
        rows = [[c["name"], c["position_mm"], c["rotation_deg"], c["focal_pct"],
                 c["principal_px"]] for c in result["cameras"]]
        print_table(rows, ["camera", "position_mm", "rotation_deg", "focal_pct",
                           "principal_px"])
        al = result["alignment"]
        how = (f"B aligned to A: rotation {al['rotation_deg']:.4f} deg, translation "
               f"({', '.join(f'{v:.4f}' for v in al['translation_m'])}) m, "
               + (f"scale {al['scale']:.6f}" if al["with_scale"] else "no scale (--no-scale)")
               if al["applied"] else "compared as they stand (--no-align)")
        typer.echo(f"\n{how}")
        typer.echo(f"grid RMS: {result['grid_rms_mm']:.4f} mm over {result['grid_points']} "
                   f"points that two cameras see ({result['grid_gross_points']} off by more "
                   f"than {GROSS_MM:g} mm)")
        typer.echo(scale_line(result["scale"]))
        v = result["verdict"]
        typer.echo(f"verdict: {v['grade']} ({v['reason']}; {v['limits']})")
        for side, names in (("A", result["only_in_a"]), ("B", result["only_in_b"])):
            if names:
                typer.echo(f"only in {side}: {', '.join(names)}")
        if json_path is not None:
            write_json(json_path, result)


def scale_line(sc: dict) -> str:
    """The scale as a user reads it: how much longer B measures, and what that is in mm."""
    if sc["error_ppm"] is None:
        return "scale: not measurable (fewer than two cameras in common)"
    where = ("removed by the alignment, not in the grid RMS" if sc["applied"] else
             "left in the grid RMS")
    return (f"scale: B measures lengths {sc['error_ppm']:+.0f} ppm ({sc['error_ppm'] / 1e4:+.4f} "
            f"%) against A: {sc['length_error_mm']:.2f} mm over the volume's "
            f"{sc['span_m']:.2f} m diagonal, {sc['grid_rms_mm']:.3f} mm RMS over the grid "
            f"({where})")

