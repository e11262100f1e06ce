"""Reloading a running daemon's configuration (SIGHUP, `mocapd reload`): checked in full first.

Apart from daemon.service.daemon, which runs the daemon: a reload reads and checks the new
file, its marker set, detectors and rig before anything changes, then swaps rigid bodies,
outputs, labeller and (for a recalibrated rig or new gates) the tracker between two frames;
a bad file is logged and the running configuration kept.
"""

from __future__ import annotations

import logging
from pathlib import Path

from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from daemon.config.mocapd import Config, load_config
from daemon.process.notify import sd_notify
from daemon.service.outputs import make_publishers
from daemon.tracking.tracker import Tracker

log = logging.getLogger("mocapd")


def reload(daemon) -> bool:
    """Re-read the configuration: rigid bodies and outputs change, the stream goes on.
    A bad file is logged and the running configuration kept."""
    sd_notify("RELOADING=1")
    try:
        path = daemon.config.path
        new = daemon.extend(load_config(path)) if path else daemon.config
        key = daemon._set_key(new)
        labelling = daemon._labeller(new) if key != daemon._markerset_key else daemon.labelling
        detectors = daemon._reload_detectors(new)
        rig = reload_rig(daemon, new)
        tracker_config = daemon._tracker_config(new, rig or daemon.rig)
    except UserError as exc:
        log.error("reload failed, keeping the running configuration: %s", exc)
        sd_notify("READY=1")
        return False
    bodies = daemon._bodies(new)
    daemon._warn_alike(bodies)
    if daemon.evaluator is not None:
        daemon.pipeline.run_idle()  # frames tracked so far are scored against the old
        daemon.evaluator.set_bodies(bodies)
    try:
        publishers = make_publishers(new, bodies, labelling.ms if labelling else None,
                                     daemon.handle, daemon.hub)
    except UserError as exc:
        log.error("reload failed, keeping the running configuration: %s", exc)
        if labelling is not daemon.labelling and labelling is not None:
            labelling.close()
        sd_notify("READY=1")
        return False
    changes = {} if labelling is daemon.labelling else {"labeller": labelling}
    if changes and daemon.labelling is not None:
        daemon.labelling.close()  # a start still searching on its thread stops
    daemon.labelling, daemon._markerset_key = labelling, key
    if rig is not None or tracker_config != daemon.tracker_config:
        # tracks start afresh on the new rig or gates, between two frames
        changes["tracker"] = Tracker(rig or daemon.rig, tracker_config)
        daemon.rig, daemon.tracker_config = rig or daemon.rig, tracker_config
    daemon.pipeline.replace(bodies=bodies, publishers=publishers, **changes)
    for src, det in detectors:
        src.detector = det
    daemon.config = new
    log.info("configuration reloaded: %d rigid bodies, %d outputs%s", len(bodies),
             len(new.udp) + len(new.serial) + len(new.mavlink),
             "" if labelling is None else f", marker set {labelling.set_name}")
    sd_notify("READY=1")
    return True


def reload_rig(daemon, new: Config) -> Rig | None:
    """The rig a reloaded configuration names, read and checked in full before anything
    changes: None when it is the running one. A live rig may change its calibration, not
    its cameras (they are open); a simulated or replayed run keeps its rig."""
    same_text = new.rig is None or daemon._rig_text == read_bytes(new.rig)
    if new.rig == daemon.config.rig and same_text:
        return None
    rig = daemon._rig(new)  # read in full: a missing or broken file fails the reload
    if daemon.scene is not None:
        log.warning("reload: the rig file changed, but a --sim or --replay run keeps the "
                    "rig it started with (restart mocapd to use %s)", new.rig)
        return None
    if rig is None:
        raise UserError("rig: a live daemon needs one; the reloaded configuration has none")
    old = [(c.name, tuple(c.size)) for c in daemon.rig]
    now = [(c.name, tuple(c.size)) for c in rig]
    if now != old:
        raise UserError(f"{new.rig}: its cameras ({', '.join(n for n, _ in now)}) are not "
                        f"the running rig's ({', '.join(n for n, _ in old)}) with their "
                        "image sizes; restart mocapd to change cameras")
    daemon._rig_text = read_bytes(new.rig)
    return rig


def read_bytes(path: Path | None) -> bytes | None:
    """A file's bytes (None: no file, or unreadable: the loader then says why)."""
    try:
        return None if path is None else Path(path).read_bytes()
    except OSError:
        return None
