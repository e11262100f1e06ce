"""`mocapd status`, `mocapd stop`, `mocapd record`: talk to a running daemon's control socket."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from calibkit.clitools import write_json

RuntimeDir = Annotated[Path | None, typer.Option(
    "--runtime-dir", help="Folder of the daemon's control socket (as given to start).")]


def request(runtime_dir: Path | None, message: dict) -> dict:
    """daemon.service.control.request, imported when a command asks the daemon: it loads the
    daemon's configuration (the tracker and its numba kernels, 0.2-0.3 s of CPU), which
    registering these commands for every mocapd command must not."""
    from daemon.service.control import request as ask  # deferred on purpose: see above

    return ask(runtime_dir, message)


def view_line(view: dict) -> str:
    """The live view's process in one line: where, and whether it had to be started again."""
    state = "serving" if view.get("alive") else "NOT RUNNING"
    n = view.get("restarts") or 0
    again = (f", started again {n} time{'s' if n > 1 else ''} (last exit {view.get('last_exit')})"
             if n else "")
    return f"view: {view.get('url')} {state}{again}"


def register(app: typer.Typer) -> None:
    @app.command("status")
    def status(runtime_dir: RuntimeDir = None,
               json_path: Annotated[Path | None, typer.Option("--json")] = None) -> None:
        """Rate per camera, dropped frames, latency, bodies tracked, outputs.

        Reads a running daemon's control socket (`mocapd start --sim` runs one on a simulated
        rig)."""
        from daemon.service.console import print_table

        st = request(runtime_dir, {"cmd": "status"})
        lat = st["latency"]
        typer.echo(f"frames {st['frames']}, {st['rate_hz']:.1f} fps, latency median "
                   f"{lat['median_ms'] or 0:.2f} ms, p99 {lat['p99_ms'] or 0:.2f} ms, "
                   f"{st['bodies_tracked']} of {len(st['bodies'])} bodies tracked, "
                   f"scheduling {st.get('scheduling', '?')}")
        if (st.get("multiplexer") or {}).get("behind"):  # falling behind: said at the top
            typer.echo(f"WARNING: {st['multiplexer']['behind']}")
        detects = any("threshold" in c for c in st["cameras"])  # [[camera]] tables
        print_table([[c["name"], "yes" if c["connected"] else "NO", round(c["rate_hz"], 1),
                      c["frames"], c["dropped"]]
                     + ([c.get("threshold", "-"), Path(c["mask"]).name if c.get("mask")
                         else "-"] if detects else []) for c in st["cameras"]],
                    ["camera", "connected", "fps", "frames", "dropped"]
                    + (["threshold", "mask"] if detects else []))
        if st.get("nodes"):  # capture nodes over Zenoh: their clocks and what they add
            print_table([[n["name"], "yes" if n["alive"] else "NO", len(n["cameras"]),
                          "-" if n["offset_ms"] is None else f"{n['offset_ms']:.3f}",
                          "-" if n["drift_ppm"] is None else f"{n['drift_ppm']:.1f}",
                          "-" if n["rtt_ms"] is None else f"{n['rtt_ms']:.2f}",
                          "-" if n["hop_median_ms"] is None else f"{n['hop_median_ms']:.2f}",
                          n["late"], n["restarts"]] for n in st["nodes"]],
                        ["node", "alive", "cameras", "offset ms", "drift ppm", "rtt ms",
                         "hop ms", "late", "restarts"])
        if st["outputs"]:
            print_table([[o["name"], "yes" if o["connected"] else "no", o["sent"], o["dropped"],
                          o["last_error"] or "-"] for o in st["outputs"]],
                        ["output", "open", "sent", "dropped", "last error"])
        for o in st["outputs"]:
            if "autopilot" in o:
                typer.echo(link_line(o))
        threads = st.get("threads") or []  # supervised threads (daemon.process.supervise)
        shown = [t for t in threads if t["state"] != "running" or t["restarts"]]
        typer.echo(f"threads: {len(threads)} supervised, "
                   + (f"{len(shown)} restarted or not running" if shown else "all running"))
        if shown:
            print_table([[t["name"], t["state"], t["restarts"], t["last_error"] or "-"]
                         for t in shown], ["thread", "state", "restarts", "last error"])
        if st.get("recording"):
            rec = st.get("recording_status") or {}
            typer.echo(f"recording to {st['recording']}: {rec.get('sent', 0)} frames"
                       + (f"; STOPPED: {rec['failed']} ({rec['lost']} frames not recorded)"
                          if rec.get("failed") else ""))
        if st.get("view"):
            typer.echo(view_line(st["view"]))
        if json_path is not None:
            write_json(json_path, st)

    @app.command("stop")
    def stop(runtime_dir: RuntimeDir = None) -> None:
        """Stop the daemon cleanly (as SIGTERM does).

        Reads a running daemon's control socket (`mocapd start --sim` runs one on a simulated
        rig)."""
        request(runtime_dir, {"cmd": "stop"})
        typer.echo("mocapd: stopping")

    @app.command("reload")
    def reload(runtime_dir: RuntimeDir = None) -> None:
        """Re-read the configuration (as SIGHUP does).

        Reads a running daemon's control socket (`mocapd start --sim` runs one on a simulated
        rig)."""
        answer = request(runtime_dir, {"cmd": "reload"})
        typer.echo("mocapd: still reloading (see the log)" if answer.get("pending")
                   else "mocapd: configuration reloaded")

    @app.command("record")
    def record(path: Annotated[Path | None, typer.Argument(
                   help="Recording to write: .mcrec (the blobs, for replay) or .mcap "
                        "(poses and markers, for Foxglove).")] = None,
               stop: Annotated[bool, typer.Option("--stop", help="Stop recording.")] = False,
               overwrite: Annotated[bool, typer.Option(
                   "--overwrite", help="Record over an existing file (refused without).")]
               = False,
               runtime_dir: RuntimeDir = None) -> None:
        """Record the cameras' blobs (.mcrec) or the poses and markers (.mcap), or stop.

        Reads a running daemon's control socket (`mocapd start --sim` runs one on a simulated
        rig)."""
        from calibkit.core.errors import UserError

        if stop:
            answer = request(runtime_dir, {"cmd": "record_stop"})
            typer.echo(f"mocapd: recorded {answer['frames']} frames to {answer['path']}")
            if answer.get("failed"):  # the frames written are kept; the rest are not there
                raise UserError(f"the recording stopped early ({answer['failed']}); "
                                f"{answer.get('lost', 0)} frames after it were not recorded")
            return
        if path is None:
            raise UserError("give a PATH to record to, or --stop")
        answer = request(runtime_dir, {"cmd": "record", "path": str(path.resolve()),
                                       "overwrite": overwrite})
        typer.echo(f"mocapd: recording to {answer['path']}")


def link_line(o: dict) -> str:
    """A MAVLink output's conversation with its autopilot, in one line."""
    ap = o["autopilot"]
    if ap is None:
        heard = "no autopilot heartbeat yet"
    else:
        heard = (f"autopilot {ap['system_id']}/{ap['component_id']} ({ap['autopilot']}, "
                 f"{ap['type']}, {ap['state']}{', armed' if ap['armed'] else ''}), "
                 f"heartbeat {ap['age_s']:.1f} s ago, {ap['heartbeats']} heard")
    rtt = o["timesync_rtt_ms"]
    sync = f"TIMESYNC {o['timesync_answered']} answered" + (
        f", round trip {rtt:.2f} ms" if rtt is not None else "")
    return f"{o['name']}: {heard}; {sync}; {o['messages_sent']} sent; origin sent " \
           f"{o['origin_sent']}x"
