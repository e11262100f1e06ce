"""Rigid bodies made, renamed and removed from the live view, in the configuration file.

A body is made exactly as `mocapd rigid-body add --from-live` makes one: frames of the
daemon's `markers` answer over its control socket (kept to the markers picked in the 3D
view instead of those --near a point), clustered into a definition
(daemon.tracking.rigid_define), appended as a [[rigid_body]] table after the whole file is checked,
and the daemon asked to reload. Renaming and removing edit that one table's text and keep
the rest of the file, comments included, byte for byte; the result must parse to the same
configuration but for that body, or nothing is written.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from calibkit.core.errors import UserError
from daemon.config.mocapd import load_config
from daemon.service.live_bodies import append_body, body_from_markers, capture_snapshots
from daemon.tracking.rigid_define import body_from_snapshots
from daemon.view import tomledit

NAME_LINE = re.compile(r"^(\s*name\s*=\s*)(\"[^\"]*\"|'[^']*')(.*)$")


def _need_config(config: str | Path | None) -> Path:
    if config is None:
        raise UserError("the daemon runs without a configuration file; start it with "
                        "--config PATH to define bodies from the view")
    return Path(config)


def add_picked(config, name: str, picked, ask, frames: int = 30, at=None,
               radius_m: float = 0.01) -> tuple[int, int]:
    """A body called `name` from the picked track ids (`ask()` is one `markers` answer of
    the daemon); (its id, its markers). UserError for what the user can fix.

    `at` (track id -> where it was picked): a track lost and found again between the pick
    and the capture (a loaded machine skipping frame sets, a hand over a marker) comes
    back under a new id; the free marker within `radius_m` of where a picked one was last
    seen stands for it. The body is held still, so position is as good an identity."""
    path = _need_config(config)
    name = name.strip()
    if not name:
        raise UserError("give the new body a name")
    cfg = load_config(path) if path.exists() else None
    if cfg is not None and any(b.name == name for b in cfg.bodies):
        raise UserError(f"{path}: a rigid body called {name!r} exists already")
    wanted = {int(i) for i in picked}
    if not 3 <= len(wanted) <= 8:
        raise UserError(f"{len(wanted)} markers picked; a new body needs 3 to 8")

    last = {int(i): np.asarray(x, float) for i, x in (at or {}).items() if int(i) in wanted}

    def only_picked():
        markers = ask()["markers"]
        out = [m for m in markers if m["id"] in wanted]
        for m in out:
            last[m["id"]] = np.asarray(m["xyz"], float)
        lost = [i for i in last if i not in {m["id"] for m in out}]
        for m in markers:  # a lost one's new track: the free marker where it was
            if not lost or m["body"] or m["id"] in wanted:
                continue
            d = [np.linalg.norm(np.asarray(m["xyz"], float) - last[i]) for i in lost]
            k = int(np.argmin(d))
            if d[k] <= radius_m:
                out.append({**m, "id": lost.pop(k)})
        return {"markers": out}

    snapshots = capture_snapshots(only_picked, frames, None, np.inf)
    if not any(len(ids) for ids, _ in snapshots):
        raise UserError("none of the picked markers was tracked during the capture (their "
                        "tracks were lost since the pick): hold the body still, pick again")
    free = body_from_snapshots(snapshots)
    if not 3 <= len(free) <= 8:
        raise UserError(f"{len(free)} of the picked markers were tracked steadily and on no "
                        "body; a new body needs 3 to 8 (hold it still, pick again)")
    body_id = max((b.id for b in cfg.bodies), default=0) + 1 if cfg else 1
    append_body(path, name, body_id, body_from_markers(free))
    return body_id, len(free)


def _body_segment(text: str, name: str) -> tuple[list, int]:
    segs = tomledit.segments(text)
    return segs, tomledit.find_table(segs, "rigid_body", name, "rigid body")


def _write_checked(path: Path, old_text: str, new_text: str, expect) -> None:
    """Write new_text only if it parses to the old configuration with its body list changed
    as `expect` (a function of the old body list) says: nothing else may have moved."""
    def want(old: dict) -> dict:
        out = dict(old)
        out["rigid_body"] = expect(old.get("rigid_body", []))
        if not out["rigid_body"]:
            del out["rigid_body"]
        return out

    tomledit.write_checked(path, old_text, new_text, want)


def remove_body(config, name: str) -> None:
    path = _need_config(config)
    text = path.read_text(encoding="utf-8")
    segs, k = _body_segment(text, name)
    new_text = "".join("".join(lines) for j, (_, lines) in enumerate(segs) if j != k)
    _write_checked(path, text, new_text,
                   lambda bodies: [b for b in bodies if b.get("name") != name])


def rename_body(config, name: str, new_name: str) -> None:
    path = _need_config(config)
    new_name = new_name.strip()
    if not new_name:
        raise UserError("give the body a new name")
    if not re.fullmatch(r"[^\"'\\\n]+", new_name):
        raise UserError(f"a body's name cannot hold quotes or backslashes: {new_name!r}")
    text = path.read_text(encoding="utf-8")
    if any(b.name == new_name for b in load_config(path).bodies):
        raise UserError(f"{path}: a rigid body called {new_name!r} exists already")
    segs, k = _body_segment(text, name)
    head, lines = segs[k]
    done = False
    for i, line in enumerate(lines):
        m = NAME_LINE.match(line.rstrip("\r\n"))
        if m and not done:
            end = line[len(line.rstrip("\r\n")):]
            lines[i] = f'{m.group(1)}"{new_name}"{m.group(3)}{end}'
            done = True
    new_text = "".join("".join(ls) for _, ls in segs)
    _write_checked(path, text, new_text, lambda bodies: [
        {**b, "name": new_name} if b.get("name") == name else b for b in bodies])
