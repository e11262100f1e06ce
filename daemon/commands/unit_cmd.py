"""`mocapd install-unit`: write a systemd unit (Type=notify, watchdog, reload on SIGHUP).

Why quoting matters: systemd splits ExecStart= at spaces and expands `%` specifiers and
`$` variables in it, so a configuration under "/srv/mocap lab/" or a `%` in a path would
start something else, or nothing. Every word is quoted the way systemd.service(5)
describes; the command printed afterwards is the one for the manager that reads the file
(the user's, or the system's).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path
from typing import Annotated

import typer

from calibkit.core.errors import UserError
from calibkit.core.fileio import write_text_atomic

USER_DIR = ".config/systemd/user"


def systemd_quote(word: str) -> str:
    """One ExecStart= word as systemd reads it back: `%` and `$` doubled (no specifier, no
    variable), in double quotes with `\\` and `"` escaped when it holds a space, a quote
    or a backslash. A control character (a newline) cannot be written: UserError."""
    if any(ord(c) < 32 or ord(c) == 127 for c in word):
        raise UserError(f"cannot write {word!r} into a systemd unit (a control character)")
    word = word.replace("%", "%%").replace("$", "$$")
    if word and not any(c in word for c in ' \t"\'\\;'):
        return word
    return '"' + word.replace("\\", "\\\\").replace('"', '\\"') + '"'


def exec_line(words: list[str]) -> str:
    return " ".join(systemd_quote(w) for w in words)


def unit_text(config: Path, executable: list[str], watchdog_s: int = 5,
              wanted_by: str = "default.target") -> str:
    # A system unit lets the daemon put its threads under real-time scheduling (daemon.
    # realtime; [pipeline] realtime_priority): under load a frame loop at the default
    # priority waits for the CPU and the latency tail grows from ~1.5 ms to tens of ms
    # (docs/tracking.md). A user manager may not raise these limits, and a unit asking for
    # them would fail to start, so user units leave them out (the daemon then says so).
    # Both kinds pass --realtime: a user unit's daemon then says once how to allow it.
    priority = "" if wanted_by == "default.target" else "Nice=-10\nLimitRTPRIO=99\n"
    realtime = ["--realtime"]
    return f"""[Unit]
Description=mocapd motion-capture tracking daemon
After=network-online.target
Wants=network-online.target

[Service]
Type=notify
NotifyAccess=main
ExecStart={exec_line([*executable, 'start', '--config', str(config), *realtime])}
ExecReload=/bin/kill -HUP $MAINPID
RuntimeDirectory=mocapd
RuntimeDirectoryMode=0700
WatchdogSec={watchdog_s}
Restart=on-failure
RestartSec=2
KillSignal=SIGTERM
TimeoutStopSec=10
{priority}
[Install]
WantedBy={wanted_by}
"""


def register(app: typer.Typer) -> None:
    @app.command("install-unit")
    def install_unit(
        config: Annotated[Path, typer.Option("--config", help="The mocapd.toml to run.")],
        out: Annotated[Path | None, typer.Option(
            "--out", help="Unit file to write (default: the user's systemd folder).")] = None,
        watchdog: Annotated[int, typer.Option("--watchdog-s", help="WatchdogSec.")] = 5,
        build_kernels: Annotated[bool, typer.Option(
            "--build-kernels/--no-build-kernels",
            help="Compile the daemon's kernels into the cache now (`mocapd build-kernels`), "
                 "so the service tracks from its first second.")] = True,
    ) -> None:
        """Write mocapd.service, compile the daemon's kernels ahead of its first start, and
        print the systemctl commands that enable it.

        Reads nothing but its options (the configuration it names is read by the service
        when it starts)."""
        if not config.exists():
            raise UserError(f"{config}: no such configuration file")
        if watchdog < 1:
            raise UserError(f"--watchdog-s must be at least 1, got {watchdog}")
        exe = shutil.which("mocapd")
        command = [exe] if exe else [sys.executable, "-m", "daemon.cli"]
        target = out or Path.home() / USER_DIR / "mocapd.service"
        user = USER_DIR in target.resolve().as_posix()
        write_text_atomic(target, unit_text(config.resolve(), command, watchdog,
                                            "default.target" if user else "multi-user.target"))
        typer.echo(f"wrote {target}")
        if build_kernels:
            from daemon.commands.kernels_cmd import build_kernels as build
            from daemon.commands.kernels_cmd import cache_location

            total = build(typer.echo)
            typer.echo(f"kernels built in {total:.1f} s; cached in {cache_location()} (run "
                       "`mocapd build-kernels` as the service's user if it is another)")
        typer.echo(f"then: {follow_up(target, user)}")


def follow_up(target: Path, user: bool) -> str:
    """The commands that load and start the unit just written, for its manager: the
    user's (`--user`) or the system's; a system unit outside systemd's own folder is
    linked in first."""
    ctl = "systemctl --user" if user else "systemctl"
    path = target.resolve()
    link = "" if user or path.parent == Path("/etc/systemd/system") else (
        f"{ctl} link {systemd_quote(str(path))} && ")
    return f"{link}{ctl} daemon-reload && {ctl} enable --now {path.name}"
