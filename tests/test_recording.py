"""Recordings and CSV files: round trips, a recording cut off mid-write, and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from calibkit.core.camera import Camera, Rig
from calibkit.core.errors import UserError
from calibkit.core.observations import Observations, Truth
from calibkit.core.recording import (
    RecordingWriter,
    load_observations,
    load_truth_csv,
    save_observations,
    truth_path_for,
)


def _obs(n_frames=20, n_cams=3, per=5, seed=0) -> tuple[Observations, Truth]:
    rng = np.random.default_rng(seed)
    n = n_frames * n_cams * per
    frame = np.repeat(np.arange(n_frames), n_cams * per)
    camera = np.tile(np.repeat(np.arange(n_cams), per), n_frames)
    obs = Observations([f"cam{i}" for i in range(n_cams)], [(640, 480)] * n_cams, frame, camera,
                       frame * 10_000_000 + camera * 17, rng.uniform(0, 639, (n, 2)),
                       rng.uniform(4, 40, n), rng.uniform(30, 255, n),
                       np.tile(np.arange(per), n_frames * n_cams), fps=100.0)
    truth = Truth(np.repeat(np.arange(n_frames), per), np.tile(np.arange(per), n_frames),
                  rng.uniform(-2, 2, (n_frames * per, 3)))
    return obs, truth


def _same(a: Observations, b: Observations, uv_tol: float) -> None:
    a, b = a.sorted(), b.sorted()
    assert a.camera_names == b.camera_names
    assert np.array_equal(a.frame, b.frame) and np.array_equal(a.camera, b.camera)
    assert np.array_equal(a.t_ns, b.t_ns)
    assert np.max(np.abs(a.uv - b.uv)) <= uv_tol
    assert np.array_equal(a.marker, b.marker)


@pytest.mark.parametrize("suffix", [".mcrec", ".csv"])
def test_round_trip_with_truth(tmp_path, suffix) -> None:
    obs, truth = _obs()
    path = tmp_path / f"capture{suffix}"
    save_observations(path, obs, truth)
    back, back_truth = load_observations(path)
    _same(obs, back, 5e-5)
    assert back_truth is not None
    assert np.max(np.abs(back_truth.xyz - truth.xyz)) < 1e-8
    if suffix == ".csv":
        assert truth_path_for(path).name == "capture.truth.csv"
        assert load_truth_csv(truth_path_for(path)).xyz.shape == truth.xyz.shape
    else:
        assert back.camera_sizes == obs.camera_sizes and back.fps == 100.0


def test_killed_recording_reads_up_to_last_complete_frame(tmp_path) -> None:
    path = tmp_path / "live.mcrec"
    writer = RecordingWriter(path, ["a", "b"], [(640, 480), (640, 480)], fps=60)
    for f in range(10):
        for c in range(2):
            writer.append(f, c, f * 1000, [[f, c], [f + 0.5, c + 0.5]], [3, 3], [200, 200])
    writer.close()
    data = path.read_bytes()
    path.write_bytes(data[:-7])  # killed in the middle of the last record
    obs, _ = load_observations(path)
    assert obs.frames().tolist() == list(range(10))
    assert np.sum(obs.frame == 9) == 2  # frame 9 lost only its torn camera record
    # the file is readable while it is being written, too
    writer = RecordingWriter(tmp_path / "open.mcrec", ["a"], [(10, 10)])
    writer.append(0, "a", 0, [[1, 2]])
    assert len(load_observations(tmp_path / "open.mcrec")[0]) == 1
    writer.close()


def test_csv_checked_against_rig(tmp_path) -> None:
    rig = Rig((Camera("left", (640, 480), 500, 500, 320, 240),
               Camera("right", (800, 600), 500, 500, 400, 300)))
    path = tmp_path / "obs.csv"
    path.write_text("frame,camera,t_ns,u,v,area,peak\n0,left,0,1.5,2.5,9,200\n"
                    "0,right,5,3,4,9,180\n")
    obs, truth = load_observations(path, rig)
    assert truth is None and obs.camera_names == ("left", "right")
    assert obs.camera_sizes == ((640, 480), (800, 600)) and obs.uv[1].tolist() == [3.0, 4.0]
    path.write_text("frame,camera,t_ns,u,v,area,peak\n0,middle,0,1,2,9,200\n")
    with pytest.raises(UserError, match=r"line 2, column 'camera': camera 'middle'"):
        load_observations(path, rig)


@pytest.mark.parametrize("text, message", [
    ("frame,camera,u,v\n0,a,1,2\n", "missing column"),
    ("frame,camera,t_ns,u,v,area,peak\n0,a,0,1,oops,3,4\n", "line 2, column 'v'"),
    ("frame,camera,t_ns,u,v,area,peak\n0,a,0,1\n", "line 2: 4 fields"),
    ("", "empty file"),
])
def test_bad_csv_gives_one_line(tmp_path, text, message) -> None:
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(UserError, match=message) as info:
        load_observations(path)
    assert "\n" not in str(info.value)


def test_not_a_recording(tmp_path) -> None:
    path = tmp_path / "x.mcrec"
    path.write_text("hello\n")
    with pytest.raises(UserError, match="not a calibkit recording"):
        load_observations(path)
    with pytest.raises(UserError, match="no such file"):
        load_observations(tmp_path / "missing.mcrec")
