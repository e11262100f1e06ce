"""The frame loop's cuts of issue 33 change nothing: on the simulator, every frame's
gathered blobs carry their own camera's index, the rigid tracker's kept marker rows equal
a fresh search, and the bodies are tracked against the simulator's truth as before."""

from __future__ import annotations

import numpy as np

from daemon.capture.pipeline import Pipeline
from daemon.config.mocapd import load_config
from daemon.service.daemon import Daemon


def test_gathered_cameras_and_kept_rows_match_a_fresh_computation(tmp_path, monkeypatch):
    conf = tmp_path / "sim.toml"
    conf.write_text(f'runtime_dir = "{tmp_path / "run"}"\n[sim]\ncameras = 5\nbodies = 3\n'
                    'realtime = false\n')
    checked = {"frames": 0, "rows": 0, "blobs": 0}
    process = Pipeline.process

    def process_and_check(self, fs):
        result = process(self, fs)
        want = [np.full(len(s.uv), s.camera) for s in fs.samples]
        want = np.concatenate(want) if want else np.zeros(0, np.int64)
        assert result.camera.dtype == np.int64
        np.testing.assert_array_equal(result.camera, want)
        checked["blobs"] += len(want)
        rigid = self.rigid
        if rigid._last_rows is not None and rigid._last_rows[0] is result.tracks:
            np.testing.assert_array_equal(rigid._last_rows[1],
                                          rigid._rows(result.tracks, rigid.assigned))
            checked["rows"] += 1
        checked["frames"] += 1
        return result

    monkeypatch.setattr(Pipeline, "process", process_and_check)
    figures = Daemon(load_config(conf), None).run(frames=600)
    assert checked["frames"] >= 600 and checked["rows"] >= 590 and checked["blobs"] > 1000
    truth = figures["truth"]
    assert truth["position_error_mm_rms"] < 2.0, truth
    assert min(b["valid_fraction"] for b in truth["bodies"].values()) > 0.8, truth
