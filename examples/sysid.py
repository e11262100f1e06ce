"""System identification of a mobile robot through mocapd: how long its commands take to
act, and how fast its speeds follow them.

    python examples/sysid.py --serial /dev/ttyUSB0 --body 2 --command-port 9880 \\
        --seconds 10 --json sysid.json

It sends a sequence of speed and turn-rate steps (or a chirp) as "V OMEGA" datagrams,
logging each one's send time, while it logs every pose of the robot off mocapd's serial
line with the pose's capture time. Both times are on one clock: `time.monotonic_ns()` here
and the packet's `t_ns` (the daemon's monotonic clock) are the same clock when both run
on one machine, as with `mocapd start --sim`. (On two machines, subtract a measured
offset from the send times first.) Then it fits the model

    speed(t) follows command(t - delay) with a first-order lag of time constant tau

to the measured forward speed and yaw rate (differences of the poses): a grid over (delay,
tau), refined by Nelder-Mead, on the response the model gives to the commands as they were
sent. The peak of the cross-correlation of commanded and measured yaw rate is printed too:
for steps it lies between the delay and delay + tau, which is why the fit, not the peak, is
the estimate.

    delay 0.050 s, time constant 0.100 s (fit residual 0.399, 1043 poses);
    cross-correlation peak 0.116 s
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np
from goto_point import Robot
from mocap_serial import SerialPoseReader, body_pose

GRID_S = 0.0005  # the model's time step


def step_sequence(seconds: float, rate_hz: float, speed: float, turn: float, seed: int):
    """(t_s, v, omega) at rate_hz: steps held 0.4-1.0 s; the speed changes sign at every
    step (the robot stays near where it started), the turn rate takes random levels."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    v, w = np.zeros_like(t), np.zeros_like(t)
    at, sign = 0.3, 1.0  # 0.3 s standing first: the fit sees the response start
    while at < seconds:
        hold = rng.uniform(0.4, 1.0)
        span = (t >= at) & (t < at + hold)
        v[span] = sign * speed * rng.uniform(0.4, 1.0)
        w[span] = turn * rng.uniform(-1.0, 1.0)
        at, sign = at + hold, -sign
    return t, v, w


def chirp_sequence(seconds: float, rate_hz: float, speed: float, turn: float,
                   f0: float = 0.2, f1: float = 2.0):
    """(t_s, v, omega): sweeps from f0 to f1 Hz, the speed a quarter turn behind the turn
    rate."""
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    phase = 2 * np.pi * (f0 * t + (f1 - f0) * t**2 / (2 * seconds))
    return t, speed * np.sin(phase - np.pi / 2), turn * np.sin(phase)


def run(reader, robot, body: int, t_s, v, w, tail_s: float = 1.0):
    """Send the sequence at its times and log every pose of the body meanwhile: (commands
    (n, 3): send ns, v, omega; poses (m, 4): capture ns, x, y, yaw)."""
    sent, poses = [], []

    def log_poses(timeout_s):
        for p in reader.read_packets(max(timeout_s, 0.0)):
            pose = body_pose(p, body, 0)
            if pose is not None:
                poses.append((pose.t_ns, pose.position[0], pose.position[1], pose.yaw))

    start = time.monotonic() + 0.1
    for k in range(len(t_s)):
        while (wait := start + t_s[k] - time.monotonic()) > 0.002:
            log_poses(min(wait - 0.001, 0.01))
        sent.append((robot.send(float(v[k]), float(w[k])), v[k], w[k]))
    end = time.monotonic() + tail_s
    while time.monotonic() < end:  # stopped: the response dies out
        sent.append((robot.send(0.0, 0.0), 0.0, 0.0))
        log_poses(0.02)
    return np.array(sent, dtype=np.float64), np.array(poses, dtype=np.float64)


def measured_speeds(poses):
    """(t_s, forward speed, yaw rate) at each inner pose, by central differences."""
    t = poses[:, 0] * 1e-9
    x, y = poses[:, 1], poses[:, 2]
    yaw = np.unwrap(poses[:, 3])
    dt = t[2:] - t[:-2]
    vx, vy = (x[2:] - x[:-2]) / dt, (y[2:] - y[:-2]) / dt
    h = yaw[1:-1]
    return t[1:-1], vx * np.cos(h) + vy * np.sin(h), (yaw[2:] - yaw[:-2]) / dt


def model_response(send_s, u, t_eval, delay_s, tau_s):
    """A first-order lag's output at t_eval for the input u held from send_s + delay_s
    (zero before the first), exact on a GRID_S grid."""
    from scipy.signal import lfilter

    grid = np.arange(send_s[0], t_eval[-1] + GRID_S, GRID_S)
    k = np.searchsorted(send_s + delay_s, grid, side="right") - 1
    held = np.where(k >= 0, u[np.maximum(k, 0)], 0.0)
    a = math.exp(-GRID_S / max(tau_s, 1e-4))
    out = lfilter([0.0, 1.0 - a], [1.0, -a], held)
    return np.interp(t_eval, grid, out)


def estimate(commands, poses):
    """Delay and time constant of the robot's speeds, fitted to both channels at once."""
    from scipy.optimize import minimize

    if len(poses) < 20:
        raise ValueError(f"only {len(poses)} poses were logged; is the robot tracked?")
    t, v_m, w_m = measured_speeds(poses)
    send = commands[:, 0] * 1e-9
    keep = (t > send[0]) & (t < send[-1])
    t, v_m, w_m = t[keep], v_m[keep], w_m[keep]
    scale_v, scale_w = max(np.std(v_m), 1e-6), max(np.std(w_m), 1e-6)

    def cost(p):
        d, tau = p
        if d < 0 or tau <= 1e-3:
            return 1e9
        ev = (model_response(send, commands[:, 1], t, d, tau) - v_m) / scale_v
        ew = (model_response(send, commands[:, 2], t, d, tau) - w_m) / scale_w
        return float(np.mean(ev**2) + np.mean(ew**2))

    grid = [(d, tau) for d in np.arange(0.0, 0.5, 0.005)
            for tau in np.geomspace(0.005, 1.0, 24)]
    best = min(grid, key=cost)
    fit = minimize(cost, best, method="Nelder-Mead",
                   options={"xatol": 1e-5, "fatol": 1e-9, "initial_simplex":
                            [best, (best[0] + 0.005, best[1]), (best[0], best[1] * 1.2)]})
    d, tau = (float(v) for v in fit.x)
    return {"delay_s": d, "tau_s": tau, "fit_residual": math.sqrt(fit.fun / 2),
            "xcorr_peak_s": xcorr_peak(send, commands[:, 2], t, w_m),
            "poses": int(len(poses)), "commands": int(len(commands))}


def xcorr_peak(send_s, u, t, measured, step_s: float = 0.001, max_lag_s: float = 1.0):
    """The lag (s) at which the measured signal best matches the commanded one (both
    resampled to step_s, means removed)."""
    grid = np.arange(t[0], t[-1], step_s)
    k = np.searchsorted(send_s, grid, side="right") - 1
    cmd = np.where(k >= 0, u[np.maximum(k, 0)], 0.0)
    got = np.interp(grid, t, measured)
    cmd, got = cmd - cmd.mean(), got - got.mean()
    lags = np.arange(0, int(max_lag_s / step_s))
    score = [np.dot(cmd[:len(cmd) - n], got[n:]) for n in lags]
    return float(lags[int(np.argmax(score))] * step_s)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--serial", required=True, help="the serial line mocapd writes poses to")
    ap.add_argument("--baud", type=int, default=115200)
    ap.add_argument("--body", type=int, required=True, help="the robot's rigid-body id")
    ap.add_argument("--command-port", type=int, required=True,
                    help="the robot's command port on 127.0.0.1 ([sim.robot] port)")
    ap.add_argument("--signal", choices=("steps", "chirp"), default="steps")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=50.0, help="commands a second")
    ap.add_argument("--speed", type=float, default=0.2, help="largest speed step, m/s")
    ap.add_argument("--turn", type=float, default=1.5, help="largest turn rate, rad/s")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--wait", type=float, default=30.0,
                    help="seconds to wait for the first pose (mocapd starting)")
    ap.add_argument("--json", help="write the estimates here")
    ap.add_argument("--log", help="write the commands and poses here (.npz)")
    args = ap.parse_args(argv)
    if args.seconds <= 1 or args.rate <= 0:
        raise SystemExit("sysid: error: --seconds must be over 1 and --rate positive")
    seq = step_sequence(args.seconds, args.rate, args.speed, args.turn, args.seed) \
        if args.signal == "steps" else chirp_sequence(args.seconds, args.rate, args.speed,
                                                      args.turn)
    try:
        reader = SerialPoseReader(args.serial, args.baud)
    except Exception as exc:  # pyserial's SerialException, or OSError
        print(f"sysid: error: cannot open {args.serial}: {exc}", file=sys.stderr)
        return 1
    robot = Robot(args.command_port)
    try:
        reader.latest(args.body, args.wait)
        print(f"sending {args.seconds:g} s of {args.signal} at {args.rate:g} Hz, then 1 s "
              "stopped; logging the poses", flush=True)
        commands, poses = run(reader, robot, args.body, *seq)
    except TimeoutError as exc:
        print(f"sysid: error: {exc} (is mocapd running, with this body on the line?)",
              file=sys.stderr)
        return 1
    finally:
        robot.close()
        reader.close()
    if args.log:
        np.savez(args.log, commands=commands, poses=poses)
    try:
        fig = estimate(commands, poses)
    except ValueError as exc:
        print(f"sysid: error: {exc}", file=sys.stderr)
        return 1
    print(f"delay {fig['delay_s']:.3f} s, time constant {fig['tau_s']:.3f} s (fit residual "
          f"{fig['fit_residual']:.3f}, {fig['poses']} poses); cross-correlation peak "
          f"{fig['xcorr_peak_s']:.3f} s", flush=True)
    if args.json:
        from pathlib import Path

        tmp = Path(args.json + ".tmp")
        tmp.write_text(json.dumps(fig, indent=2))
        tmp.replace(args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
