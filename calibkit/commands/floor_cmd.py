"""`calibkit floor`: put a calibrated rig's world frame on the floor (z up, floor at z = 0)
from an L-frame, the wand laid on the floor, or points on the floor."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from calibkit.clitools import parse_floats, print_table, write_json
from calibkit.core.errors import UserError


def register(app: typer.Typer) -> None:
    @app.command("floor")
    def floor_cmd(
        out: Annotated[Path, typer.Option("--out", help="The rig file to write.")],
        rig_path: Annotated[Path | None, typer.Option(
            "--rig", help="The calibrated rig (e.g. from calibkit wand).")] = None,
        source: Annotated[Path | None, typer.Option(
            "--from", help="A recording (.mcrec or .csv) of what lies on the floor.")] = None,
        kind: Annotated[str, typer.Option(
            "--kind", help="lframe (3 markers), wand (laid in 2+ places) or plane "
                           "(points on the floor).")] = "lframe",
        long_m: Annotated[float, typer.Option(
            "--long", help="L-frame: corner to long-arm marker, metres (+x).")] = 0.5,
        short_m: Annotated[float, typer.Option(
            "--short", help="L-frame: corner to short-arm marker, metres (+y).")] = 0.3,
        marker_height: Annotated[float, typer.Option(
            "--marker-height", help="Marker centres above the floor, metres.")] = 0.007,
        spacing: Annotated[str, typer.Option(
            "--spacing", help="wand: marker positions along it, metres.")] = "0,0.2,0.5",
        json_path: Annotated[Path | None, typer.Option(
            "--json", help="Write the transform and figures as JSON.")] = None,
        use_sim: Annotated[bool, typer.Option(
            "--sim", help="Simulate a rig in a wrong frame and an L-frame on the floor; the "
                          "true rig goes to NAME.truth.toml.")] = False,
        noise_px: Annotated[float, typer.Option("--noise-px", help="--sim: noise.")] = 0.1,
        seed: Annotated[int, typer.Option("--seed", help="--sim: random seed.")] = 0,
    ) -> None:
        """Set the world frame from the floor."""
        import numpy as np

        from calibkit.calibrate import floor
        from calibkit.core.camera import Rig, rotation_from_rvec, rvec_from_rotation
        from calibkit.core.observations import Truth
        from calibkit.core.recording import load_observations
        from calibkit.synthetic import sim
        from calibkit.synthetic.runs import truth_rig_path

        if long_m <= 0 or short_m <= 0 or abs(long_m - short_m) < 0.02:
            raise UserError("--long and --short must be positive and differ by at least "
                            "2 cm (the arms tell x from y)")
        lframe = floor.LFrame(long_m, short_m, marker_height)
        truth_rig = None
        if use_sim:
            if source is not None or rig_path is not None:
                raise UserError("--sim makes its own rig and recording: drop --rig/--from")
            truth_rig = sim.make_rig(6, 4.0, seed=seed)
            rng = np.random.default_rng(seed)
            rig = floor.transform_rig(truth_rig, rotation_from_rvec(rng.normal(0, 0.3, 3)),
                                      rng.normal(0, 1.0, 3))
            pts = lframe.points()
            n = 30
            truth = Truth(np.repeat(np.arange(n), 3), np.tile(np.arange(3), n),
                          np.tile(pts, (n, 1)))
            obs = sim.observe(truth_rig, truth, noise_px=noise_px, seed=seed)
            kind = "lframe"
        else:
            if rig_path is None or source is None:
                raise UserError("give --rig RIG.toml and --from REC (or --sim)")
            rig = Rig.load(rig_path)
            obs, _ = load_observations(source, rig)
            from calibkit.core.pairing import pair_frames

            obs = pair_frames(obs).obs  # per-camera frame counters: paired by capture time
        A, b = floor.world_from_recording(rig, obs, kind, lframe,
                                          parse_floats(spacing, "--spacing"))
        result = floor.transform_rig(rig, A, b)
        result = Rig(result.cameras, dict(rig.quality),
                     {**rig.meta, "world_frame": f"floor ({kind})"})
        result.save(out)
        figures = {"kind": kind, "rotation_rvec": rvec_from_rotation(A), "translation_m": b,
                   "cameras": {c.name: c.centre for c in result}}
        rows = [[c.name, *(round(float(v), 4) for v in c.centre)] for c in result]
        if truth_rig is not None:
            truth_rig.save(truth_rig_path(out))
            err = np.linalg.norm(result.centres() - truth_rig.centres(), axis=1) * 1000
            figures["centre_error_mm"] = err
            rows = [r + [round(float(e), 2)] for r, e in zip(rows, err, strict=True)]
        print_table(rows, ["camera", "x_m", "y_m", "z_m"]
                    + (["error_mm"] if truth_rig is not None else []))
        if json_path is not None:
            write_json(json_path, figures)
        typer.echo(f"wrote {out}" + (f" (true rig in {truth_rig_path(out)})"
                                     if truth_rig is not None else ""))
