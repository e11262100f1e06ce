"""`mocapd evaluate`: clock, frame and pose errors recovered against a simulated flight."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibkit.core.errors import UserError
from daemon.analysis.trajectory_eval import evaluate, figures, umeyama
from daemon.formats.trajectory_io import Trajectory, read_trajectory, write_tum
from daemon.synthetic.trajectory import flight


def _alignment_error(ev, truth, xyz):
    """How far the fitted alignment puts points of the flight from where the true one does
    (RMS over the path, m), and its rotation error (deg)."""
    ours = ev.alignment.apply(xyz)
    true = truth.scale * xyz @ truth.R.T + truth.t
    rms = float(np.sqrt(np.mean(np.sum((ours - true) ** 2, axis=1))))
    angle = float(np.degrees(Rotation.from_matrix(ev.alignment.R.T @ truth.R).magnitude()))
    return rms, angle


@pytest.mark.parametrize("seed", [0, 1])
def test_offset_drift_and_alignment_are_recovered(seed):
    mocap, robot, truth = flight(duration_s=40.0, noise_m=0.001, drift_ppm=50.0, seed=seed)
    ev = evaluate(mocap, robot)
    assert abs(ev.time.offset_s - truth.offset_s) < 1e-3
    assert abs(ev.time.drift - truth.drift) < 10e-6
    rms, angle = _alignment_error(ev, truth, robot.xyz)
    assert rms < 1e-4 and angle < 0.01
    # both logs carry 1 mm per axis: their difference is sqrt(2 * 3) mm RMS in 3D
    f = figures(ev)
    assert f["ate_position_mm"]["rms"] == pytest.approx(np.sqrt(6.0), rel=0.1)
    assert f["ate_position_mm"]["gross"] == 0
    assert f["poses_compared"] > 0.9 * len(robot) * 120 / 50 * 0.9


def test_a_scaled_estimate_needs_and_gets_a_scale():
    mocap, robot, truth = flight(duration_s=30.0, scale=0.8, drift_ppm=0.0, seed=3)
    rigid = figures(evaluate(mocap, robot))
    ev = evaluate(mocap, robot, with_scale=True)
    assert ev.alignment.scale == pytest.approx(0.8, rel=1e-4)
    assert figures(ev)["ate_position_mm"]["rms"] < 3.0
    assert rigid["ate_position_mm"]["rms"] > 50.0  # without the scale it cannot fit


def test_blunders_are_counted_and_do_not_bend_the_fit():
    mocap, robot, truth = flight(duration_s=40.0, drift_ppm=0.0, seed=4)
    xyz = robot.xyz.copy()
    jump = (robot.t_s > 20.0) & (robot.t_s < 21.0)
    xyz[jump] += [0.3, 0.0, 0.0]  # the robot's estimator lost itself for a second
    bad = Trajectory(robot.t_s, xyz, robot.quat, "robot")
    ev = evaluate(mocap, bad)
    f = figures(ev, gross_mm=50.0)
    assert f["ate_position_mm"]["gross"] >= 0.8 * jump.sum() * 120 / 50
    rms, _ = _alignment_error(ev, truth, robot.xyz)
    assert rms < 2e-4
    assert abs(ev.time.offset_s - truth.offset_s) < 1e-3


def test_a_known_offset_is_taken_as_given():
    mocap, robot, truth = flight(duration_s=20.0, drift_ppm=0.0, seed=5)
    ev = evaluate(mocap, robot, known_offset_s=truth.offset_s, fit_drift=False)
    assert ev.time.offset_s == truth.offset_s and ev.coarse_offset_s == truth.offset_s
    assert figures(ev)["ate_position_mm"]["rms"] < 3.0


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    R = Rotation.from_rotvec([0.3, -1.0, 2.0]).as_matrix()
    dst = 1.7 * src @ R.T + [1.0, 2.0, 3.0]
    a = umeyama(src, dst, with_scale=True)
    assert np.allclose(a.R, R) and a.scale == pytest.approx(1.7)
    assert np.allclose(a.t, [1.0, 2.0, 3.0])


def _write_csv(path, traj, body="drone", t_col="t_s", t_scale=1.0, extra=None):
    lines = [f"{t_col},body,x,y,z,qx,qy,qz,qw"]
    for i in range(len(traj)):
        values = [traj.t_s[i] * t_scale, *traj.xyz[i], *traj.quat[i]]
        text = [repr(float(v)) for v in values]
        lines.append(",".join([text[0], body, *text[1:]]))
    if extra:
        lines += extra
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def test_readers_take_tum_and_csv_alike(tmp_path):
    mocap, _, _ = flight(duration_s=5.0, seed=6)
    write_tum(tmp_path / "a.tum", mocap)
    _write_csv(tmp_path / "b.csv", mocap, t_col="timestamp_ns", t_scale=1e9)
    a = read_trajectory(tmp_path / "a.tum")
    b = read_trajectory(tmp_path / "b.csv")
    assert np.allclose(a.t_s, mocap.t_s, atol=1e-8) and np.allclose(b.t_s, mocap.t_s,
                                                                    atol=1e-6)
    assert np.allclose(a.xyz, mocap.xyz, atol=1e-8) and np.allclose(b.quat, mocap.quat)
    mm = read_trajectory(tmp_path / "a.tum", units="mm")
    assert np.allclose(mm.xyz, mocap.xyz / 1000.0, atol=1e-9)


@pytest.mark.parametrize("content, message", [
    ("1 2 3\n" * 20, "8 numbers"),
    ("# only comments\n", "0 valid poses"),
    ("t_s,x,y,z\n0,1,2,3\n", "no column for qx"),
    ("".join(f"{i % 5} 0 0 0 0 0 0 1\n" for i in range(20)), "share a timestamp"),
    ("".join(f"{i} 0 0 0 0 0 0 3\n" for i in range(20)), "quaternion of length"),
])
def test_bad_files_are_named_in_one_line(tmp_path, content, message):
    path = tmp_path / "bad.txt"
    path.write_text(content, encoding="utf-8")
    with pytest.raises(UserError, match=message):
        read_trajectory(path)


def test_the_command_scores_a_flight_and_writes_its_report(tmp_path):
    from typer.testing import CliRunner

    from daemon.cli import app

    mocap, robot, truth = flight(duration_s=30.0, seed=7)
    _write_csv(tmp_path / "mocap.csv", mocap, extra=[])
    write_tum(tmp_path / "robot.tum", robot)
    res = CliRunner().invoke(app, [
        "evaluate", str(tmp_path / "mocap.csv"), str(tmp_path / "robot.tum"),
        "--json", str(tmp_path / "e.json"), "--html", str(tmp_path / "e.html"),
        "--plot", str(tmp_path / "e.png"), "--errors", str(tmp_path / "e.csv")])
    assert res.exit_code == 0, res.output
    figs = json.loads((tmp_path / "e.json").read_text())
    assert abs(figs["time"]["offset_s"] - truth.offset_s) < 1e-3
    assert "position error RMS" in res.output
    page = (tmp_path / "e.html").read_text()
    assert 'id="figures"' in page and "data:image/png;base64," in page
    assert (tmp_path / "e.png").read_bytes()[:4] == b"\x89PNG"
    rows = (tmp_path / "e.csv").read_text().splitlines()
    assert rows[0] == "t_s,position_error_mm,orientation_error_deg"
    assert len(rows) - 1 == figs["poses_compared"]


def test_the_command_refuses_what_it_cannot_score(tmp_path):
    from typer.testing import CliRunner

    from daemon.cli import app

    mocap, robot, _ = flight(duration_s=10.0, seed=8)
    _write_csv(tmp_path / "two.csv", mocap, extra=[
        f"{mocap.t_s[0]},other,0,0,0,0,0,0,1"])
    write_tum(tmp_path / "robot.tum", robot)
    later = Trajectory(robot.t_s + 100.0, robot.xyz, robot.quat)
    write_tum(tmp_path / "later.tum", later)
    runner = CliRunner()
    for args, message in [
        (["two.csv", "robot.tum"], "choose one with --body"),
        (["two.csv", "robot.tum", "--ref-body", "ghost"], "has no body 'ghost'"),
        (["robot.tum", "missing.tum"], "missing.tum not found"),
        (["robot.tum", "later.tum"], "do not overlap in time"),
        (["robot.tum", "robot.tum", "--delta", "0"], "must be positive"),
    ]:
        res = runner.invoke(app, ["evaluate", *[str(tmp_path / a) if a.endswith(
            (".csv", ".tum")) else a for a in args]])
        assert res.exit_code != 0
        assert isinstance(res.exception, UserError) and message in str(res.exception), \
            (args, res.exception)
