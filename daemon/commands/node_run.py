"""`mocapd node`'s run: the simulated or live cameras a node serves, its clock, and the node
run until stopped.

Apart from daemon/commands/node_cmd.py, whose handler reads the options into the node's
configuration, so that a handler stays a page of options and a few checks.
"""

from __future__ import annotations

import signal
from dataclasses import replace

from calibkit.core.errors import UserError


def run_node(cfg, sim: bool, cameras: str | None, sim_cameras: int | None,
             sim_fps: float | None, sim_bodies: int | None, seed: int | None,
             clock_offset_ms: float | None, clock_drift_ppm: float | None,
             duration: float | None) -> None:
    """`mocapd node`'s run once its configuration is read: with --sim the simulated rig's
    cameras (its options over node.toml's [sim]) on a clock offset and drifting as asked,
    else the configured cameras; the node runs until SIGTERM, SIGINT or --duration."""
    from daemon.config.mocapd import SimConfig
    from daemon.nodes.node import Node, NodeTime, live_sources
    from daemon.nodes.settings import parse_camera_list
    from daemon.synthetic.node_sim import sim_capture, sim_sources

    clock, capture = NodeTime(), None
    if sim:
        sc = cfg.sim or SimConfig()
        sc = replace(sc, **{k: v for k, v in (("cameras", sim_cameras), ("fps", sim_fps),
                                              ("bodies", sim_bodies), ("seed", seed))
                            if v is not None})
        if not 2 <= sc.cameras <= 32:
            raise UserError(f"--sim-cameras must be between 2 and 32, got {sc.cameras}")
        cfg = replace(cfg, sim=sc)
        if cameras is not None:
            try:
                cfg = replace(cfg, sim_cameras=parse_camera_list(
                    cameras, [f"cam{i}" for i in range(sc.cameras)]))
            except ValueError as exc:
                raise UserError(f"--cameras: {exc}") from None
        offset = cfg.clock_offset_ms if clock_offset_ms is None else clock_offset_ms
        drift = cfg.clock_drift_ppm if clock_drift_ppm is None else clock_drift_ppm
        if abs(drift) > 1000:
            raise UserError(f"--clock-drift-ppm must be within +-1000, got {drift}")
        clock = NodeTime(round(offset * 1e6), drift)
        sources, capture = sim_sources(cfg), sim_capture
    else:
        sources = live_sources(cfg)
    n = Node(cfg, sources, clock, capture)
    signal.signal(signal.SIGTERM, lambda *_: n.stop_event.set())
    signal.signal(signal.SIGINT, lambda *_: n.stop_event.set())
    n.run(duration)
