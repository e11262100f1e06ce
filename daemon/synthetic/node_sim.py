"""The simulated cameras a capture node serves with `mocapd node --sim`.

The same scene, seed and cameras as the daemon's [sim] makes (at its default length, which
shapes the motion), taken on one trigger grid with trigger 0 at the machine's monotonic
zero: nodes started at different moments on one machine, or in network namespaces on it,
still take their frames together, and a daemon with the same [sim] scores them against
the same truth. The truth (the scene's ledger) stays in the node's process.
"""

from __future__ import annotations

from calibkit.core.errors import UserError
from daemon.nodes.settings import NodeConfig


def sim_sources(cfg: NodeConfig):
    """The simulated cameras this node serves, on the shared trigger grid."""
    # deferred on purpose: loads OpenCV only where used
    from daemon.synthetic.scene import SimCamera, SimScene

    if cfg.sim is None:
        raise UserError("--sim needs the simulated rig: a [sim] table in node.toml, or "
                        "--sim-cameras")
    scene = SimScene(cfg.sim)
    names = scene.rig.names
    serve = cfg.sim_cameras or tuple(names)
    unknown = [c for c in serve if c not in names]
    if unknown:
        raise UserError(f"node_sim.cameras: {', '.join(unknown)} not in the simulated rig "
                        f"({', '.join(names)})")
    return [SimCamera(scene, names.index(c), 0) for c in serve]
