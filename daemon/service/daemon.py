"""The daemon as a service: builds the pipeline from a configuration and runs it.

Set-up (the rig, cameras or the simulator, bodies, outputs, labelling), the run loops
(live, paced by the cameras; or as fast as the tracker goes), signals (SIGTERM and SIGINT
stop cleanly: publishers flush their queues and close their ports; SIGHUP reloads), the
control socket's requests (daemon.service.control), systemd's notify messages
(daemon.process.notify), status and the run's figures.
"""

from __future__ import annotations

import dataclasses
import logging
import signal
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from calibkit.cameras import missing_plugins
from calibkit.core.blas import one_blas_thread
from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.vision.correspondence import match_frame
from calibkit.vision.detect import DetectorConfig, detect
from calibkit.vision.gates import correspondence_config, rig_residual, tracker_gates
from calibkit.vision.masks import load_mask
from daemon.capture.pipeline import (
    CaptureThread,
    FrameSet,
    Multiplexer,
    Pipeline,
    latency_figures,
    retire,
)
from daemon.capture.sources import DetectCamera, ReplayCamera, ReplayScene
from daemon.config.mocapd import Config, default_runtime_dir
from daemon.config.zenoh import is_remote
from daemon.nodes.remote import make_hub
from daemon.process import heap
from daemon.process.notify import sd_notify, watchdog_interval_s
from daemon.process.realtime import raise_priority, restore_normal
from daemon.publish.recorder import RecorderPublisher
from daemon.service import control_requests, report, sim_bodies
from daemon.service.control import ControlServer
from daemon.service.outputs import make_publishers
from daemon.service.reload import Reloads, read_bytes
from daemon.service.reload import reload as reload_config
from daemon.synthetic import virtual
from daemon.synthetic.evaluator import Evaluator
from daemon.synthetic.labelling import LabelScore
from daemon.synthetic.scene import SimCamera, SimScene
from daemon.tracking.rigid import alike_bodies
from daemon.tracking.tracker import Tracker
from daemon.tracking.tracker_kernel import refine_step

if TYPE_CHECKING:
    from daemon.labelling.live import LiveLabeller

log = logging.getLogger("mocapd")
OPEN_GRACE_NS = 1_000_000_000  # after the start, sets wait this long for cameras not open yet


# ---- the daemon ------------------------------------------------------------------------------

def _paced(cfg: Config) -> bool:
    """Whether frames come at the cameras' pace (live, or a simulation or replay in real
    time) rather than as fast as the tracker goes."""
    if cfg.sim is not None:
        return cfg.sim.realtime
    return cfg.replay.realtime if cfg.replay is not None else True


class Daemon:
    """Builds the pipeline from a Config and runs it until stopped (or for a while)."""

    def __init__(self, config: Config, truth_rig: Rig | None = None,
                 extend=None) -> None:
        """`extend(config) -> config` re-applies command-line additions after a reload."""
        self.config = config
        self.extend = extend or (lambda c: c)
        self.stop_event = threading.Event()
        self.reload_event = threading.Event()  # SIGHUP's: the frame loop asks for the reload
        self.reloads = Reloads(self)
        self.reload_error: str | None = None  # why the last reload failed
        self.recorder: RecorderPublisher | None = None
        self.started_ns = time.monotonic_ns()
        self.scene: SimScene | None = None
        self.evaluator: Evaluator | None = None
        self.labelling: LiveLabeller | None = None
        self.label_score: LabelScore | None = None
        self.captures: list[CaptureThread] = []
        self.scheduling = "normal"  # what the live run's threads run at (daemon.process.realtime)
        self._learned: tuple[str, list] | None = None  # --sim: bodies defined live (toml, defs)
        self.learned_path: Path | None = None
        self.rig = self._rig(config)
        self._rig_text = read_bytes(config.rig)  # a reload swaps the rig only when it changed
        self._truth_rig = truth_rig
        self.control: ControlServer | None = None
        self.view = None  # the live web view (daemon.view.link.ViewLink), when asked for
        self.hub = None  # capture nodes over Zenoh (daemon.nodes.remote), with [zenoh]

    @staticmethod
    def _rig(config: Config) -> Rig | None:
        if config.rig is not None:
            try:
                return Rig.load(config.rig)
            except FileNotFoundError:
                raise UserError(f"rig file {config.rig} not found") from None
        if config.sim is None:
            where = f"{config.path}: " if config.path else ""
            raise UserError(f"{where}rig: no rig given; set rig = \"rig.toml\" in the "
                            "configuration, pass --rig, or use --sim")
        return None

    # ---- lifecycle -------------------------------------------------------------------------

    def setup(self, n_frames: int | None = None) -> None:
        cfg = self.config
        self.live_sources = None
        self.evaluator = None
        if cfg.sim is not None:
            # nodes make the scene at its default length (n_frames shapes the motion):
            # the daemon's must be the same one to score them
            self.scene = SimScene(cfg.sim, self.rig, self._truth_rig,
                                  n_frames if cfg.zenoh is None else None)
            self.rig = self.scene.rig
        elif cfg.replay is not None:
            self.scene = ReplayScene(cfg.replay.path, self.rig)
        self.hub = make_hub(cfg, self.rig.names)
        if self.scene is None and (cfg.cameras or self.hub is not None):
            self.live_sources = self._cameras(cfg)
        elif self.scene is None:
            where = f"{cfg.path}: " if cfg.path else ""
            raise UserError(f"{where}camera: no input; add [[camera]] tables, a [replay] "
                            "recording, or use --sim")
        self.tracker_config = self._tracker_config(cfg)
        bodies = self._bodies(cfg)
        self._warn_alike(bodies)
        if cfg.sim is not None and cfg.sim.score:  # against the scene's bodies, by shape
            # greedy sets mix instants by design (moved to one time): not checked
            # (the ledger of cameras served by nodes is in the nodes: instants not checked)
            self.evaluator = Evaluator(self.scene, bodies=bodies,
                                       check_instants=cfg.mode == "triggered"
                                       and not (self.hub and self.hub.cameras))
        self.labelling, self._markerset_key = self._labeller(cfg), self._set_key(cfg)
        # with the simulated person: the labelled markers scored against its truth
        self.label_score = (LabelScore(self.scene) if getattr(self.scene, "person_labels", None)
                            else None)
        # the scorers read results only: run while the frame loop waits for a set
        scorers = [h for h in (self.evaluator, self.label_score) if h is not None]
        publishers = make_publishers(cfg, bodies, self._markerset(), self.handle, self.hub)
        self.pipeline = Pipeline(self.rig, self.tracker_config, cfg.rigid, bodies,
                                 publishers, labeller=self.labelling, idle_hooks=scorers)
        self._warm_up()
        runtime = cfg.runtime_dir or default_runtime_dir()
        self.control = ControlServer(runtime, self.handle)
        self.control.open()
        if self._learned is not None:
            log.info("%s", self._learn_note)
            sim_bodies.write_learned(self, runtime)
        if self.hub is not None:
            self.hub.start()
        for p in self.pipeline.publishers:
            p.start()
        if self.view is not None:  # its own process, fed the newest result per hook call
            self.view.attach(self)

    def _tracker_config(self, cfg: Config, rig: Rig | None = None):
        """The tracker's configuration with its pixel gates (and its correspondence's, for
        new markers) following the rig's recorded residual, calibkit.vision.gates' rule, except
        the gates the configuration file sets; unchanged when the rig records none."""
        try:
            residual = rig_residual(rig or self.rig)
        except UserError as exc:
            raise UserError(f"{cfg.rig or 'rig'}: {exc}") from None
        if residual is None:
            log.debug("tracker gates: fixed (the rig records no residual)")
            return cfg.tracker
        t = cfg.tracker
        names = ("gate_px", "outlier_px", "two_view_px", "ambiguous_px")
        changes = tracker_gates(residual.px, {n: getattr(t, n) for n in names if hasattr(t, n)},
                                cfg.tracker_keys)
        changes["correspondence"] = correspondence_config(residual.px, t.correspondence)
        log.info("tracker gates follow the residual %s: %s", residual,
                 ", ".join(f"{k} {v:.2f}" for k, v in changes.items() if k != "correspondence"))
        return dataclasses.replace(t, **changes)

    def _cameras(self, cfg: Config) -> list:
        """Capture sources for the configured cameras; a camera whose plugin library is
        missing is reported and skipped, the rest run."""
        names = self.rig.names
        out = []
        for cam in cfg.cameras:
            if is_remote(cam.source):
                continue  # served by a node: the hub's
            if cam.name not in names:
                raise UserError(f"{cfg.path}: camera {cam.name!r} is not in the rig "
                                f"({', '.join(names)})")
            missing = missing_plugins([cam.source.partition(":")[0]])
            if missing:
                log.error("%s: skipped: plugin %s is not installed", cam.name, missing[0])
                continue
            out.append(DetectCamera(cam.name, names.index(cam.name), cam.source,
                                    self._detector(cam), cam.fps,
                                    device_stamps=cam.timestamps == "device"))
        out += self.hub.sources() if self.hub is not None else []
        if not out:
            raise UserError("no camera can be opened (see the messages above)")
        return out

    def _detector(self, cam):
        """A [[camera]] table's detection settings, its mask read and checked against the
        camera's size (UserError for a bad one)."""
        mask = None if cam.mask is None else load_mask(cam.mask, self.rig[cam.name].size)
        return DetectorConfig(threshold=cam.threshold, min_area=cam.min_area,
                              max_area=cam.max_area, mask=mask)

    def _reload_detectors(self, cfg: Config) -> list:
        """(source, new settings) for each live camera whose detection settings changed (a
        mask is read again: its file may have been redrawn under the same name); applied
        by assigning them, which the capture thread reads each frame."""
        if not self.live_sources:
            return []
        old = {c.name: c for c in self.config.cameras}
        new = {c.name: c for c in cfg.cameras}
        return [(src, self._detector(new[src.name])) for src in self.live_sources
                if src.name in new and (new[src.name] != old.get(src.name)
                                        or new[src.name].mask is not None)]  # redrawn?

    def _warm_up(self) -> None:
        """Run the correspondence once on a frame's blobs before READY: its compiled kernels
        load on first use (about a second), which would otherwise stall the first frames."""
        # the tracker's kernel: one track in front of the rig, one blob per camera
        warm = Tracker(self.rig, self.tracker_config)
        warm.set_tracks(np.array([1]), np.zeros((1, 3)))
        warm.update(np.arange(len(self.rig)), np.zeros((len(self.rig), 2)) + 100.0, 0)
        a = warm.arrays
        refine_step(np.tile(np.eye(3), (1, 1, 1)), np.zeros((1, 3)), np.zeros((1, 3, 3)),
                    np.full((1, 3, len(self.rig)), -1, dtype=np.int64), np.zeros((1, 2)),
                    a.R, a.t, a.fx, a.fy, a.cx, a.cy, a.skew, a.dist, np.ones(1, dtype=bool))
        if self.scene is None:  # live cameras: detection has compiled kernels too
            image = np.full((64, 64), 10, np.uint8)
            image[30:34, 30:34] = 200
            for src in self.live_sources:
                if hasattr(src, "detector"):
                    detect(image, src.detector)
            match_frame(self.rig, np.arange(len(self.rig)), np.zeros((len(self.rig), 2)) + 100.0)
            return
        samples = [self.scene.sample(c, 0, 0) for c in range(len(self.rig))]
        camera = np.concatenate([np.full(len(s.uv), s.camera) for s in samples])
        match_frame(self.rig, camera, np.concatenate([s.uv for s in samples]))

    def _labeller(self, cfg: Config) -> LiveLabeller | None:
        """The labelling stage for the configured marker set (None: no marker set)."""
        if cfg.markerset is None:
            return None
        # imported only with a marker set: the labelling modules (scipy.stats among them)
        # would cost every start a second
        from daemon.labelling.live import LiveLabeller

        # deferred on purpose: loads SciPy's optimisers, SciPy's sparse graphs only where used
        from daemon.labelling.live import load as load_markerset

        fps = self.scene.fps if self.scene is not None else cfg.fps
        return LiveLabeller(load_markerset(cfg.markerset), fps, str(cfg.markerset),
                            background=_paced(cfg))

    @staticmethod
    def _set_key(cfg: Config):
        """What identifies the configured marker set: its path and its file's bytes (a
        reload with the same, unchanged set keeps the labeller and its tracking)."""
        if cfg.markerset is None:
            return None
        try:
            return str(cfg.markerset), cfg.markerset.read_bytes()
        except OSError:
            return str(cfg.markerset), None

    def _markerset(self):
        return None if self.labelling is None else self.labelling.ms

    def _bodies(self, cfg: Config) -> list:
        """The configuration's rigid bodies; with --sim and none configured, the scene's
        bodies defined live, once, as a user would (daemon.service.sim_bodies)."""
        if cfg.bodies or cfg.sim is None or not cfg.sim.define_bodies \
                or not isinstance(self.scene, SimScene):
            return list(cfg.bodies)
        if self._learned is None:
            self._learned = sim_bodies.learn_bodies(self, cfg)
        return list(self._learned[1])

    def _warn_alike(self, bodies) -> None:
        for a, b in alike_bodies(bodies, self.config.rigid.distance_tol_m):
            log.warning("rigid bodies %s and %s have nearly the same marker distances; they "
                        "may be confused", a, b)

    def install_signals(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        self._old_signals = {
            signal.SIGTERM: signal.signal(signal.SIGTERM, lambda *_: self.stop_event.set()),
            signal.SIGINT: signal.signal(signal.SIGINT, lambda *_: self.stop_event.set()),
            signal.SIGHUP: signal.signal(signal.SIGHUP, lambda *_: self.reload_event.set())}

    def restore_signals(self) -> None:
        """Put back the handlers there were before (a daemon run inside another program)."""
        for sig, handler in getattr(self, "_old_signals", {}).items():
            signal.signal(sig, handler)
        self._old_signals = {}

    def run(self, frames: int | None = None, duration_s: float | None = None,
            progress=None) -> dict:
        """Track until stopped, `frames` frames or `duration_s` seconds; the figures."""
        cfg = self.config
        fps = cfg.sim.fps if cfg.sim is not None else cfg.fps
        n_scene = frames or (int(duration_s * fps) + 10 if duration_s else None)
        realtime = _paced(cfg)
        # BLAS on the calling thread only: the daemon's matrices are small, and OpenBLAS's
        # workers, started with numpy at normal priority, would make a real-time thread wait
        # for them behind every other process on the machine (calibkit.core.blas)
        blas = one_blas_thread()
        # before any thread starts, so that they all inherit it; a batch run stays normal
        self.scheduling = (raise_priority(cfg.realtime_priority) if realtime
                           else "normal (as fast as possible)")
        try:
            self.setup(n_scene)
            try:
                if realtime:
                    self._run_live(frames, duration_s, progress)
                else:
                    self._run_fast(frames, duration_s, progress)
            finally:
                self.pipeline.run_idle()  # the scorers see every frame
                self.shutdown()
        finally:
            restore_normal()
            heap.release()
            blas.restore_original_limits()
        return self.figures()

    def _run_fast(self, frames, duration_s, progress) -> None:
        """A simulation or replay as fast as the tracker goes: one loop, no threads. The
        simulated cameras run in virtual time (daemon.synthetic.virtual): each opens, counts,
        stamps and drops frames on its own, and their samples go through the multiplexer
        (the configured mode) as a live run's do; fast means no sleeping, not no pairing. A replay's
        frames are already paired: frame i of every camera makes set i."""
        scene = self.scene
        period = 1e9 / scene.fps
        total = frames or (int(duration_s * scene.fps) if duration_s else None)
        replay = isinstance(scene, ReplayScene)
        if replay:
            total = min(total or scene.n_frames, scene.n_frames)
            sets = (FrameSet(i, round(i * period), time.monotonic_ns(),
                             [scene.sample(c, i, round(i * period))
                              for c in range(len(self.rig)) if not scene.dropped(c, i)])
                    for i in range(total))
        else:
            cfg = self.config

            def make_mux(n, mode, fps, timeout_frames, **kw):  # the configured mode
                self.mux = Multiplexer(n, cfg.mode, fps, cfg.timeout_frames,
                                       tolerance_frames=cfg.pair_tolerance, **kw)
                return self.mux

            seconds = None
            if cfg.mode == "greedy" and not frames and duration_s:  # a set per camera report:
                seconds, total = duration_s, None  # the duration is the cameras' time
            sets = virtual.frame_sets(scene, seconds, make_mux=make_mux)
        sd_notify("READY=1")
        log.info("tracking %d cameras (%s, as fast as possible)", len(self.rig),
                 "replay" if replay else "simulated, paired by the multiplexer")
        done = 0
        for fs in sets:
            if self.stop_event.is_set() or (total is not None and done >= total):
                break
            fs.arrival_ns = time.monotonic_ns()  # handed over now (virtual arrivals aside)
            self.pipeline.process(fs)
            self.pipeline.run_idle()
            done += 1
            self._tick(progress)

    def _run_live(self, frames, duration_s, progress) -> None:
        scene = self.scene
        cfg = self.config
        t0 = time.monotonic_ns() + 50_000_000
        if self.live_sources is not None:
            sources, fps = self.live_sources, cfg.fps
        else:
            kind = ReplayCamera if isinstance(scene, ReplayScene) else SimCamera
            # cameras served by nodes take the simulated rig's frames on one trigger grid
            # from the machine's monotonic zero (daemon.nodes.node); the local ones join it
            remote = {s.camera: s for s in self.hub.sources()} if self.hub else {}
            sources = [remote.get(c) or kind(scene, c, 0 if remote and kind is SimCamera else t0)
                       for c in range(len(self.rig))]
            fps = scene.fps
        # a camera served by a node is its own capture (daemon.nodes.remote.RemoteCapture)
        self.captures = [src if hasattr(src, "deliver") else CaptureThread(src, None)
                         for src in sources]
        index = {src.camera: k for k, src in enumerate(sources)}  # rig camera -> thread
        n = len(self.rig)
        grace_ns = t0 + OPEN_GRACE_NS

        def connected():
            """The cameras a new set waits for: those delivering, and for a moment after the
            start those not open yet (a rig opening together); a camera that opens later
            joins the sets once it delivers."""
            ok = np.zeros(n, dtype=bool)
            early = time.monotonic_ns() < grace_ns
            for cam, k in index.items():
                c = self.captures[k]
                ok[cam] = c.connected or (early and c.frames == 0)
            return ok

        self.mux = Multiplexer(n, cfg.mode, fps, cfg.timeout_frames, connected=connected,
                               tolerance_frames=cfg.pair_tolerance, origin_ns=t0)
        heap.freeze_startup()  # a full collection would stop every thread for tens of ms
        for cap in self.captures:
            cap.push = self.mux.push
            cap.on_open = self.mux.reset_camera
            cap.start()
        sd_notify("READY=1")
        log.info("tracking %d cameras (%s at %.0f fps, %s; scheduling %s)", len(sources),
                 "live" if self.live_sources else "replay" if isinstance(scene, ReplayScene)
                 else "simulated", fps, cfg.mode, self.scheduling)
        end = None if duration_s is None else t0 + int(duration_s * 1e9)
        while not self.stop_event.is_set():
            if end is not None and time.monotonic_ns() >= end:
                break
            if frames is not None and self.pipeline.stats.frames >= frames:
                break
            idle = self.pipeline.idle_pending
            fs = self.mux.next(0.0 if idle else 0.1)
            if fs is not None:
                self.pipeline.process(fs)
            elif idle:  # no set waiting: the scorers' turn, one frame at a time
                self.pipeline.run_idle(1)
                # let the capture threads in: this loop holds the interpreter lock while
                # it works through a backlog, and a thread waiting for it would otherwise
                # wait out the 5 ms switch interval with its camera's frame in hand
                time.sleep(0)
                continue
            elif not any(c.thread.is_alive() for c in self.captures):
                log.info("every source has ended")
                break
            self._tick(progress)

    def _tick(self, progress) -> None:
        """Per frame: watchdog, status line, a pending reload."""
        now = time.monotonic()
        if not hasattr(self, "_next_beat"):
            self._next_beat, self._next_status = now, now
        if now >= self._next_beat:
            interval = watchdog_interval_s()
            if interval:
                sd_notify("WATCHDOG=1")
            self._next_beat = now + (interval or 1.0)
        if now >= self._next_status:
            lat = latency_figures(self.pipeline.stats.latency)
            med = lat["median_ms"] or 0.0
            sd_notify(f"STATUS={self.pipeline.stats.rate_hz():.0f} fps, latency "
                      f"{med:.2f} ms, {self.pipeline.stats.valid_bodies} bodies")
            self._next_status = now + 1.0
        if self.reload_event.is_set():  # read and checked beside the frame loop
            self.reload_event.clear()
            self.reloads.ask()
        self.pipeline.apply_pending()  # a reload's swap, also while no frames come
        if progress is not None:
            progress(self.pipeline.stats.frames)

    def reload(self) -> bool:
        return reload_config(self)

    def shutdown(self) -> None:
        sd_notify("STOPPING=1")
        for cap in self.captures:
            cap.stop()
        for cap in self.captures:
            cap.join(1.0)
        if isinstance(self.scene, SimScene):
            self.scene.close()  # a live robot's command socket and truth file
        self.reloads.join(10.0)  # a reload half-built would start outputs nobody stops
        if hasattr(self, "pipeline"):
            self.pipeline.apply_pending()
            for p in self.pipeline.publishers:
                p.stop()
            retire(self.pipeline.take_retired())
        if self.recorder is not None:
            self.recorder.stop()
        if self.labelling is not None:
            self.labelling.close()
        if self.control is not None:
            self.control.close()
        if self.view is not None:
            self.view.close()
        if self.hub is not None:
            self.hub.close()
        if threading.current_thread() is threading.main_thread():
            self.restore_signals()

    # ---- control requests ------------------------------------------------------------------

    def handle(self, req: dict) -> dict:
        return control_requests.handle(self, req)

    def status(self) -> dict:
        return report.status(self)

    def figures(self) -> dict:
        return report.figures(self, sim_bodies.LEARN_FRAMES)

    def tracking_rig_note(self) -> str:
        return report.tracking_rig_note(self)

    def mux_stats(self) -> dict | None:
        return report.mux_stats(self)
