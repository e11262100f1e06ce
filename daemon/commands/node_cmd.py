"""`mocapd node`: a capture node that publishes its cameras' blobs over Zenoh."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer

from calibkit.core.errors import UserError


def register(app: typer.Typer) -> None:
    @app.command("node")
    def node(
        config: Annotated[Path | None, typer.Option(
            "--config", "-c", help="node.toml: name, [zenoh], [[camera]], [sim], [node_sim] "
                                   "(docs/nodes.md).")] = None,
        sim: Annotated[bool, typer.Option("--sim", help="Serve cameras of the simulated "
                                                        "rig.")] = False,
        name: Annotated[str | None, typer.Option("--name", help="The node's name.")] = None,
        rig: Annotated[str | None, typer.Option(
            "--rig", help="Key prefix: mocap/RIG/... (the daemon's [zenoh] rig).")] = None,
        connect: Annotated[list[str] | None, typer.Option(
            "--connect", help="Zenoh endpoint of the daemon, e.g. tcp/192.168.1.10:7447 "
                              "(repeatable).")] = None,
        listen: Annotated[list[str] | None, typer.Option(
            "--listen", help="Zenoh endpoint to listen on (repeatable).")] = None,
        cameras: Annotated[str | None, typer.Option(
            "--cameras", help="--sim: the rig's cameras this node serves: names or indices, "
                              "e.g. 0-7 or cam0,cam3.")] = None,
        sim_cameras: Annotated[int | None, typer.Option(
            "--sim-cameras", help="--sim: cameras in the simulated rig.")] = None,
        sim_fps: Annotated[float | None, typer.Option("--sim-fps")] = None,
        sim_bodies: Annotated[int | None, typer.Option("--sim-bodies")] = None,
        seed: Annotated[int | None, typer.Option("--seed")] = None,
        clock_offset_ms: Annotated[float | None, typer.Option(
            "--clock-offset-ms", help="--sim: the node's clock against this machine's.")] = None,
        clock_drift_ppm: Annotated[float | None, typer.Option(
            "--clock-drift-ppm", help="--sim: how fast the node's clock runs.")] = None,
        publish: Annotated[str | None, typer.Option(
            "--publish", help="sets: one message per trigger with all the node's cameras "
                              "(default); cameras: one message per camera frame.")] = None,
        duration: Annotated[float | None, typer.Option(
            "--duration", help="Stop after this many seconds.")] = None,
        verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Debug log.")] = False,
        realtime: Annotated[bool, typer.Option(
            "--realtime", help="Capture and publish under real-time scheduling (SCHED_RR at "
                               "node.toml's realtime_priority, else 9; the node's network one "
                               "step above); off by default.")]
        = False,
    ) -> None:
        """Open cameras, detect blobs and publish them over Zenoh to a mocapd elsewhere."""
        from daemon.commands.node_run import run_node
        from daemon.nodes.settings import PUBLISH, load_node_config
        from daemon.process.logs import setup_logging
        from daemon.publish.zenoh_session import check_endpoint, check_name

        setup_logging(verbose)
        cfg = load_node_config(config)
        if realtime and cfg.realtime_priority == 0:
            from daemon.commands.start_run import REALTIME_DEFAULT

            # capture a step below the daemon's threads, the node's network level with them
            # (daemon.nodes.node.Node.start): a node on the daemon's machine never runs its
            # detection ahead of the daemon
            cfg = replace(cfg, realtime_priority=REALTIME_DEFAULT - 1)
        try:
            if name is not None:
                cfg = replace(cfg, name=check_name(name, "--name"))
            if publish is not None:
                if publish not in PUBLISH:
                    raise ValueError(f"--publish must be one of {', '.join(PUBLISH)}, "
                                     f"got {publish!r}")
                cfg = replace(cfg, publish=publish)
            s = cfg.session
            if rig is not None or connect or listen:
                s = replace(s, rig=check_name(rig, "--rig") if rig is not None else s.rig,
                            listen=tuple(check_endpoint(e) for e in listen) if listen
                            else s.listen,
                            connect=tuple(check_endpoint(e) for e in connect) if connect
                            else s.connect)
            cfg = replace(cfg, session=s)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        run_node(cfg, sim, cameras, sim_cameras, sim_fps, sim_bodies, seed, clock_offset_ms,
                 clock_drift_ppm, duration)
