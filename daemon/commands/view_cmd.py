"""`mocapd view`: a take (.c3d, .csv) or a recording (.mcrec) on a web page, scrubbed
frame by frame with a slider."""

from __future__ import annotations

import contextlib
import io
import time
from pathlib import Path
from typing import Annotated

import typer

from calibkit.core.errors import UserError


def serve(frames, rig, host: str, port: int, title: str):
    """(viser server, ReplayView) on host:port; UserError if it cannot serve there."""
    import viser

    from daemon.view.link import check_port_free
    from daemon.view.replay import ReplayView

    check_port_free(host, port)
    with contextlib.redirect_stdout(io.StringIO()):  # its banner: we say where it is
        server = viser.ViserServer(host=host, port=port, label="mocapd view", verbose=False)
    # as the live view: the page is served only where the user said, never tunnelled out
    server.request_share_url = lambda *args, **kwargs: None
    if server.get_port() != port:
        server.stop()
        raise UserError(f"--view: port {port} on {host} is taken; choose another")
    return server, ReplayView(server, frames, rig, title)


def register(app: typer.Typer) -> None:
    @app.command("view")
    def view(
        path: Annotated[Path, typer.Argument(
            help="A take (.c3d, or a labelled .csv) or a recording of blobs (.mcrec).")],
        rig_path: Annotated[Path | None, typer.Option(
            "--rig", help="The rig that recorded an .mcrec (its markers are triangulated "
                          "with it); with a take, its cameras are drawn.")] = None,
        markerset: Annotated[str | None, typer.Option(
            "--markerset", help="Draw a take's sticks: a marker set file or a shipped set "
                                "(cmu41).")] = None,
        where: Annotated[str, typer.Option(
            "--view", help="Serve on [HOST:]PORT (a bare port: this computer only).")]
        = "8080",
        duration: Annotated[float | None, typer.Option(
            "--duration", help="Stop after this many seconds (default: until Ctrl-C).")]
        = None,
    ) -> None:
        """Scrub through a take or a recording in the browser: a frame slider, play, the
        markers of the chosen frame with their names and a marker set's sticks.

        Reads a take or a recording; `mocapd label --sim --out take.c3d` and `calibkit sim
        static --out take.mcrec` write simulated ones."""
        from calibkit.clitools import Progress, parse_view
        from daemon.view.link import is_loopback
        from daemon.view.replay import load_replay

        host, port = parse_view(where)
        progress = Progress("triangulate") if path.suffix.lower() == ".mcrec" else None
        frames, rig = load_replay(path, rig_path, markerset,
                                  progress.update if progress else None)
        if progress is not None:
            progress.finish(f"{len(frames.xyz)} markers")
        server, page = serve(frames, rig, host, port, path.name)
        url = f"http://{host if ':' not in host else f'[{host}]'}:{port}"
        typer.echo(f"{path.name}: {len(frames)} frames ({frames.kind}) at {url}"
                   + ("" if is_loopback(host) else " (not loopback: anyone who can reach "
                                                    "this address can see it)"))
        try:
            end = None if duration is None else time.monotonic() + duration
            while end is None or time.monotonic() < end:
                time.sleep(0.2)
        except KeyboardInterrupt:
            pass
        finally:
            page.close()
            server.stop()
