"""--sim's rigid bodies defined live at the start, as a user would define them, and written out.

Apart from daemon.service.daemon, which calls these once while it sets up: each of the
scene's bodies is held still and alone, tracked with the daemon's own rig and tracker, and
defined from what was tracked; the simulator's definitions are never used.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import tomllib

from calibkit.core.errors import UserError
from calibkit.core.fileio import write_text_atomic
from daemon.capture.pipeline import Pipeline
from daemon.config.mocapd import Config, parse_config
from daemon.tracking.rigid_define import bodies_toml, learn_body

log = logging.getLogger("mocapd")

LEARN_FRAMES = 30  # --sim: frames each body is held still (as `rigid-body add`'s default)
HOLD_TRIES = 4  # --sim: places each body is held at until its definition has every marker
LEARNED_BODIES = "sim-bodies.toml"  # where (in the runtime directory) they are written


def learn_bodies(daemon, cfg: Config) -> tuple[str, list]:
    """Each of the scene's bodies held still and alone in the volume for LEARN_FRAMES
    frames (SimScene.held_alone: blobs only), tracked with this daemon's rig and
    tracker, and defined from the tracked points as `mocapd rigid-body add --from-live`
    defines one (daemon.tracking.rigid_define); named body0, body1, ... in the order held, as
    [[rigid_body]] tables read back through the configuration's checks. Never the
    simulator's definitions: the scorer matches these to its bodies by their shape."""
    started = time.monotonic()
    found = []
    want = cfg.sim.markers_per_body  # the user knows how many markers a body carries
    for k in range(len(daemon.scene.bodies_truth)):
        got, why = None, ""
        for place in range(HOLD_TRIES):  # short of markers: moved, tried again
            pipe = Pipeline(daemon.rig, daemon.tracker_config, cfg.rigid, [])
            try:
                got = learn_body(lambda fs, p=pipe: p.process(fs).tracks,
                                 daemon.scene.held_alone(k, LEARN_FRAMES, place))
            except UserError as exc:
                got, why = None, str(exc)
                continue
            if len(got) == want:
                break
            why = f"found {len(got)} markers, not {want}"
            log.debug("defining body%d live: %s; moving it and trying again", k, why)
        if got is None or len(got) != want:
            raise UserError(f"--sim: defining body{k} live failed ({why}) at "
                            f"{HOLD_TRIES} places; check the rig's calibration")
        found.append((f"body{k}", k + 1, got))
    text = bodies_toml(found)
    bodies = list(parse_config(tomllib.loads(text)).bodies)
    # logged once the outputs are checked: a start refused for them says only why
    daemon._learn_note = (f"defined {len(bodies)} rigid bodies live in "
                        f"{time.monotonic() - started:.1f} s ("
                        + ", ".join(str(len(b.markers)) for b in bodies)
                        + f" markers, each held still for {LEARN_FRAMES} frames)")
    return text, bodies


def write_learned(daemon, runtime: Path) -> None:
    """The bodies defined live, written where a user can read (and keep) them."""
    path = Path(runtime) / LEARNED_BODIES
    write_text_atomic(path, "# rigid bodies mocapd --sim defined live at its start; "
                      "copy them into your configuration to keep them\n\n"
                      + daemon._learned[0])
    daemon.learned_path = path
    log.info("rigid bodies defined live written to %s", path)
