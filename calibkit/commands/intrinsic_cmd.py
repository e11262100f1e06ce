"""`calibkit intrinsic`: a camera's intrinsics from dots on a monitor, a printed board, or --sim."""

from __future__ import annotations

import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

if TYPE_CHECKING:
    from calibkit.calibrate.intrinsic import IntrinsicResult, PlaneView
from calibkit.clitools import Progress, parse_size, print_table, write_json
from calibkit.core.errors import UserError
from calibkit.core.fileio import write_bytes_atomic
from projector.screens import parse_pixel_pitch


def _say(text: str) -> None:
    print(text, file=sys.stderr)


def _check_modes(display: bool, images: Path | None, sim: bool, camera: str, views: int,
                 samples: int) -> None:
    modes = [name for name, on in (("--display", display), ("--images", images is not None),
                                   ("--sim", sim and not display)) if on]
    if len(modes) != 1:
        raise UserError("choose one of --display (a monitor and a camera; with --sim the "
                        "simulated ones), --images DIR --board SPEC, or --sim")
    if images is not None and sim:
        raise UserError("--images reads real photos of a board: drop --sim, or use --sim "
                        "(or --display --sim) without --images")
    if camera == "all" and not sim:
        raise UserError("--camera all calibrates every camera of a simulated rig: with "
                        "--sim only; name the camera (e.g. --camera cam0)")
    if views < 3 and not images:
        raise UserError(f"--views must be at least 3 (got {views}): one view cannot "
                        "separate the focal length from the distance")
    if samples < 1:
        raise UserError(f"--samples must be >= 1, got {samples}")


def _board_views(images: Path, board: str | None
                 ) -> tuple[list[PlaneView], tuple[int, int]]:
    from calibkit.calibrate import intrinsic_pipeline as pipeline

    if board is None:
        raise UserError("--images needs --board, e.g. --board chessboard:9x6:25")
    found, size, missed = pipeline.board_capture(images, board, Progress)
    if missed:
        _say(f"board not found in {len(missed)} image(s): {', '.join(missed)}")
    return found, size


@dataclass(eq=False)
class _Bench:
    """What the monitor path needs from hardware: the screen and its pitch, a window that
    shows dots, a camera, and the user tilting the monitor between views. A real monitor
    and camera here; calibkit.synthetic.monitor_bench.SimBench for `--display --sim`."""

    screen: object
    pitch_mm: float
    window: object
    source: object

    def tilt(self, view: int, n_views: int) -> None:
        input(f"view {view + 1}/{n_views}: hold the monitor in view, tilted, then press "
              "Enter ")


@contextmanager
def _live_bench(device: str, camera: str, monitor: int, pixel_pitch: float | None):
    from calibkit.cameras import open_camera
    from projector.display import WindowDisplay
    from projector.screens import pick_screen, require_display

    require_display()  # before anything else: the commonest mistake (ssh, CI)
    with open_camera(device, name=camera) as source:
        screen, pitch = pick_screen(monitor, pixel_pitch)
        window = WindowDisplay(monitor)
        try:
            yield _Bench(screen, pitch, window, source)
        finally:
            window.close()


def _monitor_views(bench, camera: str, n_views: int, step: float, shifts: int,
                   radius: float, raster: bool, samples: int, page=None, progress=Progress
                   ) -> tuple[list[PlaneView], tuple[int, int], float]:
    """A camera watching dots on a monitor: the views, the image size, the pitch. `bench`
    is the hardware (a real monitor and camera, or the simulated ones: the same path)."""
    from calibkit.calibrate import intrinsic_pipeline as pipeline

    screen = bench.screen
    schedule = pipeline.make_schedule((screen.width_px, screen.height_px), step, shifts,
                                      radius, raster)
    first = next(iter(bench.source), None)
    if first is None:
        raise UserError(f"camera {camera} gives no frames")
    size = (first.image.shape[1], first.image.shape[0])

    def next_view(v: int, done: list) -> None:
        if page is not None:  # the views so far, and where to hold the monitor next
            page.show(camera, size, done, n_views)
        bench.tilt(v, n_views)

    views = pipeline.capture_views(pipeline.LiveMonitor(bench.window, bench.source),
                                   schedule, n_views, bench.pitch_mm, next_view, size,
                                   samples, progress, _say)
    if page is not None:
        page.show(camera, size, views, n_views)
    return views, size, bench.pitch_mm


def _report(result: IntrinsicResult) -> None:
    from calibkit.calibrate.intrinsic import PARAMS

    c = result.camera
    values = [c.fx, c.fy, c.cx, c.cy, c.skew, *c.dist]
    rows = [[name, float(v), float(result.std[name])]
            for name, v in zip(PARAMS, values, strict=True)]
    print_table(rows, ["parameter", "value", "std"])
    per_view = ", ".join(f"{e:.3f}" for e in result.view_rms_px)
    print(f"{c.name}: {result.points} points in {len(result.rvecs)} views, reprojection RMS "
          f"{result.rms_px:.3f} px (per view {per_view}), image coverage "
          f"{100 * result.coverage:.0f}%, inliers {100 * result.inliers.mean():.1f}%")


def register(app: typer.Typer) -> None:
    @app.command("intrinsic")
    def intrinsic_command(
        display: Annotated[bool, typer.Option(
            "--display", help="Show dots on a monitor and watch them with a live camera; "
                              "with --sim, the same display code draws the monitor a "
                              "simulated camera watches (headless OpenGL through EGL).")]
        = False,
        images: Annotated[Path | None, typer.Option(
            help="A folder of images of a printed board (with --board).")] = None,
        board: Annotated[str | None, typer.Option(
            help="chessboard:COLSxROWS:SQUARE_MM, charuco:COLSxROWS:SQUARE_MM:MARKER_MM"
                 "[:DICT] or circles:COLSxROWS:SPACING_MM[:asym].")] = None,
        sim: Annotated[bool, typer.Option(
            "--sim", help="A camera of a simulated rig (--sim-rig) watching a simulated "
                          "monitor; the true rig goes to NAME.truth.toml beside --rig. "
                          "Rendered, it takes about 15 s of CPU per camera at the "
                          "defaults (640x480, 6 views), longer on a busy machine; a "
                          "progress line on stderr shows the time left.")] = False,
        views: Annotated[int, typer.Option(help="Views to take (monitor and --sim).")] = 6,
        camera: Annotated[str, typer.Option(
            help="The camera's name in the rig file; --sim: a camera of the simulated rig, "
                 "or 'all' for every one.")] = "cam0",
        device: Annotated[str, typer.Option(
            help="--display: the camera: a device number, basler:SERIAL or "
                 "genicam:SERIAL (with --sim: the simulated --camera).")] = "0",
        monitor: Annotated[int, typer.Option(
            help="--display: monitor index (see `calibkit displays`, or `calibkit "
                 "displays --sim` for the simulated one).")] = 0,
        pixel_pitch_text: Annotated[str | None, typer.Option(
            "--pixel-pitch", help="Monitor pixel pitch: mm per pixel, or WIDTH_MM/WIDTH_PX "
                                  "(overrides the reported one).")]
        = None,
        step: Annotated[float, typer.Option(help="Dot grid step, screen pixels.")] = 80.0,
        shifts: Annotated[int, typer.Option(
            help="The grid is shown SHIFTS x SHIFTS times, offset by step/SHIFTS.")] = 2,
        radius: Annotated[float, typer.Option(help="Dot radius, screen pixels.")] = 6.0,
        raster: Annotated[bool, typer.Option(
            "--raster", help="One dot at a time (the slow original scan).")] = False,
        samples: Annotated[int, typer.Option(help="Frames averaged per pattern.")] = 3,
        fix_k3: Annotated[bool, typer.Option("--fix-k3", help="Keep k3 at 0.")] = False,
        estimate_skew: Annotated[bool, typer.Option(
            "--skew", help="Estimate the skew too (0 otherwise).")] = False,
        rig: Annotated[Path | None, typer.Option(
            help="Write or update the camera in this rig file.")] = None,
        view: Annotated[str | None, typer.Option(
            "--view", help="Show each view's decoded dots and the image coverage on a web "
                           "page at [HOST:]PORT as the views are taken (a bare port: this "
                           "computer only); it closes when the command ends.")] = None,
        report: Annotated[Path | None, typer.Option(
            "--report", help="Write a one-page HTML report: figures, each view's dots over "
                             "the image, the distortion plot.")] = None,
        plot: Annotated[Path | None, typer.Option(help="Write the distortion plot (PNG).")]
        = None,
        json_path: Annotated[Path | None, typer.Option(
            "--json", help="Write the figures as JSON.")] = None,
        sim_rig: Annotated[Path | None, typer.Option(
            "--sim-rig", help="--sim: the simulated hardware, a true rig (calibkit sim rig); "
                              "default: a ring made from --cameras, --volume, --seed.")]
        = None,
        cameras: Annotated[int, typer.Option(
            help="--sim without --sim-rig: cameras of the simulated rig.")] = 6,
        volume: Annotated[float, typer.Option(
            help="--sim without --sim-rig: metres across the simulated volume.")] = 4.0,
        render: Annotated[bool, typer.Option(
            "--render/--no-render", help="--sim: render every camera frame and capture it "
                                         "(slow: about 15 s of CPU per camera at the "
                                         "defaults, progress with the time left on "
                                         "stderr), or report each dot's imaged centre "
                                         "with --noise-px noise (fast: under a second per "
                                         "camera, for whole rigs).")] = True,
        noise_px: Annotated[float, typer.Option(
            "--noise-px", help="--sim --no-render: centroid noise of a captured dot per axis, "
                               "px (0.035 leaves the rendered capture's 0.05 px "
                               "residual).")] = 0.035,
        seed: Annotated[int, typer.Option(help="--sim: random seed.")] = 0,
        size: Annotated[str | None, typer.Option(
            help="--sim without --sim-rig: camera size (default 640x480).")] = None,
        latency_ms: Annotated[float, typer.Option(help="--sim: display latency.")] = 70.0,
        noise: Annotated[float, typer.Option(help="--sim: sensor noise, DN.")] = 2.0,
        fill: Annotated[float, typer.Option(
            help="--sim: how much of the image the monitor spans (above 1 it overflows "
                 "the image).")] = 0.8,
    ) -> None:
        """Calibrate one camera's intrinsics (focal lengths, principal point, distortion).

        Reads a live camera watching a monitor (--display), a folder of photos of a printed
        board (--images), or a simulated camera (--sim; --display --sim draws its monitor
        with the real display code). A rendered simulated camera takes about 15 s of CPU
        (6 views); the progress line says how long is left.
        """
        import numpy as np

        from calibkit.calibrate import intrinsic_pipeline as pipeline
        from calibkit.calibrate.intrinsic import calibrate, distortion_plot_png

        _check_modes(display, images, sim, camera, views, samples)
        pixel_pitch = parse_pixel_pitch(pixel_pitch_text)
        page = None  # viser stops its server at exit, whichever way the command ends
        if view is not None:
            from calibkit.clitools import parse_view
            from calibkit.commands.coverage_view import IntrinsicView

            page = IntrinsicView(*parse_view(view))
            print(f"views at {page.url}")
        if sim:
            if display and not render:
                raise UserError("--display --sim renders the monitor for the camera; "
                                "--no-render is for --sim alone")
            _sim_command(sim_rig, cameras, volume, size, seed, camera, views, fill, render,
                         noise_px, latency_ms, noise, pixel_pitch, step, shifts, radius,
                         raster, samples, estimate_skew, fix_k3, rig, json_path, plot, report,
                         page, monitor if display else None)
            if page is not None:
                page.close()
            return
        dot_radius_m = 0.0
        if images is not None:
            target_views, img_size = _board_views(images, board)
            if page is not None:
                page.show(camera, img_size, target_views, len(target_views))
        else:
            with _live_bench(device, camera, monitor, pixel_pitch) as bench:
                target_views, img_size, pitch = _monitor_views(
                    bench, camera, views, step, shifts, radius, raster, samples, page)
            dot_radius_m = radius * pitch / 1000.0
        result = calibrate(target_views, img_size, camera, fix_skew=not estimate_skew,
                           fix_k3=fix_k3, dot_radius_m=dot_radius_m)
        _report(result)
        figures = result.figures()
        figures["camera"] = camera
        if rig is not None:
            pipeline.write_rig(rig, result.camera, result)
            print(f"camera {camera} written to {rig}")
        if plot is not None:
            uv = np.concatenate([v.uv for v in target_views])
            write_bytes_atomic(plot, distortion_plot_png(result, uv))
        if json_path is not None:
            write_json(json_path, figures)
        if report is not None:
            _write_report(report, [(camera, result, list(target_views))])
        if page is not None:
            page.close()


def _write_report(path: Path, cameras: list) -> None:
    from calibkit.calibrate.html_report import intrinsic_page, write_page

    write_page(path, intrinsic_page(cameras))
    print(f"report written to {path}")


class _RunProgress:
    """One progress line for a whole rendered run (every camera's every view) on stderr:
    patterns shown of all, the time elapsed and the time left. The capture asks it for one
    sink per view (as it would ask calibkit.clitools.Progress); a view's summary goes out as
    its own line when it ends."""

    def __init__(self, total: int, every_s: float = 2.0, stream=None) -> None:
        self.line = Progress("rendering", total, every_s=every_s, stream=stream)
        self.base = 0
        self.camera = ""

    def __call__(self, label: str, total: int) -> _ViewProgress:
        return _ViewProgress(self, f"{self.camera} {label}".strip(), total)

    def show(self, done: int, label: str) -> None:
        self.line.update(done, self.left(done) + f" ({label})")

    def left(self, done: int) -> str:
        elapsed = time.monotonic() - self.line.start
        if done <= 0 or not self.line.total:
            return "elapsed"
        return f"elapsed, about {elapsed * (self.line.total - done) / done:.0f} s left"

    def finish(self) -> None:
        self.line.finish("elapsed")


@dataclass(eq=False)
class _ViewProgress:
    run: _RunProgress
    label: str
    total: int

    def update(self, done: int) -> None:
        self.run.show(self.run.base + done, self.label)

    def finish(self, text: str = "") -> None:
        self.run.base += self.total
        _say(f"{self.label}: {text}")
        self.run.show(self.run.base, self.label)


def _display_sim_runs(run, n_views: int, fill: float, monitor: int,
                      pixel_pitch: float | None, step: float, shifts: int, radius: float,
                      raster: bool, samples: int, fix_skew: bool, fix_k3: bool,
                      rig_path: Path | None, progress: _RunProgress):
    """--display --sim: each camera through the monitor path a real monitor takes (the same
    schedule, display code, capture and guidance), with the window drawn off-screen onto a
    simulated monitor and the camera simulated (calibkit.synthetic.monitor_bench). The
    estimate gets only the frames; the true camera travels beside it, for scoring."""
    from calibkit.calibrate.intrinsic import calibrate
    from calibkit.calibrate.intrinsic_pipeline import write_rig
    from calibkit.synthetic import intrinsic_sim
    from calibkit.synthetic.monitor_bench import open_bench

    for name in run.names:
        progress.camera = name
        truth = run.hardware[name]
        with open_bench(truth, n_views, fill, intrinsic_sim.camera_config(run, name),
                        monitor, pixel_pitch) as bench:
            found, size, pitch = _monitor_views(bench, name, n_views, step, shifts, radius,
                                                raster, samples, None, progress)
        result = calibrate(found, size, name, fix_skew=fix_skew, fix_k3=fix_k3,
                           dot_radius_m=radius * pitch / 1000.0)
        if rig_path is not None:
            write_rig(rig_path, result.camera, result)
        yield intrinsic_sim.CameraRun(name, result, truth, found)


def _sim_command(sim_rig, cameras, volume, size, seed, camera, views, fill, render, noise_px,
                 latency_ms, noise, pixel_pitch, step, shifts, radius, raster, samples,
                 estimate_skew, fix_k3, rig, json_path, plot, report=None,
                 page=None, monitor: int | None = None) -> None:
    """--sim: one camera of the simulated rig (or all of them) calibrated from simulated
    monitor views; `monitor` set (--display --sim): through the real monitor path. The
    estimate sees only the captured dots; the truth goes to NAME.truth.toml beside --rig
    and to the figures, for scoring."""
    import numpy as np

    from calibkit.calibrate.intrinsic import distortion_plot_png
    from calibkit.synthetic import intrinsic_sim
    from calibkit.synthetic.runs import truth_rig_path

    display = monitor is not None
    # --display --sim: the simulated monitor is the hardware; --pixel-pitch overrides what
    # it reports, as on a real monitor, rather than changing the monitor
    run = intrinsic_sim.setup(sim_rig, cameras, volume, parse_size(size) if size else None,
                              seed, camera, fill, noise_px, latency_ms, noise,
                              None if display else pixel_pitch, step, shifts, radius, raster)
    if plot is not None and len(run.names) > 1:
        raise UserError("--plot draws one camera's distortion: give --camera NAME with it")
    rendering = _RunProgress(len(run.names) * views * len(run.schedule.frames))
    if display:
        runs = _display_sim_runs(run, views, fill, monitor, pixel_pitch, step, shifts, radius,
                                 raster, samples, not estimate_skew, fix_k3, rig, rendering)
    else:
        runs = intrinsic_sim.calibrate_cameras(run, views, fill, render, noise_px, samples,
                                               not estimate_skew, fix_k3, radius, rig,
                                               rendering, _say)
    done = []
    progress = Progress("cameras", len(run.names), enabled=len(run.names) > 1 and not render)
    for k, cam in enumerate(runs):
        done.append(cam)
        if page is not None:  # a simulated camera's views come all at once
            page.show(cam.name, cam.result.camera.size, cam.views, views)
        if len(run.names) == 1:
            _report(cam.result)
            e = intrinsic_sim.truth_error(cam.result, cam.truth)
            print(f"against the simulator's truth: fx {100 * e['fx_rel']:+.4f}%, fy "
                  f"{100 * e['fy_rel']:+.4f}%, cx {e['cx_px']:+.3f} px, cy "
                  f"{e['cy_px']:+.3f} px")
        progress.update(k + 1, f"{cam.name}: {cam.result.points} dots, rms "
                               f"{cam.result.rms_px:.3f} px")
    progress.finish()
    if render:
        rendering.finish()
    if len(run.names) > 1:
        _sim_summary(done)
    if rig is not None:
        run.hardware.save(truth_rig_path(rig))
        print(f"{'cameras' if len(run.names) > 1 else 'camera'} {', '.join(run.names)} "
              f"written to {rig} (true rig in {truth_rig_path(rig)})")
    if plot is not None:
        uv = np.concatenate([v.uv for v in done[0].views])
        write_bytes_atomic(plot, distortion_plot_png(done[0].result, uv))
    if json_path is not None:
        figures = intrinsic_sim.figures(done, render, noise_px)
        # which capture made the views: the monitor path of --display, or the simulator's
        figures["capture"] = "display" if display else "simulator"
        write_json(json_path, figures)
    if report is not None:
        _write_report(report, [(r.name, r.result, list(r.views)) for r in done])


def _sim_summary(done) -> None:
    """One line per camera when a whole rig was calibrated."""
    from calibkit.synthetic.intrinsic_sim import truth_error

    table = []
    for r in done:
        c, e = r.result.camera, truth_error(r.result, r.truth)
        table.append([r.name, r.result.points, len(r.result.rvecs), r.result.rms_px, c.fx,
                      r.result.std["fx"], c.cx, c.cy, c.dist[0], 100 * e["fx_rel"],
                      e["cx_px"], e["cy_px"]])
    print_table(table, ["camera", "points", "views", "rms_px", "fx", "fx_std", "cx", "cy",
                        "k1", "vs_truth_fx_%", "vs_truth_cx_px", "vs_truth_cy_px"])
