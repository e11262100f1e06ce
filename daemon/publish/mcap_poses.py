"""Poses and markers as MCAP with Foxglove's schemas, so Foxglove (and any MCAP reader,
ROS 2's `ros2 bag info` among them) opens a take or a live recording without a converter.

Why JSON with Foxglove's schema names: Foxglove recognises a channel by its schema name
(`foxglove.FrameTransforms`, `foxglove.PoseInFrame`, `foxglove.SceneUpdate`) in any
encoding, and JSON needs nothing beyond the `mcap` library to write or to read back.
Channels: `/tf` (every valid body as a transform from the world frame), `/mocap/<body>/pose`
(one PoseInFrame per valid pose), `/mocap/markers` (the frame's markers as spheres, those a
body holds coloured apart). Times: `log_time` and the messages' timestamps are the capture
time, on the wall clock when the caller gives one. Units: metres, quaternions x y z w
body-to-world, as everywhere in mocapd; the world is z-up (Foxglove's 3D panel and ROS
assume it), so a caller with a y-up take turns it first. Every file says so in a
metadata record `mocapd` (up_axis, length_unit, rotation, world_frame, and whatever the
caller adds, such as where the data came from and how it was turned).
"""

from __future__ import annotations

import contextlib
import json
import re
from pathlib import Path

import numpy as np

from calibkit.core.errors import UserError
from calibkit.core.fileio import atomic_write

WORLD_FRAME = "world"
AXES_METADATA = {"up_axis": "z", "length_unit": "m",
                 "rotation": "quaternion x y z w, body to world"}
MARKER_DIAMETER_M = 0.014
_FREE_JSON = '{"r":0.55,"g":0.55,"b":0.6,"a":1}'
_HELD_JSON = '{"r":0.1,"g":0.8,"b":0.3,"a":1}'
# messages as JSON templates: metres to 0.1 um (markers 1 um), quaternions to 1e-9
_STAMP = '"timestamp":{"sec":%d,"nsec":%d}'
_POSITION = '"position":{"x":%.7f,"y":%.7f,"z":%.7f}'
_ORIENTATION = '{"x":%.9f,"y":%.9f,"z":%.9f,"w":%.9f}'
_POSE_JSON = ("{" + _STAMP + ',"frame_id":"%s","pose":{' + _POSITION + ',"orientation":'
              + _ORIENTATION + "}}")
_TRANSFORM_JSON = ("{" + _STAMP + ',"parent_frame_id":"%s","child_frame_id":"%s",'
                   '"translation":{"x":%.7f,"y":%.7f,"z":%.7f},"rotation":' + _ORIENTATION
                   + "}")
_SPHERE_JSON = ('{"pose":{"position":{"x":%.6f,"y":%.6f,"z":%.6f},'
                '"orientation":{"x":0,"y":0,"z":0,"w":1}},'
                f'"size":{{"x":{MARKER_DIAMETER_M},"y":{MARKER_DIAMETER_M},'
                f'"z":{MARKER_DIAMETER_M}}},"color":%s}}')
_SCENE_JSON = ('{"deletions":[],"entities":[{' + _STAMP + ',"frame_id":"%s","id":"markers",'
               '"lifetime":{"sec":0,"nsec":0},"frame_locked":false,"spheres":[%s]}]}')

_TIME = {"type": "object", "properties": {"sec": {"type": "integer", "minimum": 0},
                                          "nsec": {"type": "integer", "minimum": 0}}}
_VEC3 = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_QUAT = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}
_POSE = {"type": "object", "properties": {"position": _VEC3, "orientation": _QUAT}}
_COLOR = {"type": "object", "properties": {k: {"type": "number"} for k in "rgba"}}

SCHEMAS = {
    "foxglove.FrameTransforms": {
        "title": "foxglove.FrameTransforms", "type": "object",
        "properties": {"transforms": {"type": "array", "items": {
            "type": "object", "properties": {
                "timestamp": _TIME, "parent_frame_id": {"type": "string"},
                "child_frame_id": {"type": "string"}, "translation": _VEC3,
                "rotation": _QUAT}}}}},
    "foxglove.PoseInFrame": {
        "title": "foxglove.PoseInFrame", "type": "object",
        "properties": {"timestamp": _TIME, "frame_id": {"type": "string"}, "pose": _POSE}},
    "foxglove.SceneUpdate": {
        "title": "foxglove.SceneUpdate", "type": "object",
        "properties": {
            "deletions": {"type": "array", "items": {"type": "object"}},
            "entities": {"type": "array", "items": {"type": "object", "properties": {
                "timestamp": _TIME, "frame_id": {"type": "string"},
                "id": {"type": "string"}, "lifetime": _TIME,
                "frame_locked": {"type": "boolean"},
                "spheres": {"type": "array", "items": {"type": "object", "properties": {
                    "pose": _POSE, "size": _VEC3, "color": _COLOR}}}}}}}},
}


def _topic_name(name: str) -> str:
    """A body name as a topic segment: letters, digits and underscores."""
    return re.sub(r"[^A-Za-z0-9_]", "_", name) or "body"


class McapPoseWriter:
    """Writes frames of poses (and markers) to an MCAP file, whole or not at all: the file
    appears at `path` on `close()`; `abort()` (or an exception inside `with`) leaves nothing."""

    def __init__(self, path: str | Path, body_names: list[str], markers: bool = True,
                 world_frame: str = WORLD_FRAME, metadata: dict[str, str] | None = None) -> None:
        # deferred on purpose: loads mcap only where used
        from mcap.writer import Writer

        self.path = Path(path)
        if self.path.suffix.lower() != ".mcap":
            raise UserError(f"{self.path}: an MCAP file ends in .mcap")
        if len(set(body_names)) != len(body_names):
            raise UserError("two bodies share a name; MCAP topics are named after bodies")
        self.names = list(body_names)
        self._json_names = [json.dumps(n)[1:-1] for n in self.names]
        world_frame = json.dumps(world_frame)[1:-1]
        self.world = world_frame
        self.frames = 0
        self._stack = contextlib.ExitStack()
        self._file = self._stack.enter_context(atomic_write(self.path, "wb"))
        self._writer = Writer(self._file)
        self._writer.start(profile="", library="mocapd")
        self._writer.add_metadata("mocapd", {**AXES_METADATA, "world_frame": world_frame,
                                             **{str(k): str(v) for k, v in
                                                (metadata or {}).items()}})
        schema = {name: self._writer.register_schema(
            name=name, encoding="jsonschema", data=json.dumps(s).encode())
            for name, s in SCHEMAS.items()}

        def channel(topic: str, schema_name: str) -> int:
            return self._writer.register_channel(topic=topic, message_encoding="json",
                                                 schema_id=schema[schema_name])

        self._tf = channel("/tf", "foxglove.FrameTransforms")
        self._pose = [channel(f"/mocap/{_topic_name(n)}/pose", "foxglove.PoseInFrame")
                      for n in self.names]
        self._markers = channel("/mocap/markers", "foxglove.SceneUpdate") if markers else None

    def _put(self, channel: int, t_ns: int, message: str) -> None:
        self._writer.add_message(channel_id=channel, log_time=int(t_ns),
                                 publish_time=int(t_ns), sequence=self.frames,
                                 data=message.encode())

    def write(self, t_ns: int, valid: np.ndarray, xyz: np.ndarray, quat_xyzw: np.ndarray,
              markers_xyz: np.ndarray | None = None, held: np.ndarray | None = None) -> None:
        """One frame: per body (B,) valid, (B, 3) positions, (B, 4) quaternions; optionally
        (M, 3) markers (NaN rows skipped) and (M,) whether a body holds each. The JSON is
        formatted from templates in one call per message (a take has hundreds of thousands
        of messages; json.dumps of nested dicts was most of the time)."""
        sec, nsec = divmod(max(int(t_ns), 0), 1_000_000_000)
        bodies = np.flatnonzero(valid)
        if len(bodies):
            poses = []
            for b in bodies:
                values = (sec, nsec, self.world, *xyz[b], *quat_xyzw[b])
                poses.append(_POSE_JSON % values)
                self._put(self._pose[b], t_ns, poses[-1])
            transforms = ",".join(
                _TRANSFORM_JSON % (sec, nsec, self.world, self._json_names[b], *xyz[b],
                                   *quat_xyzw[b]) for b in bodies)
            self._put(self._tf, t_ns, '{"transforms":[' + transforms + "]}")
        if self._markers is not None and markers_xyz is not None:
            seen = np.isfinite(markers_xyz).all(axis=1)
            held = np.zeros(len(markers_xyz), bool) if held is None else np.asarray(held, bool)
            n = int(seen.sum())
            args = np.empty((n, 4), dtype=object)
            args[:, :3] = markers_xyz[seen]
            args[:, 3] = np.where(held[seen], _HELD_JSON, _FREE_JSON)
            spheres = ((_SPHERE_JSON + ",") * n)[:-1] % tuple(args.ravel()) if n else ""
            self._put(self._markers, t_ns, _SCENE_JSON % (sec, nsec, self.world, spheres))
        self.frames += 1

    def close(self) -> None:
        """Finish the file and put it in place."""
        if self._writer is None:
            return
        self._writer.finish()
        self._writer = None
        self._stack.close()

    def abort(self) -> None:
        """Drop what was written: no file appears."""
        if self._writer is None:
            return
        self._writer = None
        self._stack.__exit__(RuntimeError, RuntimeError("aborted"), None)

    def __enter__(self) -> McapPoseWriter:
        return self

    def __exit__(self, kind, exc, tb) -> None:
        if kind is None:
            self.close()
        else:
            self.abort()


def write_poses_mcap(path: str | Path, table, markers_xyz: np.ndarray | None = None,
                     start_ns: int = 0, progress=None,
                     metadata: dict[str, str] | None = None) -> int:
    """A PoseTable (and optionally (F, M, 3) markers) in a z-up world as MCAP, frame times
    `start_ns` + the table's seconds; the number of frames written."""
    with McapPoseWriter(path, table.names, markers=markers_xyz is not None,
                        metadata=metadata) as out:
        for f in range(len(table.frame)):
            out.write(start_ns + round(float(table.t_s[f]) * 1e9), table.valid[f],
                      table.xyz[f], table.quat[f],
                      None if markers_xyz is None else markers_xyz[f])
            if progress is not None:
                progress(f + 1)
    return len(table.frame)
