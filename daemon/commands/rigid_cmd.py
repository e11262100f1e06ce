"""`mocapd rigid-body add NAME --from-live` and `mocapd rigid-body list`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from calibkit.clitools import HELP_MARKUP, parse_floats
from calibkit.core.errors import UserError
from daemon.service.live_bodies import append_body, body_from_markers, capture_snapshots

# daemon.config.mocapd (the tracker, rigid bodies and their numba kernels) is imported where it
# is used, deferred on purpose: every mocapd command imports this module to register its
# commands, and loading it costs 0.2-0.3 s of CPU that `mocapd label` does not need. The
# work the live view shares (defining a body, appending it) is in daemon.service.live_bodies.

rigid_app = typer.Typer(help="Rigid-body definitions in the configuration.",
                        no_args_is_help=True, rich_markup_mode=HELP_MARKUP)
ConfigOpt = Annotated[Path, typer.Option("--config", help="The mocapd.toml to edit.")]


def register(app: typer.Typer) -> None:
    app.add_typer(rigid_app, name="rigid-body")

    @rigid_app.command("add")
    def add(
        name: Annotated[str, typer.Argument(help="The body's name.")],
        config: ConfigOpt,
        from_live: Annotated[bool, typer.Option(
            "--from-live", help="Take the markers the running daemon sees now.")] = False,
        body_id: Annotated[int | None, typer.Option("--id", help="Streaming id.")] = None,
        frames: Annotated[int, typer.Option(
            "--frames", help="Frames of tracked markers to define the body from (hold it "
                             "still).")] = 30,
        near: Annotated[str | None, typer.Option(
            "--near", help="Only markers within --radius of X,Y,Z (metres).")] = None,
        radius: Annotated[float, typer.Option("--radius", help="Metres.")] = 0.3,
        runtime_dir: Annotated[Path | None, typer.Option("--runtime-dir")] = None,
        reload: Annotated[bool, typer.Option(
            "--reload/--no-reload", help="Ask the daemon to reload afterwards.")] = True,
    ) -> None:
        """Define a rigid body from the free markers the daemon tracks over --frames frames
        (clustered: a marker is a cluster seen in most of them); the body's frame has its
        origin at their centroid and the world's axes.

        Reads the markers a running daemon tracks, through its control socket (`mocapd start
        --sim` runs one on a simulated rig), and the configuration file it writes to."""
        import numpy as np

        from daemon.config.mocapd import load_config  # deferred: see above
        from daemon.service.control import request
        from daemon.tracking.rigid_define import body_from_snapshots

        if not from_live:
            raise UserError("give --from-live (place the body alone in the volume), or "
                            "write its [[rigid_body]] table in the configuration by hand")
        cfg = load_config(config) if config.exists() else None
        if cfg is not None and any(b.name == name for b in cfg.bodies):
            raise UserError(f"{config}: a rigid body called {name!r} exists already")
        if not 1 <= frames <= 10000:
            raise UserError(f"--frames must be between 1 and 10000, got {frames}")
        centre = None
        if near is not None:
            centre = np.array(parse_floats(near, "--near"))
            if centre.shape != (3,):
                raise UserError(f"--near takes X,Y,Z, got {near!r}")
        snapshots = capture_snapshots(lambda: request(runtime_dir, {"cmd": "markers"}),
                                      frames, centre, radius)
        free = body_from_snapshots(snapshots)
        if not 3 <= len(free) <= 8:
            raise UserError(f"the daemon sees {len(free)} markers not on a body"
                            f"{' near ' + near if near else ''}; a new body needs 3 to 8 "
                            "(use --near X,Y,Z --radius R to pick them)")
        if body_id is None:
            body_id = max((b.id for b in cfg.bodies), default=0) + 1 if cfg else 1
        append_body(config, name, body_id, body_from_markers(free))
        typer.echo(f"added rigid body {name!r} (id {body_id}, {len(free)} markers) to {config}")
        if reload:
            answer = request(runtime_dir, {"cmd": "reload"})
            typer.echo("mocapd: still reloading (see the log)" if answer.get("pending")
                       else "mocapd: configuration reloaded")

    @rigid_app.command("list")
    def list_bodies(config: ConfigOpt) -> None:
        """The rigid bodies a configuration defines, with their closest distance gap.

        Reads a configuration file (mocapd.toml)."""
        import numpy as np

        from daemon.config.mocapd import load_config  # deferred: see above
        from daemon.service.console import print_table

        cfg = load_config(config)
        rows = []
        for b in cfg.bodies:
            d = np.sort(b.distances[np.triu_indices(len(b.markers), 1)])
            gap = float(np.min(np.diff(d))) * 1000 if len(d) > 1 else float("nan")
            rows.append([b.name, b.id, len(b.markers), round(float(d.min()) * 1000, 1),
                         round(float(d.max()) * 1000, 1), round(gap, 1)])
        if not rows:
            typer.echo(f"{config}: no rigid bodies")
            return
        print_table(rows, ["name", "id", "markers", "min_dist_mm", "max_dist_mm",
                           "min_gap_mm"])
