"""`calibkit extrinsic --projector`'s run: the references and intrinsics (simulated or read),
the sessions planned and captured, the poses solved, written, reported and said.

Apart from calibkit/commands/extrinsic_cmd.py, whose handler checks the options (and does
--template and --show-refs, which stop early), so that a handler stays a page of options
and a few checks.
"""

from __future__ import annotations

import sys
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from calibkit.clitools import Progress, print_table, write_json
from calibkit.core.errors import UserError

if TYPE_CHECKING:
    from calibkit.calibrate import extrinsic_pipeline as pipeline
    from calibkit.calibrate.extrinsic_reference import References
    from calibkit.calibrate.extrinsic_solve import ExtrinsicResult
    from calibkit.core.camera import Rig


def run_extrinsic(*, out: Path, refs_path: Path | None, intrinsics: Path | None,
                  camera: list[str] | None, monitor: int, proj_px: tuple[int, int],
                  table: bool | None, step: float, shifts: int, radius: float, samples: int,
                  joint: bool, ref_sigma_mm: float, height_sigma_mm: float,
                  json_path: Path | None, report_path: Path | None, sim: bool,
                  sim_rig: Path | None, render: bool, cameras: int | None, volume: float,
                  table_height: float, size: str | None, noise_px: float,
                  ref_error_mm: float, seed: int) -> None:
    """`calibkit extrinsic --projector`'s run once its options are checked: the capture
    (simulated or live), the solve, the rig file, the report page, the figures."""
    from calibkit.calibrate import extrinsic_pipeline as pipeline
    from calibkit.calibrate.extrinsic_solve import SolveOptions
    from calibkit.clitools import parse_size
    from calibkit.synthetic.runs import truth_rig_path

    run = None
    if sim:
        from calibkit.synthetic import extrinsic_sim

        run = extrinsic_sim.setup(intrinsics, sim_rig, cameras,
                                  parse_size(size) if size else None, volume,
                                  table_height, ref_error_mm, proj_px, seed)
        refs, intr = run.refs, run.intrinsics
    else:
        refs, intr = _live_inputs(refs_path, intrinsics, table, camera)
    sessions = pipeline.plan_sessions(refs, table, step, shifts, radius)
    _print_sessions(sessions)
    if run is not None:
        captured = extrinsic_sim.capture(run, sessions, samples, render, noise_px,
                                         Progress)
    else:
        captured = _capture_live(intr, list(camera), monitor, sessions, samples)
    opts = SolveOptions(joint=joint, reference_sigma_m=ref_sigma_mm / 1000.0,
                        height_sigma_m=height_sigma_mm / 1000.0)
    names = run.truth.names if run is not None else intr.names
    result = pipeline.solve(intr, names, captured, sessions, opts)
    _print(result)
    pipeline.write_outputs(result, intr, intrinsics, out)
    from calibkit.calibrate.html_report import extrinsic_page, write_page

    page = report_path or out.with_name(out.stem + ".report.html")
    write_page(page, extrinsic_page(result, out.name))
    if run is not None:
        t = extrinsic_sim.score(run, result, out)
        typer.echo(f"against the simulator's truth: position error up to "
                   f"{t['position_error_max_mm']:.1f} mm, orientation up to "
                   f"{t['rotation_error_max_deg']:.3f} deg")
    for w in result.warnings:
        typer.echo(f"warning: {w}", err=True)
    if json_path is not None:
        write_json(json_path, result.report)
    typer.echo(f"wrote {out}" + (f" (true rig in {truth_rig_path(out)})" if sim else "")
               + f" and the report {page}")
    if result.report["not_calibrated"]:
        print(f"not calibrated: {', '.join(result.report['not_calibrated'])}",
              file=sys.stderr)


def _live_inputs(refs_path: Path | None, intrinsics: Path | None, table: bool | None,
                 camera: list[str] | None) -> tuple[References, Rig]:
    from calibkit.calibrate import extrinsic_pipeline as pipeline
    from calibkit.calibrate.extrinsic_reference import load_references
    from calibkit.core.camera import Rig

    if refs_path is None:
        raise UserError("--refs REFS.toml is required (make one with --template "
                        "and a tape; see docs/extrinsic.md)")
    refs = load_references(refs_path)
    if intrinsics is None:
        raise UserError("--intrinsics RIG.toml is required (from calibkit intrinsic)")
    intr = Rig.load(intrinsics)
    pipeline.table_session(refs, table)
    if not camera:
        raise UserError("live capture needs --camera once per camera (or --sim)")
    return refs, intr


def _capture_live(intr: Rig, specs: list[str], monitor: int, sessions: pipeline.Sessions,
                  samples: int) -> pipeline.Captured:
    """The projector on monitor `monitor`, the cameras from their specs (calibkit.cameras:
    device numbers, files, basler:SERIAL, genicam:SERIAL)."""
    from calibkit.calibrate import extrinsic_pipeline as pipeline
    from calibkit.calibrate.extrinsic_capture import LiveProjectorRig
    from calibkit.cameras import open_camera
    from projector.display import WindowDisplay
    from projector.screens import require_display

    if len(specs) != len(intr):
        raise UserError(f"give one --camera per camera of the rig ({len(intr)}: "
                        f"{', '.join(intr.names)}), got {len(specs)}")
    require_display()
    with ExitStack() as opened:  # closed in reverse: the window first, then the cameras
        sources = [opened.enter_context(open_camera(s, name=n))
                   for s, n in zip(specs, intr.names, strict=True)]
        window = WindowDisplay(monitor)
        opened.callback(window.close)
        return pipeline.capture_sessions(
            LiveProjectorRig(window, sources, intr.names), sessions, len(intr), samples,
            Progress, before_table=lambda: input("put the table in place under the "
                                                 "projector, then press Enter "))


def _print_sessions(sessions: pipeline.Sessions) -> None:
    from calibkit.calibrate import extrinsic_pipeline as pipeline

    lines, warnings = pipeline.map_notes(sessions)
    for line in lines:
        typer.echo(line)
    for w in warnings:
        typer.echo(f"warning: {w}", err=True)


def _print(result: ExtrinsicResult) -> None:
    rows = [[c["name"], "yes" if c["calibrated"] else "NO", c["floor_dots"], c["table_dots"],
             c["reprojection_rms_px"], c["mean_ray_distance_mm"],
             c["mean_ray_distance_table_mm"]] for c in result.report["cameras"]]
    print_table(rows, ["camera", "calibrated", "floor dots", "table dots", "rms_px",
                       "ray_mm", "ray_table_mm"])
    r = result.report

    def mm(v: float) -> str:
        import numpy as np

        return "-" if not np.isfinite(v) else f"{v:.2f} mm"

    typer.echo(f"\nall cameras: reprojection RMS {r['reprojection_rms_px']:.3f} px, mean ray "
               f"distance {mm(r['mean_ray_distance_mm'])} over {r['dots']} dots, "
               f"{mm(r['mean_ray_distance_table_mm'])} over the {r['table_dot_points']} "
               "table dots (dots seen by two or more cameras)")
    c = r["capture"]
    typer.echo(f"capture: {c['frames']} camera frames, {c['seconds_at_30fps']:.1f} s at 30 fps"
               + (" (estimated from the latencies)" if c["simulated_frames"] else ""))
