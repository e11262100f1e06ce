"""`mocapd label`'s run: points read (a CSV, a C3D, a recording, or the simulator's person),
labelled with a marker set, written, and its figures.

Apart from daemon/commands/markerset_cmd.py, whose handler reads the options and calls
run_label, so that a handler stays a page of options and a few checks.
"""

from __future__ import annotations

from pathlib import Path

import typer

from calibkit.clitools import Progress, write_json
from calibkit.core.errors import UserError
from daemon.commands.points_input import bad_rows_json, read_points_for_command


def run_label(out: Path, points: Path | None, markerset: str | None, rig_path: Path | None,
              start_frames: int, start_labels: Path | None, rate: float | None,
              json_path: Path | None, strict: bool, sim: bool, frames: int, hidden: float,
              ghosts: int, sim_seed: int) -> None:
    """`mocapd label`'s run once its options are read: the points read (or simulated), the
    start labels checked, the take labelled and written, its figures said and saved."""
    import numpy as np

    from daemon.formats.c3dio import Points, read_take, write_take
    from daemon.labelling.markerset import open_set
    from daemon.labelling.offline import (
        duplicate_trajectories,
        label_take,
        merged_points,
    )

    ms = open_set(markerset or "sim_person")
    rate_hz = rate
    first_labels = None
    twins: list = []
    bad = None
    truth = None
    if sim:
        pts, truth, sim_take = _sim_points(points, rig_path, ms, frames, hidden, ghosts,
                                           sim_seed)
        rate_hz = sim_take.rate_hz
        if start_frames and start_labels is None:
            first_labels = sim_take  # its first frames stand for a user's hand labels
    elif points is None:
        raise UserError("give POINTS (a points CSV, a C3D or a .mcrec recording), or --sim "
                        "for a simulated take")
    elif not points.exists():
        raise UserError(f"{points} does not exist")
    elif points.suffix.lower() == ".c3d":
        labelled = read_take(points)
        pts = Points.from_take(labelled)
        twins = duplicate_trajectories(labelled)
        rate_hz = rate_hz or labelled.rate_hz
        if start_frames and start_labels is None:
            first_labels = labelled
    elif points.suffix.lower() == ".csv":
        pts, bad = read_points_for_command(points, strict)
    elif points.suffix.lower() == ".mcrec":
        pts, rec_rate = _triangulated(points, rig_path)
        rate_hz = rate_hz or rec_rate
    else:
        raise UserError(f"{points}: POINTS must be a .csv (frame,x,y,z), a .c3d or a "
                        f".mcrec recording")
    if rig_path is not None and not sim and points.suffix.lower() != ".mcrec":
        raise UserError("--rig is for a .mcrec recording; these points are 3D already")
    if start_labels is not None:
        first_labels = read_take(start_labels, rate_hz)
    if start_frames and first_labels is None:
        raise UserError("--start-frames needs --start-labels LABELLED.c3d|csv with those "
                        "frames")
    if first_labels is not None:
        missing = [n for n in ms.labels if n not in first_labels.labels]
        if missing:
            raise UserError(f"the --start-labels take lacks marker(s) "
                            f"{', '.join(missing[:5])} of the marker set")
    if not len(pts.frame):
        raise UserError(f"{points} holds no points")
    rate_hz = rate_hz or 120.0
    n_frames = len(np.unique(pts.frame))
    progress = Progress("label", n_frames)
    take, conf, labels = label_take(pts, ms, rate_hz, first_labels, start_frames, progress)
    progress.update(n_frames)
    progress.finish()
    write_take(out, take)
    for name, twin, together in twins:
        typer.echo(f"note: {points.name} stores one marker twice: {twin} lies within 6 mm "
                   f"of {name} in {together} frames; labelled as one")
    seen = take.visible
    n_pts = len(pts.frame)
    merged = merged_points(labels)
    figures = {"frames": int(take.n_frames), "points": n_pts,
               "labelled": int(seen.sum()),
               "unlabelled_points": int(n_pts - seen.sum() - merged),
               "confidence_median": float(np.median(conf)) if len(conf) else 0.0,
               "low_confidence_frames": int((conf < 0.5).sum()),
               "merged_points": merged,
               "duplicate_trajectories": [list(t[:2]) for t in twins],
               "per_marker_seen": {n: int(c) for n, c in zip(ms.labels, seen.sum(0),
                                                               strict=True)}}
    if bad is not None:
        figures["bad_rows"] = bad_rows_json(bad)
    twice = f" ({merged} as a duplicate)" if merged else ""
    typer.echo(f"wrote {out}: {take.n_frames} frames, {int(seen.sum()) + merged} of {n_pts} "
               f"points labelled{twice}, median confidence "
               f"{figures['confidence_median']:.2f}")
    if truth is not None:
        figures["truth"] = _sim_score(pts, truth, labels, start_frames)
    if json_path is not None:
        write_json(json_path, figures)


def _triangulated(path: Path, rig_path: Path | None):
    """A recording's blobs matched across cameras and triangulated, as `calibkit
    triangulate` does: (Points, the recording's frame rate or None)."""
    import numpy as np

    from calibkit.core.camera import Rig
    from calibkit.core.recording import load_observations
    from calibkit.vision.correspondence import match_frames
    from daemon.formats.c3dio import Points

    if rig_path is None:
        raise UserError(f"{path}: a recording holds 2D blobs; give --rig RIG.toml to "
                        f"triangulate them")
    rig = Rig.load(rig_path)
    obs, _ = load_observations(path, rig)
    if len(obs) == 0:
        raise UserError(f"{path}: holds no blobs")
    progress = Progress("triangulate", len(obs.frames()))
    found = match_frames(rig, obs, progress=progress.update)
    progress.finish(f"{len(found.frame)} points")
    return Points(found.frame.astype(np.int64), found.xyz), (float(obs.fps) if obs.fps
                                                              else None)


def _sim_points(points: Path | None, rig_path: Path | None, ms, frames: int, hidden: float,
                ghosts: int, seed: int):
    """--sim: the simulator's person walking a circle (calibkit.synthetic.person), `hidden`
    of its marker-frames hidden in spans and `ghosts` stray points a frame. Returns the
    unlabelled points, each point's true marker in the set's order (-1: a ghost; for the
    score only) and the labelled take (for --start-frames: a user's hand labels)."""
    import numpy as np

    from calibkit.synthetic import person
    from daemon.formats.c3dio import Take
    from daemon.synthetic.labelling import hide_spans, points_with_ghosts

    if points is not None:
        raise UserError(f"give POINTS or --sim, not both (got {points} and --sim)")
    if rig_path is not None:
        raise UserError("--rig is for a .mcrec recording; --sim makes 3D points")
    if frames < 60:
        raise UserError(f"--frames must be at least 60 (half a second), got {frames}")
    if not 0.0 <= hidden <= 0.5:
        raise UserError(f"--hidden is a share of marker-frames, 0 to 0.5; got {hidden}")
    if ghosts < 0:
        raise UserError(f"--ghosts must not be negative, got {ghosts}")
    walk = person.walk_circle(frames, 120.0, noise_m=0.0003, seed=seed)
    missing = [n for n in walk.labels if n not in ms.labels]
    if missing:
        raise UserError(f"--sim labels the simulated person: the set {ms.name} lacks its "
                        f"marker(s) {', '.join(missing[:5])}; use --markerset sim_person")
    take = Take(list(walk.labels), walk.markers_m, 120.0)
    seen = hide_spans(take, hidden, seed=seed) if hidden > 0 else take
    pts, marker = points_with_ghosts(seen, ghosts, seed=seed)
    to_set = np.array([ms.labels.index(n) for n in walk.labels])
    truth = np.where(marker >= 0, to_set[np.maximum(marker, 0)], -1)
    return pts, truth, seen


def _sim_score(pts, truth, labels, start_frames: int) -> dict:
    """--sim: the labels against the truth, after the start frames (given, not earned)."""
    from daemon.synthetic.labelling import score

    s = score(pts, truth, labels, start_frames)
    typer.echo(f"against the simulator's truth: {100 * s['correct']:.2f}% of "
               f"{s['marker_frames']} marker-points named right ({100 * s['unlabelled']:.2f}% "
               f"left unlabelled), {100 * s['ghosts_rejected']:.1f}% of {s['ghosts']} ghosts "
               "left out")
    return s
