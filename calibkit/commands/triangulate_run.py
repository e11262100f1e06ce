"""`calibkit triangulate`'s run: a capture's blobs paired into frames, matched across cameras
and triangulated, scored against the simulator's truth when it has one, written, its figures.

Apart from calibkit/commands/triangulate_cmd.py, whose handler checks the options and reads
the capture, so that a handler stays a page of options and a few checks.
"""

from __future__ import annotations

from pathlib import Path

import typer

from calibkit.clitools import Progress, print_table, write_json
from calibkit.core.errors import UserError


def run_triangulate(rig, obs, truth, src: Path | None, rig_path: Path | None, out: Path,
                    json_path: Path | None, epipolar_px: float | None,
                    max_reproj_px: float | None, min_cameras: int, two_camera: bool,
                    residual_px: float | None, estimate_residual: bool,
                    fixed_gates: bool) -> None:
    """`calibkit triangulate`'s run once the rig and the capture (and any truth) are read:
    the points, their CSV and JSON, the table of figures."""
    from calibkit.core.pairing import pair_frames
    from calibkit.synthetic.truthcheck import score_points, stands_for
    from calibkit.vision.correspondence import CorrespondenceConfig
    from calibkit.vision.reconstruct import reconstruct, write_points_csv

    if len(obs) == 0:
        raise UserError(f"{src}: holds no blobs")
    paired = pair_frames(obs)  # cameras counting their own frames: paired by time
    if paired.method == "time":
        obs, truth = paired.obs, None  # the truth's frame numbers are the recording's
        typer.echo(f"frames paired by capture time: {len(obs.frames())} instants",
                   err=True)
    given = {k: v for k, v in (("epipolar_px", epipolar_px),
                               ("max_reproj_px", max_reproj_px)) if v is not None}
    base = CorrespondenceConfig(min_cameras=min_cameras, two_camera=two_camera, **given)
    fixed = {"epipolar_px", "max_reproj_px"} if fixed_gates else set(given)
    n_frames = len(obs.frames())
    progress = Progress("triangulate", n_frames)
    try:
        run = reconstruct(rig, obs, base, residual_px, estimate_residual, fixed,
                          progress.update, say=lambda line: typer.echo(line, err=True))
    except UserError as exc:
        raise UserError(f"{rig_path or 'the rig'}: {exc}" if str(exc).startswith("quality.")
                        else str(exc)) from None
    points, cfg, residual, figures = run.points, run.config, run.residual, run.figures
    progress.finish(f"{len(points.frame)} points")
    error_mm = None
    if truth is not None:
        score = score_points(points.frame, points.xyz, truth, obs, rows=points.rows)
        figures["truth"] = score.as_dict()
        error_mm = stands_for(points.frame, points.xyz, truth, obs, points.rows)[1] * 1e3
    write_points_csv(out, points, rig.names, error_mm)
    if json_path is not None:
        write_json(json_path, figures)

    rows = [["frames", n_frames], ["3D points", int(len(points.frame))],
            ["points per frame", round(figures["points_per_frame"], 2)],
            ["residual px", residual.px if residual is not None else "none"],
            ["residual from", residual.source if residual is not None else "-"],
            ["epipolar gate px", cfg.epipolar_px],
            ["reprojection gate px", cfg.max_reproj_px],
            ["reprojection px (median)", figures["reproj_px_median"]],
            ["ray distance mm (median)", figures["ray_mm_median"]],
            ["frames per second", round(figures["frames_per_s"] or 0.0, 1)]]
    if truth is not None:
        t = figures["truth"]
        rows += [["3D error mm RMS, all matched points (vs truth)", t["error_mm_rms"]],
                 [f"gross errors (> {t['tolerance_mm']:g} mm) of "
                  f"{t['matched']} matched points", t["gross_errors"]],
                 ["recall of markers seen by >= 3 cameras", t["recall_3"]],
                 ["ghost points", t["ghosts"]],
                 ["ghost points (fraction)", t["ghost_fraction"]]]
    print_table(rows, ["what", "value"])
    typer.echo(f"wrote {out}")

