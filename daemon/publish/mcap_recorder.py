"""Recording output as MCAP: each frame's body poses and markers, for Foxglove and other MCAP
readers (daemon/publish/mcap_poses.py), where a .mcrec keeps the blobs for replay."""

from __future__ import annotations

import time

from daemon.publish.base import Publisher
from daemon.publish.mcap_poses import McapPoseWriter


class McapRecorderPublisher(Publisher):
    """Writes every frame it is handed; a deep queue, since a recording should be whole.
    Times are the frames' capture times moved onto the wall clock."""

    def __init__(self, path, body_names: list[str]) -> None:
        super().__init__(queue_size=4096, retry_s=5.0)
        self.path, self.body_names = path, list(body_names)
        self.name = f"record:{path}"
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
            self.writer.close()
            self.writer = None
