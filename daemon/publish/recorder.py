"""Recording output: each frame's blobs appended to a .mcrec recording (calibkit.core.recording)."""

from __future__ import annotations

from calibkit.core.recording import RecordingWriter
from daemon.publish.base import Publisher


class RecorderPublisher(Publisher):
    """Writes every frame it is handed; a deep queue, since a recording should be whole."""

    def __init__(self, path, rig, fps: float | None = None) -> None:
        super().__init__(queue_size=4096, retry_s=5.0)
        self.path, self.rig, self.fps = path, rig, fps
        self.name = f"record:{path}"
        self.writer: RecordingWriter | None = None

    def open(self) -> None:
        self.writer = RecordingWriter(self.path, self.rig.names, [c.size for c in self.rig],
                                      self.fps, meta={"source": "mocapd"})

    def send(self, result) -> None:
        for s in result.samples or ():
            self.writer.append(result.frame, s.camera, s.t_ns, s.uv, s.area, s.peak)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None
