"""`calibkit extrinsic --projector`: every camera's pose from projected floor and table dots."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from calibkit import extrinsic as ex
from calibkit import plane_views
from calibkit.camera import Rig
from calibkit.clitools import Progress, print_table, write_json
from calibkit.commands.common import (
    check_estimate,
    need_intrinsics_for_sim,
    parse_size,
    sim_hardware,
    truth_rig_path,
)
from calibkit.errors import UserError
from calibkit.fileio import write_text_atomic
from projector.patterns import Schedule, coded_schedule

# a plane map whose reference points disagree by more than this is suspect
MAP_WARN_MM = 15.0


def _schedule(projector_px, step: float, shifts: int, radius: float) -> Schedule:
    try:
        return coded_schedule(projector_px, step, shifts, radius)
    except ValueError as exc:
        raise UserError(f"dot pattern: {exc}") from None


def _sessions(refs: ex.References, table: bool | None) -> bool:
    """Whether to run the table session: as asked, else when the references have a table."""
    if table is None:
        return refs.has_table
    if table and not refs.has_table:
        raise UserError("--table needs the table in the reference-points file: add [table] "
                        "with height_m and at least 4 [[table.point]] entries")
    return table


def _capture_live(intr: Rig, specs: list[str], monitor: int, schedule: Schedule,
                  tsched: Schedule | None, samples: int) -> tuple[list, list | None, int]:
    """The projector on monitor `monitor`, the cameras from their device numbers or files."""
    from calibkit.sources import open_source
    from projector.display import WindowDisplay
    from projector.screens import require_display

    if len(specs) != len(intr):
        raise UserError(f"give one --camera per camera of the rig ({len(intr)}: "
                        f"{', '.join(intr.names)}), got {len(specs)}")
    require_display()
    sources = [open_source(s) for s in specs]
    iters = [iter(s) for s in sources]
    window = WindowDisplay(monitor)

    class LiveRig:
        def show(self, dots) -> None:
            window.show(dots)

        def grab(self) -> list[np.ndarray]:
            out = []
            for name, it in zip(intr.names, iters, strict=True):
                frame = next(it, None)
                if frame is None:
                    raise UserError(f"camera {name} stopped delivering frames")
                out.append(frame.image)
            return out

    try:
        floor = _run_session(LiveRig(), schedule, len(intr), "floor", samples)
        table = None
        if tsched is not None:
            input("put the table in place under the projector, then press Enter ")
            table = _run_session(LiveRig(), tsched, len(intr), "table", samples,
                                 floor.latency_frames)
    finally:
        window.close()
        for s in sources:
            s.close()
    frames = floor.frames + (table.frames if table is not None else 0)
    return floor.cameras, None if table is None else table.cameras, frames


def _show_references(refs: ex.References, monitor: int, radius: float) -> None:
    """Light the reference dots so the user can mark and measure where they land."""
    from projector.display import Dots, WindowDisplay
    from projector.screens import require_display

    require_display()
    pts = np.concatenate([refs.floor_px, refs.table_px])
    window = WindowDisplay(monitor)
    try:
        window.show(Dots.make(pts, radius))
        input(f"{len(pts)} reference dots shown: mark and measure them, then press Enter ")
    finally:
        window.close()


def _run_session(device, schedule: Schedule, n_cameras: int, label: str, samples: int,
                 latency_frames=None):
    progress = Progress(f"{label} dots", len(schedule.frames))
    cap = ex.capture_session(device, schedule, n_cameras, samples=samples,
                             progress=lambda done, total: progress.update(done),
                             latency_frames=latency_frames)
    progress.finish(f"{cap.frames} camera frames ({cap.frames / 30.0:.1f} s at 30 fps)")
    return cap


def _print(result: ex.ExtrinsicResult) -> None:
    rows = [[c["name"], "yes" if c["calibrated"] else "NO", c["floor_dots"], c["table_dots"],
             c["reprojection_rms_px"], c["mean_ray_distance_mm"],
             c["mean_ray_distance_table_mm"]] for c in result.report["cameras"]]
    print_table(rows, ["camera", "calibrated", "floor dots", "table dots", "rms_px",
                       "ray_mm", "ray_table_mm"])
    r = result.report
    def mm(v: float) -> str:
        return "-" if not np.isfinite(v) else f"{v:.2f} mm"

    typer.echo(f"\nall cameras: reprojection RMS {r['reprojection_rms_px']:.3f} px, mean ray "
               f"distance {mm(r['mean_ray_distance_mm'])} over {r['dots']} dots, "
               f"{mm(r['mean_ray_distance_table_mm'])} over the {r['table_dot_points']} "
               "table dots (dots seen by two or more cameras)")


def _keep_intrinsic_quality(result: ex.ExtrinsicResult, intr: Rig, intr_path: Path,
                            out: Path) -> None:
    """The intrinsics are passed through unchanged, so their figures (the per-parameter
    std the wand solve's priors read, and where the monitor views are kept, now relative to
    `out`) go on with them into the rig file."""
    per = intr.quality.get("intrinsic", {})
    kept = {n: per[n] for n in result.rig.names if n in per}
    if kept:
        quality = plane_views.rebase({"intrinsic": kept}, intr_path, out)
        result.rig = dataclasses.replace(result.rig,
                                         quality={**result.rig.quality, **quality})


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
            "--camera", help="Live: a camera device number or video, once per camera of "
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
        if not projector:
            raise UserError("say which method: --projector (dots cast by a ceiling "
                            "projector) is the one there is")
        proj_px = parse_size(projector_size)
        if template is not None:
            layout = ex.reference_layout_px(proj_px)
            refs_t = ex.References(layout, np.full((len(layout), 2), np.nan),
                                   projector_size=proj_px)
            write_text_atomic(template, ex.references_toml(
                refs_t, "Reference dots: replace each nan with where the dot lands on the\n"
                        "floor, x and y in metres from your chosen origin (docs/extrinsic.md)."
                        "\nFor the table add [table] height_m and [[table.point]] entries."))
            typer.echo(f"wrote {template}: {len(layout)} floor reference dots to measure")
            return
        if show_refs:
            if sim:
                raise UserError("--show-refs lights the real projector: not with --sim")
            shown = ex.load_references(refs_path) if refs_path is not None else ex.References(
                ex.reference_layout_px(proj_px), np.zeros((16, 2)), projector_size=proj_px)
            _show_references(shown, monitor, radius)
            return
        if out is None:
            raise UserError("--out RIG.toml is required")
        if samples < 1 or shifts < 1 or step <= 0 or radius <= 0:
            raise UserError("--samples and --shifts must be >= 1, --step and --radius > 0")
        if ref_sigma_mm <= 0 or height_sigma_mm <= 0:
            raise UserError("--ref-sigma-mm and --height-sigma-mm must be positive")
        truth = None
        if sim:
            from calibkit.synthetic import projector as sp

            if not 0 <= table_height < 2.0:
                raise UserError(f"--table-height must be in [0, 2) m, got {table_height}")
            if intrinsics is None:
                raise need_intrinsics_for_sim("calibkit extrinsic --projector")
            if sim_rig is not None and (size is not None or cameras is not None):
                raise UserError("give --sim-rig or --cameras/--size, not both: the rig file "
                                "sets the cameras")
            intr = Rig.load(intrinsics)
            hardware = sim_hardware(sim_rig, cameras or len(intr), volume, seed,
                                    parse_size(size or "640x480"))
            check_estimate(intr, hardware, intrinsics, "--intrinsics")
            volume = float(hardware.meta.get("volume_m", volume))
            scene = sp.scene_for_rig(hardware, volume, table_height or None, seed)
            truth = scene.rig
            tpx = sp.table_reference_px(scene) if scene.table is not None else np.zeros((0, 2))
            m = sp.measured_references(scene, ex.reference_layout_px(proj_px), tpx,
                                       ref_error_mm / 1000.0, seed=seed)
            refs = ex.References(m["floor_px"], m["floor_xy_m"],
                                 m.get("table_px", np.zeros((0, 2))),
                                 m.get("table_xy_m", np.zeros((0, 2))),
                                 m.get("table_height_m"), projector_size=proj_px)
        else:
            if refs_path is None:
                raise UserError("--refs REFS.toml is required (make one with --template "
                                "and a tape; see docs/extrinsic.md)")
            refs = ex.load_references(refs_path)
            proj_px = refs.projector_size
            if intrinsics is None:
                raise UserError("--intrinsics RIG.toml is required (from calibkit intrinsic)")
            intr = Rig.load(intrinsics)
        with_table = _sessions(refs, table)
        if not sim and not camera:
            raise UserError("live capture needs --camera once per camera (or --sim)")
        floor_map, table_map = ex.plane_maps(refs)
        if not with_table:
            table_map = None
        for what, pm in (("floor", floor_map), ("table", table_map)):
            if pm is None:
                continue
            fit = ("exact with 4 points: add more to check it" if pm.n_points == 4 else
                   f"residual RMS {pm.residual_rms_mm:.1f} mm, max {pm.residual_max_mm:.1f} mm")
            typer.echo(f"{what} map from {pm.n_points} reference points: {fit}")
            if pm.residual_max_mm > MAP_WARN_MM:
                typer.echo(f"warning: a {what} reference point is {pm.residual_max_mm:.0f} mm "
                           "off the others' fit: re-measure it", err=True)
        schedule = _schedule(proj_px, step, shifts, radius)
        tsched = ex.table_schedule(schedule, table_map) if table_map is not None else None
        if sim and render:
            from calibkit.synthetic import projector as sp

            cfg = sp.ProjectorSimConfig(projector_px=proj_px, seed=seed)
            with sp.ProjectorRigSim(scene, cfg) as dev:
                fcap = _run_session(dev, schedule, len(scene.rig), "floor", samples)
                tcap = None
                if with_table:
                    dev.set_table(True)
                    tcap = _run_session(dev, tsched, len(scene.rig), "table", samples,
                                        fcap.latency_frames)
            floor_dots, table_dots = fcap.cameras, None if tcap is None else tcap.cameras
            frames = fcap.frames + (tcap.frames if tcap is not None else 0)
        elif sim:
            from calibkit.synthetic import projector as sp

            floor_dots = sp.simulated_dots(scene, schedule.points_xy, False, noise_px,
                                           seed=seed)
            table_dots = None
            cfg = sp.ProjectorSimConfig(projector_px=proj_px, seed=seed)
            lat = sp.latency_frames(cfg, len(scene.rig))
            frames = ex.capture_frames_estimate(schedule, lat, samples)
            if tsched is not None:
                table_dots = sp.simulated_dots(scene, schedule.points_xy, True, noise_px,
                                               seed=seed + 1,
                                               shown=np.concatenate(tsched.layers))
                frames += ex.capture_frames_estimate(tsched, lat, samples)
        else:
            floor_dots, table_dots, frames = _capture_live(intr, list(camera), monitor,
                                                           schedule, tsched, samples)
        names = truth.names if truth is not None else intr.names
        dots = ex.assemble(names, floor_dots, table_dots, schedule, floor_map, table_map)
        opts = ex.SolveOptions(joint=joint, reference_sigma_m=ref_sigma_mm / 1000.0,
                               height_sigma_m=height_sigma_mm / 1000.0)
        result = ex.calibrate(intr, dots, floor_map, table_map, opts)
        result.report["capture"] = {"frames": frames, "seconds_at_30fps": frames / 30.0,
                                    "sessions": 1 + int(with_table),
                                    "simulated_frames": bool(sim and not render)}
        _print(result)
        typer.echo(f"capture: {frames} camera frames, {frames / 30.0:.1f} s at 30 fps"
                   + (" (estimated from the latencies)" if sim and not render else ""))
        _keep_intrinsic_quality(result, intr, intrinsics, out)
        result.rig.save(out)
        ex.save_dots(out.with_name(out.stem + ".dots.npz"), result.dots, result.inlier)
        rec = ex.floor_recording(result.rig, result.dots, result.inlier)
        if rec is not None:
            from calibkit.recording import save_observations

            save_observations(out.with_name(out.stem + ".floor.mcrec"), rec)
        if truth is not None:
            from calibkit.compare import compare_rigs

            truth.save(truth_rig_path(out))
            write_text_atomic(out.with_name(out.stem + ".refs.toml"), ex.references_toml(
                refs, "simulated tape measurements (calibkit extrinsic --sim)"))
            cmp = compare_rigs(truth, result.rig, align=False)
            result.report["truth"] = {
                "cameras": cmp["cameras"],
                "position_error_max_mm": max(c["position_mm"] for c in cmp["cameras"]),
                "rotation_error_max_deg": max(c["rotation_deg"] for c in cmp["cameras"])}
            t = result.report["truth"]
            typer.echo(f"against the simulator's truth: position error up to "
                       f"{t['position_error_max_mm']:.1f} mm, orientation up to "
                       f"{t['rotation_error_max_deg']:.3f} deg")
        for w in result.warnings:
            typer.echo(f"warning: {w}", err=True)
        if json_path is not None:
            write_json(json_path, result.report)
        typer.echo(f"wrote {out}" + (f" (true rig in {truth_rig_path(out)})" if sim else ""))
        if result.report["not_calibrated"]:
            print(f"not calibrated: {', '.join(result.report['not_calibrated'])}",
                  file=sys.stderr)
