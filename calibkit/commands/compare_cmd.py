"""`calibkit compare`: how far one calibration is from another (or from the simulator's truth)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from calibkit.calibrate.compare import GROSS_MM, compare_rigs
from calibkit.clitools import print_table, write_json
from calibkit.core.camera import Rig


def register(app: typer.Typer) -> None:
    @app.command("compare")
    def compare(
        a: Annotated[Path, typer.Argument(help="The reference rig (e.g. NAME.truth.toml).")],
        b: Annotated[Path, typer.Argument(help="The rig to measure against it.")],
        align: Annotated[bool, typer.Option(
            "--align/--no-align",
            help="First align B to A by the similarity that best maps its camera centres.")]
        = True,
        json_path: Annotated[Path | None, typer.Option("--json", help="Write the figures.")]
        = None,
    ) -> None:
        """Per camera: position (mm), orientation (deg), focal length (%) and principal point
        (px) differences; and the RMS 3D difference of a grid of points filling the volume."""
        rig_a, rig_b = Rig.load(a), Rig.load(b)
        result = compare_rigs(rig_a, rig_b, align=align)
        rows = [[c["name"], c["position_mm"], c["rotation_deg"], c["focal_pct"],
                 c["principal_px"]] for c in result["cameras"]]
        print_table(rows, ["camera", "position_mm", "rotation_deg", "focal_pct",
                           "principal_px"])
        al = result["alignment"]
        how = (f"B aligned to A: rotation {al['rotation_deg']:.4f} deg, translation "
               f"({', '.join(f'{v:.4f}' for v in al['translation_m'])}) m, scale "
               f"{al['scale']:.6f}" if al["applied"] else "compared as they stand (--no-align)")
        typer.echo(f"\n{how}")
        typer.echo(f"grid RMS: {result['grid_rms_mm']:.4f} mm over {result['grid_points']} "
                   f"points that two cameras see ({result['grid_gross_points']} off by more "
                   f"than {GROSS_MM:g} mm)")
        for side, names in (("A", result["only_in_a"]), ("B", result["only_in_b"])):
            if names:
                typer.echo(f"only in {side}: {', '.join(names)}")
        if json_path is not None:
            write_json(json_path, result)
