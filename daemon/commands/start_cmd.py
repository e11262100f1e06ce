"""`mocapd start`: run the tracking daemon in the foreground, as systemd expects."""

from __future__ import annotations

import ipaddress
from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer

from calibkit.clitools import write_json
from calibkit.core.errors import UserError

# The daemon's modules (configuration, tracker, rigid bodies and their numba kernels) are
# imported where `start` uses them, deferred on purpose: every mocapd command imports this
# module to register `start`, and loading them costs 0.2-0.3 s of CPU that `mocapd label`
# and the other file commands do not need.


def protocol_outputs(natnet: str | None, natnet_up: str | None, vrpn: list[str]):
    """--natnet IFACE[:COMMAND_PORT] (data port: the next one), --vrpn [HOST:]PORT."""
    from daemon.config.outputs import NatnetOut, VrpnOut, parse_address  # deferred: see above

    out_natnet = None
    if natnet is not None:
        iface, _, port = natnet.partition(":")
        try:
            ipaddress.IPv4Address(iface)
            cmd = int(port) if port else 1510
            if not 0 < cmd < 65535:
                raise ValueError
        except ValueError:
            raise UserError(f"--natnet: expected the IPv4 address of a local interface "
                            f"(0.0.0.0 for all), optionally :COMMAND_PORT; got {natnet!r}"
                            ) from None
        out_natnet = NatnetOut(iface, cmd, cmd + 1 if port else 1511)
    if natnet_up is not None and natnet_up not in ("y", "z"):
        raise UserError(f"--natnet-up must be y or z, got {natnet_up!r}")
    outs_vrpn = []
    for text in vrpn:
        try:
            # a bare port is this computer's only: the network is reached on purpose
            host, port = parse_address(text if ":" in text else f"127.0.0.1:{text}")
        except ValueError as exc:
            raise UserError(f"--vrpn: {exc}") from None
        outs_vrpn.append(VrpnOut(host, port))
    return out_natnet, tuple(outs_vrpn)


def command_line_additions(udp: list[str], serial: list[str], mavlink: list[str],
                           mavlink_body: int | None, mavlink_message: str | None,
                           natnet: str | None = None, natnet_up: str | None = None,
                           vrpn: list[str] = (), mavlink_origin: str | None = None):
    """A function that adds the flags' outputs to a Config (and again after a reload)."""
    from daemon.config.mocapd import Config  # deferred: see above
    from daemon.config.outputs import (
        MavlinkOut,
        NatnetOut,
        SerialOut,
        UdpOut,
        mavlink_device,
        parse_address,
        parse_serial,
    )

    out_natnet, outs_vrpn = protocol_outputs(natnet, natnet_up, list(vrpn))
    outs_udp = []
    for text in udp:
        try:
            host, port = parse_address(text)
        except ValueError as exc:
            raise UserError(f"--udp: {exc}") from None
        outs_udp.append(UdpOut(host, port))
    outs_serial = [SerialOut(*parse_serial(t)) for t in serial]
    outs_mav = []
    for t in mavlink:
        dev, baud = parse_serial(t, 921600)
        try:
            outs_mav.append((mavlink_device(dev), baud))
        except ValueError as exc:
            raise UserError(f"--mavlink: {exc}") from None
    origin = None
    if mavlink_origin is not None:
        try:
            origin = tuple(float(v) for v in mavlink_origin.split(","))
            if len(origin) != 3 or not (-90 <= origin[0] <= 90 and -180 <= origin[1] <= 180):
                raise ValueError
        except ValueError:
            raise UserError("--mavlink-origin: expected LAT,LON,ALT (degrees, degrees, metres "
                            f"above sea level), got {mavlink_origin!r}") from None
    if mavlink_message is not None and mavlink_message not in (
            "vision_position_estimate", "odometry", "att_pos_mocap"):
        raise UserError("--mavlink-message must be vision_position_estimate, odometry or "
                        f"att_pos_mocap; got {mavlink_message!r}")

    def extend(cfg: Config) -> Config:
        body = mavlink_body
        if body is None:
            body = cfg.bodies[0].id if cfg.bodies else 1
        mav = tuple(MavlinkOut(d, body, b, mavlink_message or "vision_position_estimate",
                               origin=origin) for d, b in outs_mav)
        cfg = replace(cfg, udp=cfg.udp + tuple(outs_udp), serial=cfg.serial + tuple(outs_serial),
                      mavlink=cfg.mavlink + mav, vrpn=cfg.vrpn + outs_vrpn)
        if out_natnet is not None:  # the flag's address and ports; the rest from [natnet]
            cfg = replace(cfg, natnet=replace(
                cfg.natnet or NatnetOut(), interface=out_natnet.interface,
                command_port=out_natnet.command_port, data_port=out_natnet.data_port))
        if natnet_up is not None:
            cfg = replace(cfg, natnet=replace(cfg.natnet or NatnetOut(), up_axis=natnet_up))
        return cfg

    return extend


def register(app: typer.Typer) -> None:
    @app.command("start")
    def start(
        config: Annotated[Path | None, typer.Option(
            "--config", help="mocapd.toml (rig, rigid bodies, outputs).")] = None,
        sim: Annotated[bool, typer.Option(
            "--sim", help="Track a simulated scene (the rig's cameras, moving rigid bodies).")]
        = False,
        rig: Annotated[Path | None, typer.Option(
            "--rig", help="A calibrated rig (overrides the configuration's).")] = None,
        truth_rig: Annotated[Path | None, typer.Option(
            "--truth-rig", help="--sim: the true rig the blobs are made with (default: "
                                "--rig itself).")] = None,
        udp: Annotated[list[str], typer.Option(
            "--udp", help="Send pose packets to HOST:PORT (repeatable).")] = [],  # noqa: B006
        serial: Annotated[list[str], typer.Option(
            "--serial", help="Send COBS-framed packets on DEV[:BAUD] (repeatable).")]
        = [],  # noqa: B006
        mavlink: Annotated[list[str], typer.Option(
            "--mavlink", help="Send MAVLink to a flight controller on DEV[:BAUD], or "
                              "udpin:/udpout:/tcp:HOST:PORT (repeatable).")]
        = [],  # noqa: B006
        mavlink_body: Annotated[int | None, typer.Option(
            "--mavlink-body", help="Rigid body id for --mavlink (default: the first).")]
        = None,
        mavlink_message: Annotated[str | None, typer.Option(
            "--mavlink-message", help="vision_position_estimate, odometry or "
                                      "att_pos_mocap.")] = None,
        mavlink_origin: Annotated[str | None, typer.Option(
            "--mavlink-origin", help="LAT,LON,ALT of the world's origin, sent to the "
                                     "autopilot as its GPS origin and home.")] = None,
        natnet: Annotated[str | None, typer.Option(
            "--natnet", help="Serve NatNet 4.1 (OptiTrack clients) on this local interface "
                             "address, IFACE[:COMMAND_PORT] (default ports 1510/1511).")]
        = None,
        natnet_up: Annotated[str | None, typer.Option(
            "--natnet-up", help="NatNet's up axis: z (ours, default) or y (Motive's).")]
        = None,
        vrpn: Annotated[list[str], typer.Option(
            "--vrpn", help="Serve VRPN trackers (one per rigid body) on [HOST:]PORT, "
                           "e.g. 3883 (this computer only) or 192.168.1.10:3883 (that "
                           "network; 0.0.0.0: all), repeatable.")] = [],  # noqa: B006
        mode: Annotated[str | None, typer.Option(
            "--mode", help="Multiplexer: triggered (synchronised cameras) or greedy.")] = None,
        frames: Annotated[int | None, typer.Option(
            "--frames", help="Stop after N frames.")] = None,
        duration: Annotated[float | None, typer.Option(
            "--duration", help="Stop after SECONDS.")] = None,
        json_path: Annotated[Path | None, typer.Option(
            "--json", help="Write rate, latency and (with --sim) pose errors here.")] = None,
        runtime_dir: Annotated[Path | None, typer.Option(
            "--runtime-dir", help="Folder of the control socket.")] = None,
        fast: Annotated[bool, typer.Option(
            "--fast", help="--sim/--replay: as fast as the tracker goes, not at the camera "
                           "rate.")] = False,
        replay: Annotated[Path | None, typer.Option(
            "--replay", help="Play a recording (.mcrec or CSV) instead of cameras.")] = None,
        sim_bodies: Annotated[int | None, typer.Option(
            "--sim-bodies", help="--sim: rigid bodies in the scene (default 3).")] = None,
        sim_cameras: Annotated[int | None, typer.Option(
            "--sim-cameras", help="--sim without --rig: cameras (default 8).")] = None,
        sim_fps: Annotated[float | None, typer.Option(
            "--sim-fps", help="--sim: camera rate, Hz (default 240).")] = None,
        noise_px: Annotated[float | None, typer.Option(
            "--noise-px", help="--sim: centroid noise sigma, px (default 0.2).")] = None,
        seed: Annotated[int | None, typer.Option("--seed", help="--sim: random seed.")] = None,
        verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Debug log.")] = False,
        realtime: Annotated[bool, typer.Option(
            "--realtime", help="Run the tracking threads under real-time scheduling (SCHED_RR "
                               "at [pipeline] realtime_priority, else 10): steadier latency, "
                               "but it takes the CPU from everything else. Off by default; "
                               "the systemd unit (mocapd install-unit) turns it on.")] = False,
        view: Annotated[str | None, typer.Option(
            "--view", help="Serve the live web view on [HOST:]PORT (a bare port: this "
                           "computer only), e.g. 8080.")] = None,
    ) -> None:
        """Track markers and rigid bodies and serve their poses until stopped (SIGTERM).

        SIGHUP reloads the configuration. With --frames or --duration it stops by itself
        and prints (and with --json writes) its figures.
        """
        from daemon.commands.start_run import StartOverrides, run_daemon
        from daemon.config.mocapd import Config, load_config  # deferred: see above
        from daemon.process.logs import setup_logging

        setup_logging(verbose)
        for name, value in (("--frames", frames), ("--duration", duration)):
            if value is not None and value <= 0:
                raise UserError(f"{name} must be positive, got {value}")
        if mode is not None and mode not in ("triggered", "greedy"):
            raise UserError(f"--mode must be triggered or greedy, got {mode!r}")
        extend = command_line_additions(udp, serial, mavlink, mavlink_body, mavlink_message,
                                        natnet, natnet_up, vrpn, mavlink_origin)
        overrides = StartOverrides(rig, runtime_dir, mode, replay, fast, sim, sim_bodies,
                                   sim_cameras, sim_fps, noise_px, seed, realtime)

        def full(cfg: Config) -> Config:
            return overrides.apply(extend(cfg))

        figures = run_daemon(full(load_config(config)), full, truth_rig, frames, duration,
                             view)
        _report(figures)
        if json_path is not None:
            write_json(json_path, figures)
        # Everything is written and closed: the process may end without the interpreter's
        # teardown (1-3 s of a loaded machine after SIGTERM; daemon/process/ending.py).
        # Only the entry point acts on it, so an in-process run returns as before.
        from daemon.process import ending

        ending.arm()


def _report(fig: dict) -> None:
    from daemon.service.console import print_table  # deferred: see above (loads rich)

    lat = fig["latency_to_poses"]
    rows = [["frames", fig["frames"]],
            ["rate (fps)", round(fig["rate_hz"] or 0.0, 1)],
            ["latency to poses, median (ms)", lat["median_ms"] or float("nan")],
            ["latency to poses, p99 (ms)", lat["p99_ms"] or float("nan")]]
    if "latency_to_udp_sent" in fig:
        u = fig["latency_to_udp_sent"]
        rows += [["latency to UDP sent, median (ms)", u["median_ms"] or float("nan")],
                 ["latency to UDP sent, p99 (ms)", u["p99_ms"] or float("nan")]]
    print_table(rows, ["what", "value"])
    live = fig.get("bodies_defined_live")
    if live:
        typer.echo(f"\nrigid bodies defined live at the start (each held still for "
                   f"{live['frames_each']} frames): "
                   + ", ".join(f"{b['name']} ({b['markers']} markers)" for b in live["bodies"])
                   + (f"; written to {live['file']}" if live["file"] else ""))
    truth = fig.get("truth")
    if truth and truth["bodies"]:
        typer.echo(f"\ntracked with {truth['tracking_rig']}")
        print_table([[name, b.get("defined_as") or "-", round(100 * b["valid_fraction"], 1),
                      b["position_error_mm_rms"] if b["position_error_mm_rms"] is not None
                      else float("nan"),
                      b["orientation_error_deg_rms"] if b["orientation_error_deg_rms"]
                      is not None else float("nan"), b["gross_error_frames"]]
                     for name, b in truth["bodies"].items()],
                    ["body (scene)", "tracked as", "valid_%", "pos_err_mm_rms",
                     "rot_err_deg_rms", "gross (>2 cm / 5 deg)"])
        typer.echo(f"\nidentity swaps: {truth['track_swaps']} track, {truth['body_swaps']} body;"
                   f" frame sets mixing instants: {truth.get('sets_mixing_instants', 0)} of "
                   f"{truth.get('sets_checked_for_instants', 0)}")
