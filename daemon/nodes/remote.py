"""The daemon's side of the nodes: remote cameras whose blobs come over Zenoh.

One NodeHub per daemon holds the Zenoh session: it pings the nodes for their clocks
(daemon.nodes.clock), hears their announcements, and hands every frame of a message (a
node's set of one trigger, or one camera's frame), its times mapped to the daemon's clock,
to its camera's capture (RemoteCapture, daemon/nodes/remote_capture.py), which pushes it to
the multiplexer as a local camera's capture thread does: the multiplexer pairs, drops and
re-joins it unchanged. A camera whose node has died goes silent and the hub's watchdog
drops it after `timeout_ms`; a node that restarts (a new boot id) ends the camera's
session at its first message, and the multiplexer starts the camera's clock afresh; a node
whose frames come more than `max_lag_ms` after it got them is behind: those frames are
dropped, and a camera with only late frames for `timeout_ms` is dropped until it catches
up. Zenoh's callbacks do no more than decode and push (the multiplexer's push never
waits for the frame loop): nothing the network does can hold up the frame loop.

A sample's `arrival_ns` is when the node got the frame, mapped to the daemon's clock: the
multiplexer's per-camera clock model (daemon.capture.clocks) then learns the camera's clock
against the node's arrivals (a USB or GigE transfer, tight), not against the network's
jitter; what the node -> daemon hop adds is counted here, per node.
"""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from collections import deque

import numpy as np

from calibkit.core.errors import UserError
from daemon.capture.sources import CameraSample
from daemon.config.zenoh import DaemonZenoh, is_remote
from daemon.nodes.clock import NodeClock
from daemon.nodes.remote_capture import RemoteCapture
from daemon.process.supervise import Supervised
from daemon.publish import zenoh_wire as wire
from daemon.publish.bad_input import BadInput
from daemon.publish.zenoh_session import all_blobs_key, all_sets_key, check_name, ping_key

log = logging.getLogger("mocapd.nodes")
PING_HZ = 20.0
WATCH_HZ = 100.0  # how often silent cameras are looked for
NODE_SILENT_S = 3.0  # a node not heard (announcements, pongs) for this long is gone
MAX_NODES = 64  # nodes remembered before the silent ones are forgotten
SESSION_CHECK_S = 0.2  # how often the session is looked at (closed under the daemon?)
REOPEN_MAX_WAIT_S = 30.0  # the back-off's ceiling between attempts to reopen it


class SessionLost(RuntimeError):
    """The daemon's Zenoh session closed while the daemon runs (its watcher reopens it)."""


class _Camera:
    """A remote camera: where its samples go (its capture, while the daemon runs)."""

    def __init__(self, name: str, index: int) -> None:
        self.name, self.index = name, index
        self.capture: RemoteCapture | None = None
        self.node = ""  # the node last heard serving it
        self.boot = -1


class _Node:
    """What the daemon knows of one node process (by its boot id)."""

    def __init__(self, name: str, boot: int) -> None:
        self.name, self.boot = name, boot
        self.clock = NodeClock()
        self.cameras: list[str] = []
        self.last_heard = time.monotonic()
        self.samples = 0
        self.waiting_clock = 0  # samples that came before its clock was known
        self.late = 0  # samples later than max_lag_ms
        # per message: the node got its newest frame -> the daemon has its frames, ns
        self.hop_ns: deque = deque(maxlen=4096)
        # per frame: the node got it -> sent it (waiting for the set's other frames too)
        self.in_node_ns: deque = deque(maxlen=4096)
        self.lag_ns = 0  # the latest sample's node arrival -> daemon


class NodeHub:
    """The daemon's Zenoh session and every remote camera's samples (see the module)."""

    def __init__(self, settings: DaemonZenoh, rig_names: list[str], remote: dict) -> None:
        """`remote`: the node's name of each remote camera (its key) -> the rig's name."""
        self.settings = settings
        self.rig = settings.session.rig
        self.cameras = {k: _Camera(n, rig_names.index(n)) for k, n in remote.items()}
        self.nodes: dict[int, _Node] = {}  # by boot id
        self.restarts: dict[str, int] = {}  # node name -> times it came back with a new boot
        self.lock = threading.Lock()
        self.session = None
        self.unknown = 0  # blobs of cameras the daemon does not take
        self.bad = 0  # messages that failed to decode
        # ... by kind, each logged once a minute: junk on the bus must not flood the log
        self.refused = BadInput(log, "zenoh")
        self._restart_said: dict[str, float] = {}
        self._stop = threading.Event()
        self._seq = 0
        self._captures: list[RemoteCapture] | None = None
        self._warned: set = set()
        self.supervised: list[Supervised] = []  # the pinger and the session's watcher
        self.reopened = 0  # times the session was opened again after it closed
        self._said_reopen = -1e18  # when a reopening was last logged

    # ---- lifecycle ---------------------------------------------------------------------------

    def start(self) -> None:
        # a clock exchange is stamped by Python on both ends: a thread stamping t1 or t4
        # that then waits out the interpreter's 5 ms switch interval behind the frame loop
        # makes one leg of the exchange longer than the other (an offset error of tens of
        # us on a busy daemon); a short interval keeps the wait to a fraction of that
        sys.setswitchinterval(min(sys.getswitchinterval(), 1e-4))
        s = self.settings.session
        self._open()
        # supervised (daemon.process.supervise): a pinger that raises is restarted, and a
        # session that closes under the daemon is reopened, with a back-off while that fails
        self._pinger = Supervised("node-clocks", self._ping_loop, stopping=self._stop.is_set)
        self._watch = Supervised("zenoh-session", self._watch_session,
                                 stopping=self._stop.is_set, reset=self._reopen,
                                 max_wait_s=REOPEN_MAX_WAIT_S, expected=(SessionLost,))
        self.supervised = [self._pinger, self._watch]
        for sup in self.supervised:
            sup.start()
        log.info("zenoh: %d remote cameras on mocap/%s/ (%s)", len(self.cameras), self.rig,
                 ", ".join(s.listen + s.connect))

    def _open(self) -> None:
        """Open the session and declare the clock pings and the four subscriptions."""
        # deferred on purpose: loads Zenoh only where used
        import zenoh

        session = self.settings.session.open()
        try:
            self._ping = session.declare_publisher(
                ping_key(self.rig), express=True,
                congestion_control=zenoh.CongestionControl.DROP,
                priority=zenoh.Priority.REAL_TIME)
            self._subs = [
                session.declare_subscriber(all_blobs_key(self.rig), self._on_blobs),
                session.declare_subscriber(all_sets_key(self.rig), self._on_sets),
                session.declare_subscriber(f"mocap/{self.rig}/_nodes/*/clock", self._on_pong),
                session.declare_subscriber(f"mocap/{self.rig}/_nodes/*/announce",
                                           self._on_announce)]
        except Exception:
            session.close()
            raise
        self.session = session

    def _watch_session(self) -> None:
        """Return at the stop; raise SessionLost when the session closed under the daemon
        (Zenoh closed it, or a bug did): the supervisor then reopens it (`_reopen`)."""
        while not self._stop.wait(SESSION_CHECK_S):
            session = self.session
            if session is not None and session.is_closed() and not self._stop.is_set():
                raise SessionLost("the Zenoh session closed")

    def _reopen(self) -> None:
        """A new session in place of the closed one; the Zenoh output finds it when its own
        publishers fail (its worker reopens against `self.session`). A failure (the port
        still taken) raises: the supervisor counts it and tries again after its back-off."""
        old = self.session
        if old is not None and not old.is_closed():
            return  # not lost after all (a failure of the watcher itself)
        self._open()
        self.reopened += 1
        now = time.monotonic()
        if now - self._said_reopen >= 60.0:  # a session closing over and over: once a minute
            self._said_reopen = now
            log.warning("zenoh: session reopened (%d so far)", self.reopened)

    def close(self) -> None:
        self._stop.set()
        for sup in self.supervised:
            sup.join(2.0)
        if self.session is not None:
            self.session.close()
            self.session = None

    def _ping_loop(self) -> None:
        """Clock pings at PING_HZ, and the remote cameras' watchdog at WATCH_HZ."""
        k = 0
        while not self._stop.wait(1.0 / WATCH_HZ):
            now = time.monotonic_ns()
            for cap in self._captures or ():
                cap.check(now)
            k += 1
            if k % round(WATCH_HZ / PING_HZ):
                continue
            self._seq += 1
            try:
                self._ping.put(wire.encode_ping(self._seq, time.monotonic_ns()))
            except Exception as exc:  # noqa: BLE001 - a closing session
                log.debug("ping: %s", exc)

    # ---- Zenoh's callbacks -------------------------------------------------------------------

    def _node(self, name: str, boot: int) -> _Node:
        node = self.nodes.get(boot)
        if node is None:
            with self.lock:
                node = self.nodes.get(boot)
                if node is None:
                    old = [n for n in self.nodes.values() if n.name == name]
                    if old:
                        self.restarts[name] = self.restarts.get(name, 0) + 1
                        if self._say_restart(name):
                            log.warning("node %s restarted (boot %08x; %d restarts so far)",
                                        name, boot, self.restarts[name])
                        for o in old:
                            del self.nodes[o.boot]
                    else:
                        log.info("node %s joined (boot %08x)", name, boot)
                    if len(self.nodes) >= MAX_NODES:  # forget the silent: a stream of
                        now = time.monotonic()        # made-up boot ids cannot grow this
                        for o in [n for n in self.nodes.values()
                                  if now - n.last_heard > NODE_SILENT_S]:
                            del self.nodes[o.boot]
                    node = self.nodes[boot] = _Node(name, boot)
        node.last_heard = time.monotonic()
        return node

    def _say_restart(self, name: str) -> bool:
        """A node's restarts said once a minute: two processes claiming one name (or a
        forger) flip its boot id at every message, and each flip is counted, not logged."""
        now = time.monotonic()
        if now - self._restart_said.get(name, -1e18) < 60.0:
            return False
        if len(self._restart_said) >= 4 * MAX_NODES:
            self._restart_said.clear()
        self._restart_said[name] = now
        return True

    def _refuse(self, kind: str, detail: object = "") -> None:
        self.bad += 1
        self.refused(kind, detail)

    def _safely(self, what: str, handle, sample) -> None:
        """A callback's work: whatever a message holds, nothing escapes into Zenoh's
        thread (which would print a traceback per message and drop the rest)."""
        try:
            handle(sample)
        except wire.WireError as exc:
            self._refuse(f"{what} message that does not decode", exc)
        except Exception as exc:  # noqa: BLE001 - a message no check foresaw
            self._refuse(f"{what} message that failed ({type(exc).__name__})", exc)

    def _on_pong(self, sample) -> None:
        self._safely("clock", self._pong, sample)

    def _on_announce(self, sample) -> None:
        self._safely("announcement", self._announce, sample)

    def _on_blobs(self, sample) -> None:
        self._safely("blobs", self._blobs, sample)

    def _on_sets(self, sample) -> None:
        self._safely("blob-sets", self._sets, sample)

    def _pong(self, sample) -> None:
        t4 = time.monotonic_ns()
        boot, _, t1, t2, t3 = wire.decode_pong(sample.payload.to_bytes())
        name = str(sample.key_expr).split("/")[-2]
        self._node(name, boot).clock.add(t1, t2, t3, t4)

    def _announce(self, sample) -> None:
        try:
            msg = json.loads(sample.payload.to_bytes())
            name, boot, cameras = str(msg["node"]), int(msg["boot"]), msg["cameras"]
            if not isinstance(cameras, list) or not 0 <= boot < 2 ** 32:
                raise TypeError("cameras not a list, or boot not a 32-bit id")
        except (ValueError, KeyError, TypeError, OverflowError) as exc:
            raise wire.WireError(f"{type(exc).__name__}: {exc}") from None
        node = self._node(name, boot)
        node.cameras = [str(c) for c in cameras]
        now = time.monotonic()
        for cam in node.cameras:
            others = [n.name for n in list(self.nodes.values()) if n is not node
                      and n.name != node.name and cam in n.cameras
                      and now - n.last_heard < NODE_SILENT_S]
            if cam not in self.cameras:
                self._warn_once(("unknown", node.name, cam),
                                "node %s serves camera %s, which this daemon does not take "
                                "(not in the rig, or not a zenoh: camera)", node.name, cam)
            elif others:
                self._warn_once(("twice", cam), "camera %s is served by nodes %s and %s: "
                                "give each camera one node", cam, node.name, others[0])

    def _warn_once(self, key, message: str, *args) -> None:
        if key in self._warned:
            return
        if len(self._warned) >= 4 * MAX_NODES:  # made-up names: once a minute from here
            self.refused("announcement warning beyond the first ones", message % args)
            return
        self._warned.add(key)
        log.warning(message, *args)

    def _blobs(self, sample) -> None:
        """One camera's frame (a node with `publish = "cameras"`)."""
        name = str(sample.key_expr).split("/")[-2]
        self._take(((name, wire.decode_blobs(sample.payload.to_bytes())),))

    def _sets(self, sample) -> None:
        """The frames of one trigger from all of a node's cameras: decoded as arrays, their
        times mapped in one call, and handed to the multiplexer in one push (one lock and
        one wake-up of the frame loop per node per trigger, not per camera)."""
        m = wire.decode_sets_arrays(sample.payload.to_bytes())
        if not m.names:
            return
        node = self.nodes.get(m.boot)
        if node is None or not node.clock.ready:
            if node is not None:
                node.waiting_clock += len(m.names)
            return
        has = time.monotonic_ns()
        table = m.table
        times = node.clock.to_daemon_array(np.concatenate([table["t_ns"], table["arrival_ns"]]))
        count = len(m.names)
        t_ns, arrival = times[:count].tolist(), times[count:].tolist()
        node.in_node_ns.extend((m.sent_ns - table["arrival_ns"]).tolist())
        batches: dict = {}  # push -> the samples for it (one multiplexer: one batch)
        a = 0
        for k, (name, index, device, fid, b) in enumerate(zip(
                m.names, table["index"].tolist(), table["device_time_ns"].tolist(),
                table["device_frame_id"].tolist(), m.ends, strict=True)):
            cam = self.cameras.get(name)
            if cam is None:
                self.unknown += 1
            else:
                node.samples += 1
                cap = cam.capture
                if cap is not None:
                    s = CameraSample(cam.index, index, t_ns[k], arrival[k], m.uv[a:b],
                                     m.area[a:b], m.peak[a:b], device, fid)
                    accept = getattr(cap, "accept", None)
                    if accept is None:  # a capture of another shape: one at a time
                        cap.deliver(s, node, has)
                    elif accept(s, node, has):
                        batches.setdefault(cap.push, []).append(s)
            a = b
        for push, samples in batches.items():
            many = getattr(getattr(push, "__self__", None), "push_many", None)
            if many is not None and getattr(push, "__name__", "") == "push":
                many(samples)
            else:
                for s in samples:
                    push(s)
        ready = (node.clock.to_daemon(m.sent_ns) if m.flags & wire.SET_SHORT
                 else max(arrival))
        node.hop_ns.append(time.monotonic_ns() - ready)

    def _take(self, frames) -> None:
        """A message's frames, their times mapped to the daemon's clock, to their cameras'
        captures; its hop (the node got its newest frame, or sent a short set -> the
        daemon has them all)."""
        node = self.nodes.get(frames[0][1].boot)
        if node is None or not node.clock.ready:
            if node is not None:
                node.waiting_clock += len(frames)
            return
        to_daemon = node.clock.to_daemon
        has = time.monotonic_ns()
        for name, m in frames:
            cam = self.cameras.get(name)
            if cam is None:
                self.unknown += 1
                continue
            node.samples += 1
            node.in_node_ns.append(m.sent_ns - m.arrival_ns)
            cap = cam.capture
            if cap is not None:
                cap.deliver(CameraSample(cam.index, m.index, to_daemon(m.t_ns),
                                         to_daemon(m.arrival_ns), m.uv, m.area, m.peak,
                                         m.device_time_ns, m.device_frame_id), node, has)
        m = frames[0][1]
        # a set that left short waited for a late camera on purpose (set_wait_ms): what
        # the link and the daemon add is counted from when it left, the wait is the
        # frames' in-node time (and a set whose late frame follows was not complete before)
        ready = m.sent_ns if m.flags & wire.SET_SHORT else max(f.arrival_ns for _, f in frames)
        node.hop_ns.append(time.monotonic_ns() - to_daemon(ready))

    # ---- figures -----------------------------------------------------------------------------

    def status(self) -> list[dict]:
        """Per node: its cameras, clock (offset, drift, round trip) and hop latency."""
        now = time.monotonic()
        out = []
        for node in list(self.nodes.values()):
            hop = np.asarray(node.hop_ns, dtype=np.float64) * 1e-6
            in_node = np.asarray(node.in_node_ns, dtype=np.float64) * 1e-6
            st = node.clock.status()
            out.append({
                "name": node.name, "boot": f"{node.boot:08x}",
                "alive": now - node.last_heard < NODE_SILENT_S,
                "cameras": node.cameras, "restarts": self.restarts.get(node.name, 0),
                "offset_ms": st["offset_ms"], "offset_at_ns": st["at_ns"],
                "drift_ppm": st["drift_ppm"],
                "rtt_ms": st["rtt_ms"], "rtt_min_ms": st["rtt_min_ms"],
                "clock_exchanges": st["exchanges"], "samples": node.samples,
                "late": node.late, "waiting_for_clock": node.waiting_clock,
                "lag_ms": node.lag_ns * 1e-6,
                "hop_median_ms": float(np.median(hop)) if len(hop) else None,
                "hop_p99_ms": float(np.percentile(hop, 99)) if len(hop) else None,
                "in_node_median_ms": float(np.median(in_node)) if len(in_node) else None,
                "in_node_p99_ms": float(np.percentile(in_node, 99)) if len(in_node)
                else None})
        return sorted(out, key=lambda n: n["name"])

    def sources(self) -> list[RemoteCapture]:
        """A capture for every remote camera, in the rig's order (made once: each is the
        camera's capture for the daemon's run)."""
        if self._captures is None:
            self._captures = sorted((RemoteCapture(self, k) for k in self.cameras),
                                    key=lambda s: s.camera)
        return self._captures


def make_hub(cfg, rig_names: list[str]) -> NodeHub | None:
    """The daemon's hub for a configuration with [zenoh] (None without): the cameras whose
    source is "zenoh:<camera>", and with `cameras = "announced"` every rig camera that has
    no [[camera]] table (with [sim]: every simulated camera not served that way)."""
    if cfg.zenoh is None:
        return None
    where = f"{cfg.path}: " if cfg.path else ""
    if cfg.sim is not None and not cfg.sim.realtime:
        raise UserError(f"{where}zenoh: cameras served by nodes run in real time; drop --fast")
    remote = {}
    for cam in cfg.cameras:
        if not is_remote(cam.source):
            continue
        if cam.name not in rig_names:
            raise UserError(f"{where}camera {cam.name!r} is not in the rig "
                            f"({', '.join(rig_names)})")
        key = cam.source.partition(":")[2] or cam.name
        try:
            check_name(key, "camera")
        except ValueError as exc:
            raise UserError(f"{where}camera {cam.name!r}: source: {exc}") from None
        remote[key] = cam.name
    if cfg.zenoh.cameras == "announced":
        configured = set() if cfg.sim is not None else {c.name for c in cfg.cameras}
        configured |= set(remote.values())
        remote.update({n: n for n in rig_names if n not in configured})
    return NodeHub(cfg.zenoh, rig_names, remote)
