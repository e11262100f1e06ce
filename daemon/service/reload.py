"""Reloading a running daemon's configuration (SIGHUP, `mocapd reload`): checked in full first.

Apart from daemon.service.daemon, which runs the daemon: a reload reads and checks the new
file, its marker set, detectors and rig before anything changes, then swaps rigid bodies,
outputs, labeller and (for a recalibrated rig or new gates) the tracker between two frames;
a bad file is logged and the running configuration kept.
"""

from __future__ import annotations

import logging
import sys
import threading
from pathlib import Path

from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from daemon.capture.pipeline import retire
from daemon.config.mocapd import Config, load_config
from daemon.process.notify import sd_notify
from daemon.service.outputs import make_publishers
from daemon.tracking.tracker import Tracker

log = logging.getLogger("mocapd")
SWAP_WAIT_S = 2.0  # the longest a reload waits for the frame loop to swap
GAP_WAIT_S = 0.05  # the longest a reload's step waits for a frame to have gone out
RELOAD_SWITCH_S = 0.0005  # the interpreter's switch interval while a reload is built


class Reloads:
    """Reloads run one at a time on a thread beside the frame loop, which only swaps what
    they built: reading and checking a configuration, building a labeller or a tracker
    takes milliseconds to seconds that the stream must not wait for. Asking while one runs
    makes one more run after it (the file may have changed again); `wait` gives a ticket's
    outcome, for `mocapd reload` to say whether the new configuration took."""

    def __init__(self, daemon) -> None:
        self.daemon = daemon
        self._cond = threading.Condition()
        self.asked = self.done = 0
        self.outcome: tuple[bool, str | None] = (True, None)  # of the newest finished
        self._thread: threading.Thread | None = None

    def ask(self) -> int:
        """A reload is wanted: its ticket (never from a signal handler: it takes a lock)."""
        with self._cond:
            self.asked += 1
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="reload", daemon=True)
                self._thread.start()
            return self.asked

    def wait(self, ticket: int, timeout_s: float) -> tuple[bool, str | None] | None:
        """(ok, why not) of the reload that began after `ticket` was given; None: not done."""
        with self._cond:
            if not self._cond.wait_for(lambda: self.done >= ticket, timeout_s):
                return None
            return self.outcome

    def join(self, timeout_s: float) -> None:
        thread = self._thread
        if thread is not None:
            thread.join(timeout_s)

    def _run(self) -> None:
        while True:
            with self._cond:
                if self.done >= self.asked:
                    self._thread = None
                    return
                upto = self.asked
            # while this thread works the frame loop waits for the interpreter at most this
            # long each time it asks (5 ms by default: more than half a frame at 120 fps)
            interval = sys.getswitchinterval()
            sys.setswitchinterval(min(interval, RELOAD_SWITCH_S))
            try:
                ok = reload(self.daemon)
            except Exception:  # noqa: BLE001 - a bug must not end reloading for good
                log.exception("reload failed, keeping the running configuration")
                ok, self.daemon.reload_error = False, "internal error (see the log)"
            finally:
                sys.setswitchinterval(interval)
            with self._cond:
                self.done, self.outcome = upto, (ok, self.daemon.reload_error)
                self._cond.notify_all()


def reload(daemon) -> bool:
    """Re-read the configuration: rigid bodies and outputs change, the stream goes on.
    A bad file is logged and the running configuration kept. Runs beside the frame loop
    (daemon.service.daemon starts it on a thread of its own); the frame loop only swaps."""
    sd_notify("RELOADING=1")
    daemon.reload_error = None
    gap = daemon.pipeline.after_frame  # each step in the gap after a frame (a few ms each)
    try:
        path = daemon.config.path
        gap(GAP_WAIT_S)
        new = daemon.extend(load_config(path)) if path else daemon.config
        key = daemon._set_key(new)
        labelling = daemon._labeller(new) if key != daemon._markerset_key else daemon.labelling
        detectors = daemon._reload_detectors(new)
        rig = reload_rig(daemon, new)
        tracker_config = daemon._tracker_config(new, rig or daemon.rig)
    except UserError as exc:
        return _failed(daemon, exc)
    gap(GAP_WAIT_S)
    bodies = daemon._bodies(new)
    daemon._warn_alike(bodies)
    try:
        publishers = make_publishers(new, bodies, labelling.ms if labelling else None,
                                     daemon.handle, daemon.hub,
                                     running=daemon.pipeline.publishers)
    except UserError as exc:
        if labelling is not daemon.labelling and labelling is not None:
            labelling.close()
        return _failed(daemon, exc)
    changes = {} if labelling is daemon.labelling else {"labeller": labelling}
    daemon.labelling, daemon._markerset_key = labelling, key
    if rig is not None or tracker_config != daemon.tracker_config:
        # a new rig: tracks start afresh on it; new gates only: the tracks go on
        tracker = Tracker(rig or daemon.rig, tracker_config)
        tracker.carry = rig is None  # the frame loop hands the tracks over as it swaps
        changes["tracker"] = tracker
        daemon.rig, daemon.tracker_config = rig or daemon.rig, tracker_config
    if daemon.evaluator is not None:  # scored against the new bodies from the swap on
        evaluator = daemon.evaluator
        gap(GAP_WAIT_S)  # the simulator's scorer matches bodies by shape: fits, milliseconds
        matched = evaluator.match(bodies)
        changes["idle_call"] = lambda: evaluator.adopt(matched)
    gap(GAP_WAIT_S)
    for p in publishers:  # a thread's start waits for it to run: not on the frame loop
        if not p.started and not p.takes_over:
            p.start()
    last = daemon.pipeline.last_result  # new bodies found here, not in the swap's frame
    if last is not None and "tracker" not in changes:
        changes["seeds"] = daemon.pipeline.rigid.seed(bodies, last.tracks)
    daemon.pipeline.replace(bodies=bodies, publishers=publishers, **changes)
    for src, det in detectors:
        src.detector = det
    daemon.config = new
    # done once the frame loop has swapped (within a frame; it swaps while idle too), so
    # that `mocapd reload` answers with the new configuration running
    daemon.pipeline.swapped.wait(SWAP_WAIT_S)
    gap(GAP_WAIT_S)  # the swap's frame is still being tracked
    retire(daemon.pipeline.take_retired())  # the replaced outputs flush and close here
    log.info("configuration reloaded: %d rigid bodies, %d outputs%s", len(bodies),
             len(new.udp) + len(new.serial) + len(new.mavlink),
             "" if labelling is None else f", marker set {labelling.set_name}")
    sd_notify("READY=1")
    return True


def _failed(daemon, exc: UserError) -> bool:
    log.error("reload failed, keeping the running configuration: %s", exc)
    daemon.reload_error = str(exc)
    sd_notify("READY=1")
    return False


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
