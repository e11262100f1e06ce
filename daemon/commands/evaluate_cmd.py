"""`mocapd evaluate`: a robot's own trajectory against ours (clock, frame, pose errors)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from calibkit.clitools import print_table, write_json
from calibkit.core.errors import UserError
from calibkit.core.fileio import write_text_atomic


def register(app: typer.Typer) -> None:
    @app.command("evaluate")
    def evaluate_cmd(
        reference: Annotated[Path, typer.Argument(
            help="The reference trajectory (ours: a poses CSV, or TUM).")],
        estimate: Annotated[Path, typer.Argument(
            help="The trajectory to score (a robot's own log: TUM or CSV).")],
        ref_body: Annotated[str | None, typer.Option(
            "--ref-body", help="The body to take from a reference CSV with several.")] = None,
        est_body: Annotated[str | None, typer.Option(
            "--est-body", help="The body to take from an estimate CSV with several.")] = None,
        ref_format: Annotated[str, typer.Option(
            "--ref-format", help="auto, tum or csv.")] = "auto",
        est_format: Annotated[str, typer.Option(
            "--est-format", help="auto, tum or csv.")] = "auto",
        ref_units: Annotated[str, typer.Option(
            "--ref-units", help="Position units of the reference: m, cm or mm.")] = "m",
        est_units: Annotated[str, typer.Option(
            "--est-units", help="Position units of the estimate: m, cm or mm.")] = "m",
        scale: Annotated[bool, typer.Option(
            "--scale/--no-scale", help="Fit a scale too (Sim(3)), e.g. for monocular "
                                       "visual odometry.")] = False,
        drift: Annotated[bool, typer.Option(
            "--drift/--no-drift", help="Fit the clocks' drift (ppm) besides their "
                                       "offset.")] = True,
        offset: Annotated[float | None, typer.Option(
            "--offset", help="The clock offset (estimate minus reference, s) when known; "
                             "otherwise it is found.")] = None,
        max_offset: Annotated[float, typer.Option(
            "--max-offset", help="Search clock offsets up to this many seconds.")] = 2.0,
        delta: Annotated[float, typer.Option(
            "--delta", help="Time step of the relative errors, s.")] = 1.0,
        body_rotation: Annotated[bool, typer.Option(
            "--body-rotation/--no-body-rotation",
            help="Fit a constant rotation between the two bodies' frames (a robot's body "
                 "frame and the marker body's are rarely the same).")] = False,
        gross_mm: Annotated[float, typer.Option(
            "--gross-mm", help="Position errors above this are counted as gross.")] = 50.0,
        plot: Annotated[Path | None, typer.Option(
            "--plot", help="Write the paths and errors as a PNG.")] = None,
        html_path: Annotated[Path | None, typer.Option(
            "--html", help="Write one HTML page with the figures and the plots.")] = None,
        errors_path: Annotated[Path | None, typer.Option(
            "--errors", help="Write the per-pose errors as CSV.")] = None,
        json_path: Annotated[Path | None, typer.Option(
            "--json", help="Write the figures as JSON.")] = None,
    ) -> None:
        """Line up a trajectory's clock and world frame with a reference, then measure its
        absolute and relative pose errors.

        Reads two trajectory files: the reference (our poses, e.g. `mocapd track --out`) and
        the estimate (a robot's own log, TUM or CSV); `mocapd track --sim` writes poses of a
        simulated take to try it on."""
        # imported here: scipy.signal and the plotting cost every other mocapd command a
        # second and more at its start
        from daemon.analysis import trajectory_report as report
        from daemon.analysis.trajectory_eval import evaluate, figures
        from daemon.formats.trajectory_io import read_trajectory

        if delta <= 0 or max_offset <= 0 or gross_mm <= 0:
            raise UserError("--delta, --max-offset and --gross-mm must be positive")
        ref = read_trajectory(reference, ref_format, ref_body, ref_units)
        est = read_trajectory(estimate, est_format, est_body, est_units)
        ev = evaluate(ref, est, with_scale=scale, fit_drift=drift, max_offset_s=max_offset,
                      known_offset_s=offset, rpe_delta_s=delta,
                      fit_body_rotation=body_rotation)
        figs = figures(ev, gross_mm=gross_mm)
        figs["reference"] = {"file": str(reference), "poses": len(ref)}
        figs["estimate"] = {"file": str(estimate), "poses": len(est)}
        print_table(report.table_rows(figs), ["figure", "value"])
        png = None
        if plot is not None or html_path is not None:
            png = report.plot_png(ev, f"{estimate.name} against {reference.name}")
        if plot is not None:
            report.write_png(plot, png)
        if html_path is not None:
            report.write_html(html_path, figs, png, str(reference), str(estimate))
        if errors_path is not None:
            write_text_atomic(errors_path, report.errors_csv(ev))
        if json_path is not None:
            write_json(json_path, figs)
