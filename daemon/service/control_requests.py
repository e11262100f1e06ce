"""The requests a running daemon answers on its control socket: status, stop, reload, record.

Apart from daemon.service.daemon, which sets the daemon up and runs it: the socket's
thread calls `handle` with the Daemon; a user's mistake (an unknown request, a bad path)
is a UserError, which the socket sends back as one line.
"""

from __future__ import annotations

from pathlib import Path

from calibkit.core.errors import UserError
from daemon.publish.mcap_recorder import McapRecorderPublisher
from daemon.publish.recorder import RecorderPublisher

RELOAD_ANSWER_S = 4.0  # a reload still running then is answered 'pending' (clients wait 5 s)


def handle(daemon, req: dict) -> dict:
    """One control request's answer (daemon.service.control calls it on its thread)."""
    cmd = req.get("cmd")
    if cmd == "status":
        return {"ok": True, **daemon.status()}
    if cmd == "stop":
        daemon.stop_event.set()
        return {"ok": True}
    if cmd == "reload":  # answered once the new configuration took (or why it did not)
        outcome = daemon.reloads.wait(daemon.reloads.ask(), RELOAD_ANSWER_S)
        if outcome is None:
            return {"ok": True, "pending": True}
        if not outcome[0]:
            raise UserError(f"reload failed, keeping the running configuration: {outcome[1]}")
        return {"ok": True}
    if cmd == "record":
        return record(daemon, req.get("path"), bool(req.get("overwrite")))
    if cmd == "record_stop":
        if daemon.recorder is None:
            raise UserError("not recording")
        rec, daemon.recorder = daemon.recorder, None
        daemon.pipeline.hooks.remove(rec.submit)
        rec.stop(timeout=10.0)
        return {"ok": True, "path": str(rec.path), "frames": rec.sent,
                "failed": rec.failed or None, "lost": rec.lost}
    if cmd == "markers":
        return {"ok": True, **markers(daemon)}
    raise UserError(f"unknown request {cmd!r}")


def record(daemon, path, overwrite: bool = False) -> dict:
    """Start recording to `path` (.mcrec: the blobs, for replay; .mcap: poses and markers)."""
    if not path or not isinstance(path, str):
        raise UserError("record needs a PATH")
    if "\0" in path:  # no file has such a name: it would fail only at the first frame
        raise UserError(f"{path!r}: a path cannot hold a NUL byte")
    try:  # a name the file system refuses (too long, say) is said, not a traceback
        exists, folder = Path(path).exists(), Path(path).parent.is_dir()
    except OSError as exc:
        raise UserError(f"cannot record to {path}: {exc.strerror}") from None
    if exists and not overwrite:
        raise UserError(f"{path} exists; record to another name (or --overwrite)")
    if not folder:
        raise UserError(f"{path}: the folder {Path(path).parent} does not exist")
    if daemon.recorder is not None:
        raise UserError(f"already recording to {daemon.recorder.path}; "
                        "`mocapd record --stop` first")
    if Path(path).suffix.lower() not in (".mcrec", ".mcap"):
        raise UserError(f"{path}: record to a .mcrec (the blobs, for replay) or a .mcap "
                        "(poses and markers, for Foxglove)")
    if Path(path).suffix.lower() == ".mcap":
        rec = McapRecorderPublisher(Path(path), [b.name for b in daemon.pipeline.rigid.bodies],
                                    daemon.config.record_min_free_mb)
    else:
        rec = RecorderPublisher(Path(path), daemon.rig, daemon.scene.fps if daemon.scene else None,
                                daemon.config.record_min_free_mb)
    rec.start()
    daemon.recorder = rec
    daemon.pipeline.hooks.append(rec.submit)
    return {"ok": True, "path": str(path)}


def markers(daemon) -> dict:
    """The seen tracks of the latest frame, and whether a body holds each (for
    `mocapd rigid-body add --from-live`)."""
    res = daemon.pipeline.last_result
    if res is None:
        return {"markers": []}
    tr, taken = res.tracks, res.held_by_bodies()
    sel = tr.seen
    return {"markers": [{"id": int(i), "xyz": [float(v) for v in p], "body": bool(t)}
                        for i, p, t in zip(tr.ids[sel], tr.xyz[sel], taken[sel],
                                           strict=True)]}
