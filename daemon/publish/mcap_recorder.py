"""Recording output as MCAP: each frame's body poses and markers, for Foxglove and other MCAP
readers (daemon/publish/mcap_poses.py), where a .mcrec keeps the blobs for replay."""

from __future__ import annotations

import time

from daemon.publish.mcap_poses import McapPoseWriter
from daemon.publish.recording_output import RecordingOutput


class McapRecorderPublisher(RecordingOutput):
    """Writes every frame it is handed, once (daemon.publish.recording_output). Times are
    the frames' capture times moved onto the wall clock."""

    def __init__(self, path, body_names: list[str], min_free_mb: float = 0.0) -> None:
        super().__init__(path, min_free_mb)
        self.body_names = list(body_names)
        self.writer: McapPoseWriter | None = None
        self._wall_offset_ns = time.time_ns() - time.monotonic_ns()

    def open(self) -> None:
        self.writer = McapPoseWriter(self.path, self.body_names)

    def send(self, result) -> None:
        poses, tracks = result.poses, result.tracks
        held = result.held_by_bodies()
        self.writer.write(int(result.t_ns) + self._wall_offset_ns, poses.valid,
                          poses.position, poses.quaternion, tracks.xyz[tracks.seen],
                          held[tracks.seen])

    def close(self) -> None:
        if self.writer is not None:
            writer, self.writer = self.writer, None
            writer.close()
