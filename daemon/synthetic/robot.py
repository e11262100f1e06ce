"""A simulated differential-drive robot driven live: wheel commands in over UDP, its markers
into the simulated cameras at every trigger, its true path to the scorers.

Why live: the rest of the scene is computed before the run, but a robot that goes where a
program steers it cannot be. At each trigger the robot's state is integrated up to that
instant from the commands that have arrived, its markers are projected into every camera
as the scene's other bodies are (`sim.observe`: the same noise, dropout and merging of its
own overlapping blobs), and the daemon gets those blobs and nothing else: it defines and
identifies the robot's body as any other.

The model is a unicycle (x, y, heading) whose forward speed v and turn rate omega follow
the commanded ones through a dead time and a first-order lag, as a robot's motor
controllers and drive train do:

    v(t) -> v_cmd(t - delay_s) with time constant tau_s   (omega alike)

integrated exactly between events (a command taking effect, the watchdog), the position by
sub-steps of at most 1 ms. A command is the ASCII datagram "V OMEGA" (m/s, rad/s) sent to
127.0.0.1:port, clipped to the configured limits; it takes effect delay_s after the kernel
received it. With no command for COMMAND_TIMEOUT_S the robot's firmware stops it (zero
command), so a program that ends leaves the robot standing.
"""

from __future__ import annotations

import logging
import math
import socket
import threading
import time
from collections import OrderedDict
from pathlib import Path

import numpy as np

from calibkit.core.errors import UserError
from calibkit.core.observations import Truth
from calibkit.synthetic import sim
from daemon.config.mocapd import SimConfig, SimRobot
from daemon.publish.arrival_stamps import receive_stamped, stamp_arrivals

log = logging.getLogger("mocapd")

COMMAND_TIMEOUT_S = 0.5  # no command for this long: the robot stops
ROBOT_MARKER_BASE = 3000  # the robot's truth marker ids start here
PLATE_HEIGHT_M = 0.15  # its markers' plate, above the floor
PLATE_SIZE_M = 0.1  # markers within this of the plate's centre (a 20 cm robot)
SUBSTEP_NS = 1_000_000  # position sub-steps at most this long
HISTORY = 1 << 15  # triggers of state and blobs kept for the scorers
TRUTH_HEADER = "t_ns,x_m,y_m,yaw_rad,v_m_s,omega_rad_s,v_cmd_m_s,omega_cmd_rad_s\n"


def parse_command(data: bytes) -> tuple[float, float] | None:
    """(v, omega) from a command datagram "V OMEGA"; None if it is not one."""
    try:
        parts = data.decode("ascii").split()
        v, w = float(parts[0]), float(parts[1])
    except (UnicodeDecodeError, ValueError, IndexError):
        return None
    if len(parts) != 2 or not (math.isfinite(v) and math.isfinite(w)):
        return None
    return v, w


class Dynamics:
    """The unicycle with delayed, lagged speeds: commands in, state integrated to a time.
    Pure (no clock, no socket): `command` queues what arrived, `advance` integrates."""

    def __init__(self, cfg: SimRobot, t_ns: int) -> None:
        self.cfg = cfg
        self.delay_ns = round(cfg.delay_s * 1e9)
        self.timeout_ns = round(COMMAND_TIMEOUT_S * 1e9)
        x, y, yaw_deg = cfg.start
        self.t_ns = t_ns
        self.x, self.y, self.yaw = float(x), float(y), math.radians(yaw_deg)
        self.v = self.w = 0.0
        self.v_cmd = self.w_cmd = 0.0  # the command acting now
        self.acting_since = None  # when it took effect (None: the watchdog's zero)
        self.pending: list[tuple[int, float, float]] = []  # (takes effect, v, w), in order

    def command(self, arrival_ns: int, v: float, w: float) -> None:
        c = self.cfg
        v = min(max(v, -c.max_speed_m_s), c.max_speed_m_s)
        w = min(max(w, -c.max_turn_rad_s), c.max_turn_rad_s)
        at = max(arrival_ns + self.delay_ns, self.t_ns)
        if self.pending and at < self.pending[-1][0]:
            at = self.pending[-1][0]  # datagrams are acted on in the order they came
        self.pending.append((at, v, w))

    def advance(self, t_ns: int) -> None:
        """Integrate to t_ns (no-op for a time already passed)."""
        while self.t_ns < t_ns:
            nxt = t_ns
            if self.pending:
                nxt = min(nxt, self.pending[0][0])
            if self.acting_since is not None:
                nxt = min(nxt, self.acting_since + self.timeout_ns)
            if nxt > self.t_ns:
                self._coast(nxt - self.t_ns)
                self.t_ns = nxt
            while self.pending and self.pending[0][0] <= self.t_ns:
                at, self.v_cmd, self.w_cmd = self.pending.pop(0)
                self.acting_since = at
            if self.acting_since is not None and \
                    self.t_ns >= self.acting_since + self.timeout_ns:
                self.v_cmd = self.w_cmd = 0.0
                self.acting_since = None

    def _coast(self, dt_ns: int) -> None:
        """dt under the acting command: speeds exactly (first order), the heading exactly,
        the position by midpoint sub-steps."""
        tau = self.cfg.tau_s
        n = max(1, -(-dt_ns // SUBSTEP_NS))
        h = dt_ns * 1e-9 / n
        decay = math.exp(-h / tau)
        gain = tau * (1.0 - decay)  # integral over a step of the speed's approach
        for _ in range(n):
            dv, dw = self.v - self.v_cmd, self.w - self.w_cmd
            yaw1 = self.yaw + self.w_cmd * h + dw * gain
            dist = self.v_cmd * h + dv * gain
            mid = 0.5 * (self.yaw + yaw1)
            self.x += dist * math.cos(mid)
            self.y += dist * math.sin(mid)
            self.yaw = yaw1
            self.v = self.v_cmd + dv * decay
            self.w = self.w_cmd + dw * decay

    def state(self) -> tuple[float, ...]:
        return self.x, self.y, self.yaw, self.v, self.w, self.v_cmd, self.w_cmd


def pose_matrix(x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """The robot body's (R, t): turned by yaw about z, its marker plate at PLATE_HEIGHT_M."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), \
        np.array([x, y, PLATE_HEIGHT_M])


class LiveRobot:
    """The robot in a live simulated capture: its body (markers and truth ids), the command
    socket, its state at every trigger, the blobs the cameras see of it, and its truth."""

    def __init__(self, sim_cfg: SimConfig, rig, offsets_ns, body_id: int,
                 other_layouts: list[np.ndarray]) -> None:
        self.cfg = sim_cfg.robot
        self.sim_cfg, self.rig, self.offsets_ns = sim_cfg, rig, offsets_ns
        self.period_ns = 1e9 / sim_cfg.fps
        k = sim_cfg.markers_per_body
        existing = [np.sort(np.linalg.norm(m[:, None] - m[None], axis=2)[np.triu_indices(
            len(m), 1)]) for m in other_layouts]
        layout = sim._body_layout(k, PLATE_SIZE_M, existing,
                                  np.random.default_rng(sim_cfg.seed + 9))
        self.body = sim.SimBody("robot", body_id, layout, np.zeros((0, 4, 4)),
                                ROBOT_MARKER_BASE + np.arange(k))
        self.lock = threading.Lock()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind(("127.0.0.1", self.cfg.port))
        except OSError as exc:
            self.sock.close()
            raise UserError(f"sim.robot.port: cannot listen for the robot's commands on "
                            f"127.0.0.1:{self.cfg.port} ({exc.strerror}); pick a free "
                            "port") from None
        self.sock.setblocking(False)
        self.stamped = stamp_arrivals(self.sock)
        self.commands = self.bad_commands = 0
        self.t0_ns: int | None = None
        self._truth_file = None

    # ---- the run ------------------------------------------------------------------------

    def _reset(self, t0_ns: int) -> None:
        """A new run of triggers from t0_ns (the capture starts; the warm-up ran on 0)."""
        self.t0_ns = t0_ns
        self.dyn = Dynamics(self.cfg, t0_ns)
        self.first = 0
        self.last = -1  # the last trigger integrated
        self.states = np.zeros((HISTORY, 7))  # per trigger: Dynamics.state()
        self.blob_cache: OrderedDict[int, tuple] = OrderedDict()
        if self.cfg.truth is not None:
            if self._truth_file is not None:
                self._truth_file.close()
            try:
                self._truth_file = open(self.cfg.truth, "w", encoding="ascii")
            except OSError as exc:
                raise UserError(f"sim.robot.truth: cannot write {self.cfg.truth}: "
                                f"{exc.strerror}") from None
            self._truth_file.write(TRUTH_HEADER)
            self._truth_lines: list[str] = []

    def _drain(self) -> None:
        """Every command waiting on the socket, stamped when the kernel received it."""
        while True:
            try:
                data, _, arrived = receive_stamped(self.sock, 256)
            except OSError:  # nothing waiting (BlockingIOError), or the socket closed
                return
            cmd = parse_command(data)
            if cmd is None:
                self.bad_commands += 1
                if self.bad_commands == 1:
                    log.warning("sim robot: ignored a command that is not \"V OMEGA\": %r",
                                data[:40])
                continue
            self.commands += 1
            self.dyn.command(arrived if arrived is not None else time.monotonic_ns(), *cmd)

    def _to_trigger(self, g: int) -> None:
        """The state integrated (and recorded) up to trigger g."""
        if g <= self.last:
            return
        self._drain()
        start = self.last + 1
        if self.last < 0:
            self.first = start = g
        for k in range(start, g + 1):
            self.dyn.advance(self.t0_ns + round(k * self.period_ns))
            s = self.dyn.state()
            self.states[k % HISTORY] = s
            if self._truth_file is not None:
                self._truth_lines.append(
                    f"{self.dyn.t_ns},{s[0]:.6f},{s[1]:.6f},{s[2]:.6f},{s[3]:.6f},"
                    f"{s[4]:.6f},{s[5]:.6f},{s[6]:.6f}\n")
        self.last = g
        if self._truth_file is not None and len(self._truth_lines) >= 25:
            self._truth_file.writelines(self._truth_lines)
            self._truth_file.flush()
            self._truth_lines = []

    def blobs(self, camera: int, trigger: int, t0_ns: int):
        """(uv, area, peak, marker) camera `camera` sees of the robot at trigger `trigger`
        of the run that started at t0_ns; each trigger's blobs are made once, for every
        camera at its own instant (its phase), and kept for the scorers."""
        with self.lock:
            if t0_ns != self.t0_ns:
                self._reset(t0_ns)
            got = self.blob_cache.get(trigger)
            if got is None:
                got = self._observe(trigger)
            uv, area, peak, marker, starts = got
            s, e = starts[camera], starts[camera + 1]
            return uv[s:e], area[s:e], peak[s:e], marker[s:e]

    def known_blobs(self, camera: int, trigger: int):
        """The blobs made for a past trigger (None: never made, or forgotten), for the
        scorers: never integrates."""
        with self.lock:
            got = self.blob_cache.get(trigger)
        if got is None:
            return None
        uv, area, peak, marker, starts = got
        s, e = starts[camera], starts[camera + 1]
        return uv[s:e], area[s:e], peak[s:e], marker[s:e]

    def _observe(self, g: int):
        self._to_trigger(g)
        # a camera that opened a trigger before the first one asked for (its phase) sees
        # the robot where it started
        k = min(max(g, self.first, self.last - HISTORY + 1), self.last)
        x, y, yaw, v, w = self.states[k % HISTORY][:5]
        # the trigger's pose, and where its speeds take it a period on: each camera sees
        # the robot at its own phase between the two (sim.observe interpolates)
        h = self.period_ns * 1e-9
        ahead = (x + v * h * math.cos(yaw + w * h / 2), y + v * h * math.sin(yaw + w * h / 2),
                 yaw + w * h)
        layout = self.body.markers_body
        xyz = []
        for px, py, pyaw in ((x, y, yaw), ahead):
            R, t = pose_matrix(px, py, pyaw)
            xyz.append(layout @ R.T + t)
        k = len(layout)
        truth = Truth(np.repeat([0, 1], k), np.tile(self.body.marker_ids, 2),
                      np.concatenate(xyz))
        c = self.sim_cfg
        obs = sim.observe(self.rig, truth, noise_px=c.noise_px, dropout=c.dropout,
                          fps=c.fps, seed=[c.seed, 9, g], clock_offset_ns=self.offsets_ns)
        first = obs.frame == 0
        cam = obs.camera[first]
        order = np.argsort(cam, kind="stable")
        starts = np.searchsorted(cam[order], np.arange(len(self.rig) + 1))
        got = (obs.uv[first][order], obs.area[first][order], obs.peak[first][order],
               obs.marker[first][order].astype(np.int64), starts)
        self.blob_cache[g] = got
        if len(self.blob_cache) > HISTORY:
            self.blob_cache.popitem(last=False)
        return got

    # ---- the truth, for the scorers -----------------------------------------------------

    def pose_at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """The robot's true (R, t) at daemon time t_ns, between the triggers' states (the
        nearest end outside those integrated)."""
        with self.lock:
            if self.t0_ns is None or self.last < 0:
                x, y, yaw_deg = self.cfg.start
                return pose_matrix(x, y, math.radians(yaw_deg))
            at = (t_ns - self.t0_ns) / self.period_ns
            lo = max(self.first, self.last - HISTORY + 1)
            at = min(max(at, lo), self.last)
            g = min(int(math.floor(at)), self.last - 1) if self.last > lo else self.last
            a = self.states[g % HISTORY]
            b = self.states[min(g + 1, self.last) % HISTORY]
        f = min(max(at - g, 0.0), 1.0)
        s = (1 - f) * a[:3] + f * b[:3]  # the heading is integrated unwrapped
        return pose_matrix(*s)

    def close(self) -> None:
        with self.lock:
            if self._truth_file is not None:
                self._truth_file.writelines(self._truth_lines)
                self._truth_file.close()
                self._truth_file = None
            self.sock.close()


def read_truth(path: Path) -> np.ndarray:
    """A robot truth file as a structured array (t_ns, x_m, y_m, yaw_rad, ...)."""
    return np.genfromtxt(path, delimiter=",", names=True, dtype=None, encoding="ascii")
