"""`calibkit extrinsic --projector`: every camera's pose from projected floor and table dots."""

from __future__ import annotations

import sys
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from calibkit.clitools import Progress, parse_size, print_table, write_json
from calibkit.core.errors import UserError

if TYPE_CHECKING:
    import numpy as np

    from calibkit.calibrate import extrinsic_pipeline as pipeline
    from calibkit.calibrate.extrinsic_reference import References
    from calibkit.calibrate.extrinsic_solve import ExtrinsicResult
    from calibkit.core.camera import Rig


def _check_options(out: Path | None, samples: int, shifts: int, step: float, radius: float,
                   ref_sigma_mm: float, height_sigma_mm: float) -> None:
    if out is None:
        raise UserError("--out RIG.toml is required")
    if samples < 1 or shifts < 1 or step <= 0 or radius <= 0:
        raise UserError("--samples and --shifts must be >= 1, --step and --radius > 0")
    if ref_sigma_mm <= 0 or height_sigma_mm <= 0:
        raise UserError("--ref-sigma-mm and --height-sigma-mm must be positive")


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


def _show_references(pts: np.ndarray, monitor: int, radius: float) -> None:
    """Light the reference dots so the user can mark and measure where they land."""
    from projector.display import WindowDisplay
    from projector.dots import Dots
    from projector.screens import require_display

    require_display()
    window = WindowDisplay(monitor)
    try:
        window.show(Dots.make(pts, radius))
        input(f"{len(pts)} reference dots shown: mark and measure them, then press Enter ")
    finally:
        window.close()


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


def register(app: typer.Typer) -> None:
    @app.command("extrinsic")
    def extrinsic(
        projector: Annotated[bool, typer.Option(
            "--projector", help="Calibrate from dots a ceiling projector casts on the floor "
                                "and a table (the method there is).")] = False,
        out: Annotated[Path | None, typer.Option(
            "--out", help="The rig file to write (cameras with their poses).")] = None,
        refs_path: Annotated[Path | None, typer.Option(
            "--refs", help="Reference points measured with a tape (TOML, see "
                           "docs/extrinsic.md).")] = None,
        template: Annotated[Path | None, typer.Option(
            "--template", help="Write a reference-points file to fill in (the projector "
                               "pixels of the reference dots) and stop.")] = None,
        show_refs: Annotated[bool, typer.Option(
            "--show-refs", help="Light the reference dots of --refs (or of the template "
                                "layout) on --monitor until Enter, to mark them, and stop.")]
        = False,
        intrinsics: Annotated[Path | None, typer.Option(
            "--intrinsics", help="Rig file with every camera's intrinsics (poses are "
                                 "ignored).")] = None,
        camera: Annotated[list[str] | None, typer.Option(
            "--camera", help="Live: a camera (device number, video, image folder, "
                             "basler:SERIAL, genicam:SERIAL), once per camera of "
                             "--intrinsics, in its order.")] = None,
        monitor: Annotated[int, typer.Option(
            "--monitor", help="Live: the projector's display index.")] = 1,
        projector_size: Annotated[str, typer.Option(
            "--projector-size", help="The projector's resolution (for --template).")]
        = "1280x800",
        table: Annotated[bool | None, typer.Option(
            "--table/--no-table", help="Run the table session (default: when the "
                                       "references have a table).")] = None,
        step: Annotated[float, typer.Option(help="Dot grid step, projector pixels.")] = 64.0,
        shifts: Annotated[int, typer.Option(
            help="The grid is shown SHIFTS x SHIFTS times, offset by step/SHIFTS.")] = 2,
        radius: Annotated[float, typer.Option(help="Dot radius, projector pixels.")] = 8.0,
        samples: Annotated[int, typer.Option(help="Frames averaged per pattern.")] = 3,
        joint: Annotated[bool, typer.Option(
            "--joint/--no-joint", help="Refine all cameras together on the shared dots.")]
        = True,
        ref_sigma_mm: Annotated[float, typer.Option(
            "--ref-sigma-mm", help="How well the reference points were measured.")] = 5.0,
        height_sigma_mm: Annotated[float, typer.Option(
            "--height-sigma-mm", help="How well the table height was measured.")] = 2.0,
        json_path: Annotated[Path | None, typer.Option(
            "--json", help="Write the figures as JSON.")] = None,
        report_path: Annotated[Path | None, typer.Option(
            "--report", help="The report page to write (one self-contained HTML file; "
                             "default NAME.report.html beside the rig file).")] = None,
        sim: Annotated[bool, typer.Option(
            "--sim", help="A simulated projector, table and rig, calibrated from the "
                          "--intrinsics file (calibkit intrinsic --sim); the true rig goes "
                          "to NAME.truth.toml, the simulated tape measurements to "
                          "NAME.refs.toml.")] = False,
        sim_rig: Annotated[Path | None, typer.Option(
            "--sim-rig", help="--sim: the simulated hardware, a true rig (calibkit sim rig); "
                              "default: a ring made from --cameras, --volume, --seed.")]
        = None,
        render: Annotated[bool, typer.Option(
            "--render/--no-render", help="--sim: render every camera frame and detect the "
                                         "dots (slow) instead of projecting them.")] = False,
        cameras: Annotated[int | None, typer.Option(
            "--cameras", help="--sim without --sim-rig: cameras (default: as many as the "
                              "--intrinsics file has).")] = None,
        volume: Annotated[float, typer.Option(
            "--volume", help="--sim: metres across (a --sim-rig file's own volume wins).")]
        = 4.0,
        table_height: Annotated[float, typer.Option(
            "--table-height", help="--sim: table height, metres (0: no table).")] = 0.75,
        size: Annotated[str | None, typer.Option(
            help="--sim without --sim-rig: camera size (default 640x480).")] = None,
        noise_px: Annotated[float, typer.Option(
            "--noise-px", help="--sim (projected dots): centroid noise.")] = 0.2,
        ref_error_mm: Annotated[float, typer.Option(
            "--ref-error-mm", help="--sim: error of the tape measurements.")] = 5.0,
        seed: Annotated[int, typer.Option("--seed", help="--sim: random seed.")] = 0,
    ) -> None:
        """Every camera's pose from projected dots on the floor and a table top."""
        from calibkit.calibrate import extrinsic_pipeline as pipeline
        from calibkit.calibrate.extrinsic_reference import load_references
        from calibkit.calibrate.extrinsic_solve import SolveOptions
        from calibkit.synthetic.runs import truth_rig_path

        if not projector:
            raise UserError("say which method: --projector (dots cast by a ceiling "
                            "projector) is the one there is")
        proj_px = parse_size(projector_size)
        if template is not None:
            n = pipeline.write_template(template, proj_px)
            typer.echo(f"wrote {template}: {n} floor reference dots to measure")
            return
        if show_refs:
            if sim:
                raise UserError("--show-refs lights the real projector: not with --sim")
            refs = load_references(refs_path) if refs_path is not None else None
            _show_references(pipeline.shown_references(refs, proj_px), monitor, radius)
            return
        _check_options(out, samples, shifts, step, radius, ref_sigma_mm, height_sigma_mm)
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
