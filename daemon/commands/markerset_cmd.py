"""`mocapd markerset learn|check`, `mocapd label`, `mocapd fill`, `mocapd skeleton`: marker sets."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from calibkit.clitools import HELP_MARKUP, print_table, write_json
from calibkit.core.errors import UserError
from daemon.commands.points_input import read_points_for_command

JsonOpt = Annotated[Path | None, typer.Option("--json", help="Write the figures as JSON.")]
RateOpt = Annotated[float | None, typer.Option(
    "--rate", help="Frame rate, Hz, for inputs that do not carry one (CSV).")]


def _check_out(path: Path, inputs: list[Path]) -> None:
    if path.suffix.lower() not in (".c3d", ".csv"):
        raise UserError(f"--out must end in .c3d or .csv, got {path.name}")
    for p in inputs:
        if p.exists() and path.resolve() == p.resolve():
            raise UserError(f"--out {path} is an input; write to another file")


def _csv_columns(path: Path) -> list[str]:
    """The column names of a CSV file (its first line that is not a # comment)."""
    try:
        with open(path, encoding="utf-8") as handle:
            for line in handle:
                if line.strip() and not line.startswith("#"):
                    return [c.strip().lower() for c in line.split(",")]
    except (OSError, UnicodeDecodeError):
        raise UserError(f"cannot read {path} as a text CSV file") from None
    raise UserError(f"{path} is empty")


def register(app: typer.Typer) -> None:
    ms_app = typer.Typer(help="Marker sets: learn one from labelled takes; check one on a take.",
                         no_args_is_help=True, rich_markup_mode=HELP_MARKUP)
    app.add_typer(ms_app, name="markerset")

    @ms_app.command("learn")
    def learn_cmd(
        takes: Annotated[list[Path], typer.Argument(help="Labelled takes (.c3d or .csv).")],
        out: Annotated[Path, typer.Option("--out", help="Marker set to write (.toml).")],
        name: Annotated[str | None, typer.Option("--name", help="Marker set name.")] = None,
        spread_mm: Annotated[float, typer.Option(
            "--segment-spread-mm", help="Markers whose distances vary less than this "
                                        "form a segment.")] = 12.0,
        json_path: JsonOpt = None,
    ) -> None:
        """Learn a marker set (segments, distances, handedness) from labelled takes.

        Reads labelled takes (.c3d or CSV); `mocapd label --sim --out
        take.c3d` writes a simulated one."""
        from daemon.formats.c3dio import read_take
        from daemon.labelling.markerset import learn

        if out.suffix.lower() != ".toml":
            raise UserError(f"--out must be a .toml file, got {out.name}")
        if spread_mm <= 0:
            raise UserError("--segment-spread-mm must be positive")
        loaded = [read_take(p) for p in takes]
        ms = learn(loaded, spread_mm / 1000.0, name or out.stem)
        ms.save(out)
        rows = [[s.name, len(s.markers), round(1000 * s.spread_m, 1),
                 ms.segments[s.parent].name if s.parent >= 0 else "-"] for s in ms.segments]
        print_table(rows, ["segment", "markers", "spread_mm", "parent"])
        typer.echo(f"wrote {out}: {ms.n} markers, {len(ms.segments)} segments, "
                   f"{len(ms.chiral)} handedness checks, from "
                   f"{sum(t.n_frames for t in loaded)} frames")
        if json_path is not None:
            write_json(json_path, {"markers": ms.n, "segments": [
                {"name": s.name, "markers": [ms.labels[i] for i in s.markers],
                 "spread_mm": 1000 * s.spread_m} for s in ms.segments]})

    @ms_app.command("check")
    def check_cmd(
        take_path: Annotated[Path, typer.Argument(
            help="A take: labelled (.c3d, or CSV frame,label,x,y,z) or unlabelled points "
                 "(CSV frame,x,y,z, or --unlabelled).")],
        markerset: Annotated[str, typer.Option(
            "--markerset", help="Marker set: a .toml file or a shipped set's name (cmu41, "
                                "sim_person).")],
        unlabelled: Annotated[bool, typer.Option(
            "--unlabelled", help="Ignore the take's labels: judge the set as labelling "
                                 "will use it, from its start on a window of frames.")] = False,
        json_path: JsonOpt = None,
    ) -> None:
        """How well a marker set fits a take, before labelling it: the body's scale, each
        segment's proportions, markers placed otherwise or missing, and a verdict.

        Reads a take, labelled or not; `mocapd label --sim --out
        take.c3d` writes a simulated one."""
        import numpy as np

        from daemon.formats.c3dio import Points, read_take
        from daemon.labelling.markerset import open_set
        from daemon.labelling.markerset_fit import check_fit, check_points

        ms = open_set(markerset)
        if not take_path.exists():
            raise UserError(f"{take_path} does not exist")
        suffix = take_path.suffix.lower()
        if suffix not in (".c3d", ".csv"):
            raise UserError(f"{take_path}: a take is a .c3d or .csv file")
        labelled = suffix == ".c3d" or "label" in _csv_columns(take_path)
        if labelled:
            take = read_take(take_path)
            shared = [n for n in ms.labels if n in take.labels]
            if not unlabelled and len(shared) < 3:
                raise UserError(f"{take_path}: its labels share {len(shared)} marker(s) with "
                                f"the set {ms.name}; give --unlabelled to judge it from "
                                f"its points")
        if labelled and not unlabelled:
            xyz = np.full((take.n_frames, ms.n, 3), np.nan)
            idx = [take.labels.index(n) for n in shared]
            xyz[:, [ms.labels.index(n) for n in shared]] = take.xyz_m[:, idx]
            extra = [n for n in take.labels if n not in ms.labels]
            fit = check_fit(ms, xyz, "labels", extra)
        else:
            pts = Points.from_take(take) if labelled else \
                read_points_for_command(take_path)[0]
            if not len(pts.frame):
                raise UserError(f"{take_path} holds no points")
            fit = check_points(ms, pts.split()[1])
        rows = [[s.name, s.markers, s.seen, s.length_ratio, s.relative, s.misfit,
                 s.spread_mm, s.set_spread_mm] for s in fit.segments]
        print_table(rows, ["segment", "markers", "seen", "length_ratio", "relative",
                           "misfit", "spread_mm", "set_spread_mm"])
        worst = ", ".join(f"{k} {fit.misfit[k]:.2f}" for k in
                          sorted(fit.misfit, key=lambda k: -fit.misfit[k])[:5])
        source = "its labels" if fit.labelled_by == "labels" else \
            "a start from the set alone on a window of frames"
        typer.echo(f"{take_path.name} against {ms.name} ({fit.frames} frames, labelled by "
                   f"{source}): scale {fit.scale:.3f}; misfit (allowances for another "
                   f"subject) median {fit.misfit_median:.2f}, worst {worst}")
        typer.echo(fit.verdict)
        if json_path is not None:
            write_json(json_path, fit.to_json())

    @app.command("label")
    def label_cmd(
        out: Annotated[Path, typer.Option("--out", help="Labelled take (.c3d or .csv).")],
        points: Annotated[Path | None, typer.Argument(
            help="Unlabelled points: CSV frame,x,y,z (metres), a C3D (labels ignored), or a "
                 "recording of blobs (.mcrec, with --rig: triangulated first).")] = None,
        markerset: Annotated[str | None, typer.Option(
            "--markerset", help="Marker set: a .toml file or a shipped set's name (cmu41, "
                                "sim_person; --sim: sim_person).")] = None,
        rig_path: Annotated[Path | None, typer.Option(
            "--rig", help="The calibrated rig, to triangulate a .mcrec recording.")] = None,
        start_frames: Annotated[int, typer.Option(
            "--start-frames", help="Use the first N frames' labels from --start-labels (or "
                                   "from a labelled C3D given as POINTS).")] = 0,
        start_labels: Annotated[Path | None, typer.Option(
            "--start-labels", help="Labelled take holding the first frames' labels.")] = None,
        old_frames: Annotated[int | None, typer.Option("--seed-frames", hidden=True)] = None,
        old_labels: Annotated[Path | None, typer.Option("--seed", hidden=True)] = None,
        rate: RateOpt = None,
        json_path: JsonOpt = None,
        strict: Annotated[bool, typer.Option(
            "--strict", help="Refuse a points CSV with bad rows (text, NaN, inf, wrong "
                             "column count) instead of skipping and counting them.")] = False,
        sim: Annotated[bool, typer.Option(
            "--sim", help="Instead of POINTS: the simulator's person walking a circle in "
                          "its marker set, --hidden of the marker-frames hidden and --ghosts "
                          "stray points a frame; the labels scored against the truth. "
                          "--start-frames N takes the first N frames' true labels, as a "
                          "user's hand labels.")] = False,
        frames: Annotated[int, typer.Option(help="--sim: frames (120 a second).")] = 600,
        hidden: Annotated[float, typer.Option(
            help="--sim: share of marker-frames hidden, in spans of 0.1-1 s.")] = 0.1,
        ghosts: Annotated[int, typer.Option(help="--sim: stray points a frame.")] = 2,
        sim_seed: Annotated[int, typer.Option(
            "--sim-seed", help="--sim: random seed (--seed is the old name of "
                               "--start-labels).")] = 0,
    ) -> None:
        """Name every point of every frame; ghosts are left out."""
        from daemon.commands.label_run import run_label  # deferred: loads numpy when run

        _check_out(out, [points] if points is not None else [])
        # --seed and --seed-frames: the names these options had before
        start_frames = start_frames if old_frames is None else old_frames
        start_labels = start_labels if old_labels is None else old_labels
        if start_frames < 0:
            raise UserError("--start-frames must be >= 0")
        if markerset is None and not sim:
            raise UserError("give --markerset SET (a .toml file, cmu41 or sim_person)")
        run_label(out, points, markerset, rig_path, start_frames, start_labels, rate, json_path,
                  strict, sim, frames, hidden, ghosts, sim_seed)

    @app.command("fill")
    def fill_cmd(
        out: Annotated[Path, typer.Option("--out", help="Filled take (.c3d or .csv).")],
        take_path: Annotated[Path | None, typer.Argument(
            help="Labelled take (.c3d or .csv).")] = None,
        max_gap: Annotated[float | None, typer.Option(
            "--max-gap", help="Longest gap to fill, seconds (longer ones stay empty).")] = None,
        method: Annotated[str, typer.Option(
            "--method", help="auto, rigid, cubic, linear, newton or pca.")] = "auto",
        markerset: Annotated[str | None, typer.Option(
            "--markerset", help="Marker set (.toml or a shipped set's name) for segment "
                                "spreads; else the take's own.")] = None,
        rate: RateOpt = None,
        json_path: JsonOpt = None,
        sim: Annotated[bool, typer.Option(
            "--sim", help="Instead of a take: the simulator's person walking, --hidden of "
                          "its marker-frames hidden in spans of 0.1-1 s; the filled samples "
                          "scored against where the markers truly were.")] = False,
        frames: Annotated[int, typer.Option(help="--sim: frames (120 a second).")] = 600,
        hidden: Annotated[float, typer.Option(
            help="--sim: share of marker-frames hidden.")] = 0.1,
        seed: Annotated[int, typer.Option(help="--sim: random seed.")] = 0,
    ) -> None:
        """Fill the gaps of hidden markers; filled samples are marked (CSV column filled).

        Reads a labelled take with gaps, or with --sim a simulated one (`mocapd label --sim
        --out take.c3d` writes one too)."""
        from daemon.analysis.gapfill import METHODS, fill
        from daemon.formats.c3dio import read_take, write_take
        from daemon.labelling.markerset import open_set

        _check_out(out, [take_path] if take_path is not None else [])
        if method not in METHODS:
            raise UserError(f"--method must be one of {', '.join(METHODS)}, got {method!r}")
        if max_gap is not None and max_gap <= 0:
            raise UserError("--max-gap must be positive (seconds)")
        truth = None
        if sim:
            take, truth = _sim_gaps(take_path, frames, hidden, seed)
        elif take_path is None:
            raise UserError("give TAKE (a labelled .c3d or .csv), or --sim for a simulated "
                            "one")
        else:
            take = read_take(take_path, rate)
        ms = open_set(markerset) if markerset is not None else None
        before = int((~take.visible).sum())
        filled, counts = fill(take, ms, max_gap, method)
        write_take(out, filled)
        after = int((~filled.visible).sum())
        typer.echo(f"wrote {out}: filled {before - after} of {before} missing samples "
                   f"({', '.join(f'{k} {v}' for k, v in counts.items() if v) or 'no gaps'})")
        figures = {"missing_before": before, "missing_after": after,
                   "gaps_by_method": counts}
        if truth is not None:
            figures["truth"] = _fill_score(take, filled, truth)
        if json_path is not None:
            write_json(json_path, figures)

    _register_skeleton(app)


def _register_skeleton(app: typer.Typer) -> None:
    @app.command("skeleton")
    def skeleton_cmd(
        rom: Annotated[Path, typer.Argument(
            help="Range-of-motion take, labelled (.c3d or .csv).")],
        out: Annotated[Path, typer.Option("--out", help="Skeleton to write (.toml).")],
        model: Annotated[str, typer.Option(
            "--model", help="Segment model: cmu41 (shipped) or a model TOML.")] = "cmu41",
        bvh: Annotated[Path | None, typer.Option(
            "--bvh", help="Also export this take's motion as BVH.")] = None,
        motion: Annotated[Path | None, typer.Option(
            "--motion", help="Take to export with --bvh (default: the ROM take).")] = None,
        rate: RateOpt = None,
        json_path: JsonOpt = None,
    ) -> None:
        """Joint centres by sphere fits, bone lengths; export motion as BVH.

        Reads a labelled range-of-motion take (and optionally a take to export)."""
        from daemon.analysis.skeleton import export_bvh, fit_skeleton, load_model
        from daemon.formats.c3dio import read_take

        if out.suffix.lower() != ".toml":
            raise UserError(f"--out must be a .toml file, got {out.name}")
        if bvh is not None and bvh.suffix.lower() != ".bvh":
            raise UserError(f"--bvh must end in .bvh, got {bvh.name}")
        take = read_take(rom, rate)
        mdl = load_model(model)
        skel = fit_skeleton(take, mdl)
        skel.save(out)
        rows = [[j.name, j.parent or "-", round(1000 * j.rms_m, 1),
                 round(1000 * float(skel.bone_length_m(j.name)), 1)] for j in skel.joints]
        print_table(rows, ["joint", "parent", "fit_rms_mm", "bone_mm"])
        typer.echo(f"wrote {out}: {len(skel.joints)} joints")
        if bvh is not None:
            mtake = read_take(motion, rate) if motion is not None else take
            export_bvh(bvh, skel, mtake)
            typer.echo(f"wrote {bvh}: {mtake.n_frames} frames")
        if json_path is not None:
            write_json(json_path, {"joints": {j.name: {"parent": j.parent,
                                                       "fit_rms_mm": 1000 * j.rms_m}
                                              for j in skel.joints}})


def _sim_gaps(take_path: Path | None, frames: int, hidden: float, seed: int):
    """--sim: the simulator's person walking with spans of its markers hidden (the take to
    fill), and the whole walk (where the hidden markers were: for the score only)."""
    from calibkit.synthetic import person
    from daemon.formats.c3dio import Take
    from daemon.synthetic.labelling import hide_spans

    if take_path is not None:
        raise UserError(f"give TAKE or --sim, not both (got {take_path} and --sim)")
    if frames < 60:
        raise UserError(f"--frames must be at least 60 (half a second), got {frames}")
    if not 0.0 < hidden <= 0.5:
        raise UserError(f"--hidden is a share of marker-frames, above 0 and up to 0.5; got "
                        f"{hidden}")
    walk = person.walk_circle(frames, 120.0, noise_m=0.0003, seed=seed)
    truth = Take(list(walk.labels), walk.markers_m, 120.0)
    return hide_spans(truth, hidden, seed=seed), truth


def _fill_score(gapped, filled, truth) -> dict:
    """--sim: the filled samples against the truth (mm), gross (> 20 mm) counted apart."""
    import numpy as np

    new = ~gapped.visible & filled.visible
    err = 1000.0 * np.linalg.norm(filled.xyz_m[new] - truth.xyz_m[new], axis=1)
    figures = {"filled": int(new.sum()),
               "error_mm_rms": float(np.sqrt(np.mean(err ** 2))) if len(err) else None,
               "error_mm_median": float(np.median(err)) if len(err) else None,
               "error_mm_p95": float(np.percentile(err, 95)) if len(err) else None,
               "gross_over_20mm": int((err > 20.0).sum())}
    if len(err):
        typer.echo(f"against the simulator's truth: {figures['filled']} filled samples, "
                   f"{figures['error_mm_rms']:.2f} mm RMS (median "
                   f"{figures['error_mm_median']:.2f}, p95 {figures['error_mm_p95']:.2f}), "
                   f"{figures['gross_over_20mm']} over 20 mm")
    return figures
