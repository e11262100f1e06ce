"""Robot go-to-point: a differential-drive robot reads its own pose off mocapd's serial line
and drives to a list of targets on the floor.

    python examples/goto_point.py --serial /dev/ttyUSB0 --body 2 --command-port 9880 \\
        --targets "0.5,0.5 -0.5,0.3 0,0"

Each pose comes off the serial line (mocap_serial.SerialPoseReader); the controller turns
the distance and bearing to the target into a forward speed and a turn rate, sent as the
datagram "V OMEGA" to the robot's command port on 127.0.0.1 (the simulated robot of
`[sim.robot]`; on a real robot, replace `send` with the motor driver). Near a target the
robot is stopped; once it has settled within --tolerance the target counts as reached (else
it drives on), and the error is printed with the capture time of the pose it was measured
on:

    target 1 (0.219, -0.368): reached in 2.83 s, error 7.8 mm (pose t_ns 787647020982)
    10 of 10 targets reached; error mean 7.0 mm, worst 8.0 mm

The controller (why it is this simple): a unicycle steered to a point by bearing and
distance, driving backwards when the target is behind (no U-turn near the goal), speed
proportional to the distance so the robot slows as it arrives; the gains leave room for
the robot's command delay and lag (about 0.15 s together on the simulator's defaults).
Exit status: 0 when every target was reached, 3 when one was not within --timeout, 1 when
the line cannot be opened or the poses stop.
"""

from __future__ import annotations

import argparse
import math
import socket
import sys
import time

import numpy as np
from mocap_serial import SerialPoseReader


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def steer(x: float, y: float, yaw: float, target, max_speed: float, max_turn: float,
          k_dist: float = 1.5, k_turn: float = 3.0) -> tuple[float, float]:
    """(v, omega) towards the target from pose (x, y, yaw): forwards or backwards,
    whichever faces it, slowing in proportion to the distance."""
    dx, dy = target[0] - x, target[1] - y
    rho = math.hypot(dx, dy)
    alpha = wrap(math.atan2(dy, dx) - yaw)
    sign = 1.0
    if abs(alpha) > math.pi / 2:  # behind: back up to it
        alpha, sign = wrap(alpha + math.pi), -1.0
    v = sign * min(max_speed, k_dist * rho) * max(math.cos(alpha), 0.0) ** 2
    w = min(max(k_turn * alpha, -max_turn), max_turn)
    return v, w


class Robot:
    """The command link: one datagram "V OMEGA" per command."""

    def __init__(self, port: int, host: str = "127.0.0.1") -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.address = (host, port)

    def send(self, v: float, w: float) -> int:
        """Send a command; its send time (monotonic ns)."""
        t = time.monotonic_ns()
        self.sock.sendto(f"{v:.5f} {w:.5f}".encode(), self.address)
        return t

    def close(self) -> None:
        self.sock.close()


def parse_targets(text: str) -> list[tuple[float, float]]:
    out = []
    for item in text.split():
        parts = item.split(",")
        try:
            if len(parts) != 2:
                raise ValueError
            out.append((float(parts[0]), float(parts[1])))
        except ValueError:
            raise SystemExit(f"goto_point: error: --targets needs x,y pairs separated by "
                             f"spaces, got {item!r}") from None
    return out


def random_targets(n: int, half_m: float, seed: int, spacing_m: float = 0.3):
    """n targets in the square |x|, |y| <= half_m, each at least spacing_m from the one
    before (a target where the robot stands tests nothing)."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        p = tuple(float(v) for v in rng.uniform(-half_m, half_m, 2))
        if not out or math.dist(p, out[-1]) >= spacing_m:
            out.append(p)
    return out


def settle(reader, robot, body: int, settle_s: float, pose_timeout_s: float):
    """Stop and wait out the robot's delay and lag; the last pose seen."""
    end = time.monotonic() + settle_s
    pose = reader.latest(body, pose_timeout_s)
    while time.monotonic() < end:
        robot.send(0.0, 0.0)
        pose = reader.latest(body, pose_timeout_s)
    return pose


def drive(reader, robot, body: int, targets, tolerance_m: float, max_speed: float,
          max_turn: float, timeout_s: float, settle_s: float, pose_timeout_s: float = 10.0,
          gap_s: float = 0.1, out=print):
    """Drive to each target in turn; per target (reached, seconds, error_m, pose).

    A target counts as reached when the robot, stopped and settled, is within tolerance;
    if it settled outside, it drives on. Without a new pose for gap_s (the line or mocapd
    stalled) it stops until poses come again: steering on an old pose overshoots."""
    results = []
    for k, target in enumerate(targets, 1):
        start = time.monotonic()
        reached, pose = False, None
        while time.monotonic() - start < timeout_s:
            try:
                p = reader.latest(body, gap_s)
            except TimeoutError:
                robot.send(0.0, 0.0)
                p = reader.latest(body, pose_timeout_s)
            x, y = p.position[:2]
            if math.hypot(target[0] - x, target[1] - y) < tolerance_m:
                pose = settle(reader, robot, body, settle_s, pose_timeout_s)
                if math.dist(pose.position[:2], target) < tolerance_m:
                    reached = True
                    break
                continue
            robot.send(*steer(x, y, p.yaw, target, max_speed, max_turn))
        if pose is None or not reached:
            pose = settle(reader, robot, body, settle_s, pose_timeout_s)
        error = math.dist(pose.position[:2], target)
        took = time.monotonic() - start
        what = f"reached in {took:.2f} s" if reached else f"NOT reached in {timeout_s:g} s"
        out(f"target {k} ({target[0]:.3f}, {target[1]:.3f}): {what}, error "
            f"{error * 1000:.1f} mm (pose t_ns {pose.t_ns})", flush=True)
        results.append((reached, took, error, pose))
    return results


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--serial", required=True, help="the serial line mocapd writes poses to")
    ap.add_argument("--baud", type=int, default=115200)
    ap.add_argument("--body", type=int, required=True, help="the robot's rigid-body id")
    ap.add_argument("--command-port", type=int, required=True,
                    help="the robot's command port on 127.0.0.1 ([sim.robot] port)")
    ap.add_argument("--targets", help='"x,y x,y ..." in metres, world frame')
    ap.add_argument("--random", type=int, default=0, help="this many random targets instead")
    ap.add_argument("--area", type=float, default=0.8,
                    help="random targets within |x|, |y| <= this (m)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tolerance", type=float, default=0.01, help="reached within this (m)")
    ap.add_argument("--max-speed", type=float, default=0.4, help="m/s")
    ap.add_argument("--max-turn", type=float, default=2.5, help="rad/s")
    ap.add_argument("--timeout", type=float, default=20.0, help="seconds per target")
    ap.add_argument("--wait", type=float, default=30.0,
                    help="seconds to wait for the first pose (mocapd starting)")
    ap.add_argument("--settle", type=float, default=0.4,
                    help="seconds stopped at a target before its error is measured")
    args = ap.parse_args(argv)
    if args.targets:
        targets = parse_targets(args.targets)
    elif args.random > 0:
        targets = random_targets(args.random, args.area, args.seed)
    else:
        raise SystemExit("goto_point: error: give --targets or --random N")
    try:
        reader = SerialPoseReader(args.serial, args.baud)
    except Exception as exc:  # pyserial's SerialException, or OSError
        print(f"goto_point: error: cannot open {args.serial}: {exc}", file=sys.stderr)
        return 1
    robot = Robot(args.command_port)
    try:
        reader.latest(args.body, args.wait)  # mocapd may still be starting
        results = drive(reader, robot, args.body, targets, args.tolerance, args.max_speed,
                        args.max_turn, args.timeout, args.settle)
    except TimeoutError as exc:
        print(f"goto_point: error: {exc} (is mocapd running, with this body on the line?)",
              file=sys.stderr)
        return 1
    finally:
        try:
            robot.send(0.0, 0.0)
        finally:
            robot.close()
            reader.close()
    errors = np.array([r[2] for r in results]) * 1000
    n_ok = sum(r[0] for r in results)
    print(f"{n_ok} of {len(results)} targets reached; error mean {errors.mean():.1f} mm, "
          f"worst {errors.max():.1f} mm", flush=True)
    return 0 if n_ok == len(results) else 3


if __name__ == "__main__":
    sys.exit(main())
