"""`mocapd install-unit`: write a systemd unit (Type=notify, watchdog, reload on SIGHUP)."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path
from typing import Annotated

import typer

from calibkit.errors import UserError
from calibkit.fileio import write_text_atomic


def unit_text(config: Path, executable: str, watchdog_s: int = 5,
              wanted_by: str = "default.target") -> str:
    # A system unit runs the tracking ahead of ordinary work on the machine: under load a
    # frame loop at the default priority waits for the CPU and the latency tail grows from
    # ~3 ms to tens of ms (docs/tracking.md). A user manager may not raise priority, and a
    # unit asking for it would fail to start, so user units leave it out.
    priority = "" if wanted_by == "default.target" else "Nice=-10\n"
    return f"""[Unit]
Description=mocapd motion-capture tracking daemon
After=network-online.target
Wants=network-online.target

[Service]
Type=notify
NotifyAccess=main
ExecStart={executable} start --config {config}
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
    ) -> None:
        """Write mocapd.service; then `systemctl --user daemon-reload` and enable it."""
        if not config.exists():
            raise UserError(f"{config}: no such configuration file")
        if watchdog < 1:
            raise UserError(f"--watchdog-s must be at least 1, got {watchdog}")
        exe = shutil.which("mocapd") or f"{sys.executable} -m daemon.cli"
        target = out or Path.home() / ".config/systemd/user/mocapd.service"
        wanted = "default.target" if out is None or ".config/systemd/user" in str(target) \
            else "multi-user.target"
        write_text_atomic(target, unit_text(config.resolve(), exe, watchdog, wanted))
        typer.echo(f"wrote {target}\nthen: systemctl --user daemon-reload && "
                   "systemctl --user enable --now mocapd")
