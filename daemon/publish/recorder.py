"""Recording output: each frame's blobs appended to a .mcrec recording (calibkit.core.recording)."""

from __future__ import annotations

from calibkit.core.recording import RecordingWriter
from daemon.publish.recording_output import RecordingOutput


class RecorderPublisher(RecordingOutput):
    """Writes every frame it is handed, once (daemon.publish.recording_output)."""

    def __init__(self, path, rig, fps: float | None = None, min_free_mb: float = 0.0) -> None:
        super().__init__(path, min_free_mb)
        self.rig, self.fps = rig, fps
        self.writer: RecordingWriter | None = None

    def open(self) -> None:
        self.writer = RecordingWriter(self.path, self.rig.names, [c.size for c in self.rig],
                                      self.fps, meta={"source": "mocapd"})

    def send(self, result) -> None:
        for s in result.samples or ():
            self.writer.append(result.frame, s.camera, s.t_ns, s.uv, s.area, s.peak)

    def close(self) -> None:
        if self.writer is not None:
            writer, self.writer = self.writer, None
            writer.close()
