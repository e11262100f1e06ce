"""`mocapd track`: rigid bodies from 3D marker files, against Motive, the truth and the
daemon's own rigid tracker called frame by frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import tomli_w

from calibkit.synthetic import sim
from daemon.analysis.offline_track import (
    cloud_from_points,
    rotation_difference_deg,
    track_cloud,
)
from daemon.analysis.point_tracks import PointTrackConfig, associate
from daemon.formats.c3dio import Points, Take, read_points_csv, write_points_csv
from daemon.formats.motive_csv import read_motive_csv, to_z_up
from daemon.formats.trajectory_io import read_poses_csv, read_trajectory
from daemon.synthetic.labelling import hide_spans
from daemon.synthetic.motive_export import displaced, write_motive_1_0
from daemon.tracking.rigid import (
    BodyDef,
    RigidConfig,
    RigidTracker,
    matrix_from_quaternion,
    quaternion_xyzw,
)

DATA = Path(__file__).resolve().parent.parent / "fixtures" / "optitrack_rigidbody_csv"
RATE = 120.0


def capture(n_frames=600, noise_m=0.0005, hidden=0.05, strays=2, seed=0,
            markers=(4, 5, 3, 4)):
    """A simulated take of rigid bodies as 3D points: shuffled within each frame, noisy,
    with occlusion spans and stray points. Returns (Points, bodies, visible (F, K))."""
    truth, bodies = sim.rigid_body_motion(len(markers), n_frames, fps=RATE,
                                          markers_per_body=list(markers), seed=seed)
    k = int(truth.marker.max()) + 1
    xyz = np.full((n_frames, k, 3), np.nan)
    xyz[truth.frame, truth.marker] = truth.xyz
    take = hide_spans(Take([str(i) for i in range(k)], xyz, RATE), hidden, seed=seed + 1)
    rng = np.random.default_rng(seed + 2)
    noisy = take.xyz_m + rng.normal(0.0, noise_m, take.xyz_m.shape)
    pts = Points.from_take(Take(take.labels, noisy, RATE), seed=seed + 3)
    stray_frame = np.repeat(np.arange(n_frames), strays)
    stray_xyz = rng.uniform([-1.5, -1.5, 0.2], [1.5, 1.5, 2.0], (len(stray_frame), 3))
    pts = Points(np.concatenate([pts.frame, stray_frame]),
                 np.concatenate([pts.xyz_m, stray_xyz]))
    return pts, bodies, np.isfinite(take.xyz_m).all(axis=2)


def body_defs(bodies) -> list[BodyDef]:
    return [BodyDef(b.name, b.id, b.markers_body, np.zeros(3),
                    min(len(b.markers_body), 4) if len(b.markers_body) >= 4 else 3, 3, 0.0)
            for b in bodies]


def write_config(path: Path, bodies) -> Path:
    tables = [{"name": b.name, "id": int(b.id), "markers": b.markers_body.tolist()}
              for b in bodies]
    path.write_text(tomli_w.dumps({"rigid_body": tables}))
    return path


def predicted_rms(body, visible: np.ndarray, noise_m: float):
    """The pose errors a least-squares fit of the body's visible markers gives under
    isotropic noise (per axis noise_m), frame by frame: position of the pivot (the body
    origin) in m and rotation in rad, as RMS over the frames given. The rotation's
    covariance is noise^2 J^-1 with J = sum |d|^2 I - d d^T over the markers' offsets d
    from their centroid; the pivot adds the rotation's error times its lever arm."""
    m = body.markers_body
    pos2, ang2 = [], []
    for vis in visible:
        d = m[vis] - m[vis].mean(axis=0)
        J = np.sum(np.einsum("ki,ki->k", d, d)) * np.eye(3) - d.T @ d
        cov = np.linalg.inv(J) * noise_m ** 2
        c = m[vis].mean(axis=0)
        C = np.array([[0, -c[2], c[1]], [c[2], 0, -c[0]], [-c[1], c[0], 0]])
        pos2.append(3 * noise_m ** 2 / vis.sum() + np.trace(C @ cov @ C.T))
        ang2.append(np.trace(cov))
    return np.sqrt(np.mean(pos2)), np.sqrt(np.mean(ang2))


def test_simulated_capture_poses_against_the_truth(tmp_path, mocapd_cli):
    noise_m = 0.0005
    pts, bodies, visible = capture(n_frames=900, noise_m=noise_m)
    src = tmp_path / "points.csv"
    write_points_csv(src, pts)
    out = tmp_path / "poses.csv"
    r = mocapd_cli("track", src, "--bodies", write_config(tmp_path / "m.toml", bodies),
                   "--rate", RATE, "--out", out, "--json", tmp_path / "f.json")
    assert r.code == 0, r.err
    table = read_poses_csv(out)
    assert table.names == [b.name for b in bodies]
    np.testing.assert_allclose(table.t_s, np.arange(900) / RATE, atol=1e-6)
    start = 0
    for b, body in enumerate(bodies):
        k = len(body.markers_body)
        vis = visible[:, start:start + k]
        start += k
        v = table.valid[:, b]
        # valid wherever enough markers to start it are seen (four, or three of a
        # three-marker body; with fewer a body only keeps going), after the first frames
        enough = vis.sum(axis=1) >= min(k, 4)
        assert v[5:][enough[5:]].mean() > 0.99, body.name
        dp = np.linalg.norm(table.xyz[v, b] - body.poses[v, :3, 3], axis=1)
        da = np.radians(rotation_difference_deg(table.quat[v, b],
                                                quaternion_xyzw(body.poses[v, :3, :3])))
        want_p, want_a = predicted_rms(body, vis[v], noise_m)
        # every valid pose counted; 1.3x the least-squares prediction (its RMS over ~900
        # frames is known to a few per cent; the margin covers markers released as outliers)
        assert np.sqrt(np.mean(dp ** 2)) < 1.3 * want_p, (body.name, dp, want_p)
        assert np.sqrt(np.mean(da ** 2)) < 1.3 * want_a, (body.name, da, want_a)
        assert dp.max() < 0.02  # no pose on a wrong marker
    # the poses file is what `mocapd evaluate` reads
    traj = read_trajectory(out, body=bodies[0].name)
    assert len(traj) == table.valid[:, 0].sum()


def test_command_output_is_the_rigid_tracker_called_frame_by_frame(tmp_path, mocapd_cli):
    """The poses `mocapd track` writes are those of the daemon's RigidTracker.update() on
    the same tracks, frame by frame, with the same settings; a body that is not in the
    take (only strays to search among) and occlusions exercise every branch."""
    pts, bodies, _ = capture(n_frames=500, strays=3, seed=4)
    defs = body_defs(bodies)
    absent = sim.rigid_body_motion(5, 2, fps=RATE, markers_per_body=4, seed=9)[1][4]
    config_bodies = bodies + [sim.SimBody("absent", 99, absent.markers_body, absent.poses,
                                          absent.marker_ids)]
    src = tmp_path / "points.csv"
    write_points_csv(src, pts)
    out = tmp_path / "poses.csv"
    r = mocapd_cli("track", src, "--bodies", write_config(tmp_path / "m.toml", config_bodies),
                   "--rate", RATE, "--out", out)
    assert r.code == 0, r.err
    table = read_poses_csv(out)

    cloud = cloud_from_points(read_points_csv(src), RATE)  # the markers the command read
    tracks = associate(cloud.xyz, cloud.counts(), cloud.frame, PointTrackConfig())
    rigid = RigidTracker(defs + [BodyDef("absent", 99, absent.markers_body, np.zeros(3))],
                         RigidConfig(refine=False))
    direct = [rigid.update(tracks.tracks_at(f)) for f in range(len(cloud))]
    valid = np.array([p.valid for p in direct])
    np.testing.assert_array_equal(table.valid, valid)
    assert not valid[:, -1].any() and valid[:, :-1].mean() > 0.9
    pos = np.array([p.position for p in direct])
    quat = np.array([p.quaternion for p in direct])
    np.testing.assert_allclose(table.xyz[valid], pos[valid], rtol=0, atol=6e-8)  # 0.1 um
    np.testing.assert_allclose(table.quat[valid], quat[valid], rtol=0, atol=6e-9)
    np.testing.assert_array_equal(table.markers, np.array([p.n_markers for p in direct]))

    # the runs fitted at once give exactly what update() gives
    all_defs = defs + [BodyDef("absent", 99, absent.markers_body, np.zeros(3))]
    fast = track_cloud(cloud, all_defs)
    slow = track_cloud(cloud, all_defs, batched=False)
    np.testing.assert_array_equal(fast.valid, slow.valid)
    np.testing.assert_array_equal(fast.position, slow.position)
    np.testing.assert_array_equal(fast.quaternion, slow.quaternion)
    np.testing.assert_array_equal(fast.error_m, slow.error_m)


def test_real_motive_export_tracked_with_its_own_definition(tmp_path, mocapd_cli):
    """v1.1.csv: Motive's raw markers (every reconstructed one, as an anonymous cloud) and
    its body definition; our poses against the ones Motive solved.

    Measured: from frame 266 on (found again with Marker4 in view), 0.13 mm median / 1.1 mm worst in
    position and 1.3 deg median / 4.9 deg worst in orientation. The orientation offset is
    Motive's, not noise: the template it fitted per frame (its rigidbody rows) sits up to
    1.1 mm from the definition it exported, on markers 60-90 mm from the centre
    (atan(1.1 / 50) = 1.3 deg). Frames 0-261 see Markers 1, 2, 3 and 5 only (the body is
    found there and kept until both lose it at frame 266), and with
    Marker4 gone the definition is symmetric within the identification tolerance
    (swapping Markers 2 and 3 changes no distance by more than 2 mm): the distances alone
    cannot tell the body from itself turned half over, and the fit with the smaller
    residual is the turned one. Motive keeps the right one from its history. So the test
    holds the unambiguous frames to the agreement measured (with margin) and checks that
    the others are exactly the ambiguous stretch, fitted on the measured markers."""
    out = tmp_path / "poses.csv"
    r = mocapd_cli("track", DATA / "v1.1.csv", "--bodies-from-file", "--out", out,
                   "--json", tmp_path / "f.json")
    assert r.code == 0, r.err
    motive = to_z_up(read_motive_csv(DATA / "v1.1.csv"))  # our poses are z-up
    theirs = motive.poses["Rigid Body 1"]
    ours = read_poses_csv(out)
    both = ours.valid[:, 0] & theirs.valid
    dp = np.linalg.norm(ours.xyz[:, 0] - theirs.xyz_m, axis=1) * 1000
    da = rotation_difference_deg(ours.quat[:, 0], theirs.quat_xyzw)
    lost = int(np.argmin(theirs.valid))  # frame 266: both lose the body, then find it anew
    seen4 = np.isfinite(motive.labelled_m[:, motive.labels.index("Rigid Body 1:Marker4")]
                        ).all(axis=1)
    assert lost == 266 and not seen4[:262].any() and seen4[271]
    clear = both & (np.arange(len(both)) >= lost)
    assert clear.sum() >= 250
    assert np.median(dp[clear]) < 0.3 and dp[clear].max() < 2.5
    assert np.median(da[clear]) < 2.0 and da[clear].max() < 7.0
    turned = both & ~clear
    assert turned.sum() == lost
    assert np.all(da[turned] > 170)  # half a turn: the mirror-symmetric reading
    assert np.nanmax(ours.error_mm[turned, 0]) < 2.0  # and a fit as good as the right one
    # Motive's own agreement figures, as the command reports them
    import json
    figs = json.loads((tmp_path / "f.json").read_text())
    vs = figs["against_motive"]["Rigid Body 1"]
    assert vs["frames_both"] == both.sum() and vs["gross"] == turned.sum()


def test_modern_motive_export_and_motive_out_round_trip(tmp_path, mocapd_cli):
    """The 1.21 sample (a static body, three markers): our pose is Motive's to within its
    static noise; --motive-out writes our take in Motive's layout, which reads back."""
    out, again = tmp_path / "poses.csv", tmp_path / "ours_motive.csv"
    r = mocapd_cli("track", DATA / "sample_optitrack_take.csv", "--from-motive", "--out", out,
                   "--motive-out", again)
    assert r.code == 0, r.err
    motive = to_z_up(read_motive_csv(DATA / "sample_optitrack_take.csv"))
    ours = read_poses_csv(out)
    assert ours.valid.all()
    dp = np.linalg.norm(ours.xyz[:, 0] - motive.poses["Rigid Body 1"].xyz_m, axis=1)
    da = rotation_difference_deg(ours.quat[:, 0], motive.poses["Rigid Body 1"].quat_xyzw)
    assert np.median(dp) < 1e-4 and np.median(da) < 0.05  # measured 0.06 mm, 0.006 deg
    back = read_motive_csv(again)
    assert back.up_axis == "y"  # written in the input's own (Motive's) world, and says so
    np.testing.assert_allclose(to_z_up(back).poses["Rigid Body 1"].xyz_m, ours.xyz[:, 0],
                               atol=1e-6)
    assert back.unlabelled_m.shape[1] == 6  # every measured marker, as unlabelled


@pytest.mark.parametrize("args, message", [
    (["missing.csv", "--bodies", "m.toml"], "missing.csv not found"),
    (["points.txt", "--bodies", "m.toml"], "markers are read from .csv"),
    (["points.csv"], "give the bodies to track"),
    (["points.csv", "--bodies", "m.toml", "--bodies-from-file"], "give the bodies to track"),
    (["points.csv", "--bodies", "m.toml"], "has no frame rate"),
    (["points.csv", "--bodies-from-file", "--rate", "120"], "is not a Motive CSV"),
    (["points.csv", "--bodies", "empty.toml", "--rate", "120"], "defines no [[rigid_body]]"),
    (["points.csv", "--bodies", "m.toml", "--rate", "-1"], "--rate must be positive"),
    (["junk.csv", "--bodies", "m.toml", "--rate", "120"], "missing column"),
])
def test_bad_inputs_one_line_and_exit_2(tmp_path, mocapd_cli, args, message):
    pts, bodies, _ = capture(n_frames=20, seed=1)
    write_points_csv(tmp_path / "points.csv", pts)
    (tmp_path / "points.txt").write_text("x")
    (tmp_path / "junk.csv").write_text("a,b\n1,2\n")
    (tmp_path / "empty.toml").write_text("")
    write_config(tmp_path / "m.toml", bodies)
    out = tmp_path / "poses.csv"
    r = mocapd_cli("track", *[str(tmp_path / a) if a.endswith((".csv", ".txt", ".toml"))
                              else a for a in args], "--out", out)
    assert r.code == 2, (r.code, r.err)
    lines = r.err.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], r.err
    assert not out.exists()


def test_out_must_not_be_the_input(tmp_path, mocapd_cli):
    pts, bodies, _ = capture(n_frames=20, seed=1)
    src = tmp_path / "points.csv"
    write_points_csv(src, pts)
    before = src.read_text()
    r = mocapd_cli("track", src, "--bodies", write_config(tmp_path / "m.toml", bodies),
                   "--rate", 120, "--out", src)
    assert r.code == 2 and "is the input file" in r.err
    assert src.read_text() == before


# ---- definitions that do not match their markers, a body that is not there --------------

def within(table, b, R_true, p_true, frames) -> np.ndarray:
    """Frames (bool over `frames`) where body b is posed within 1 mm and 1 deg."""
    v = table.valid[frames, b]
    dp = np.linalg.norm(table.xyz[frames, b] - p_true, axis=1)
    da = rotation_difference_deg(table.quat[frames, b], quaternion_xyzw(R_true))
    return v & (dp < 0.001) & (da < 1.0)


def test_definition_4mm_off_is_fitted_to_the_take(tmp_path, mocapd_cli):
    """A body whose definition has one marker 4 mm off its real place: at default settings
    the command learns its real geometry from the take and poses it in >= 95 % of frames
    within 1 mm / 1 deg of the truth; with the refinement off it does not (the test can
    fail). A body defined but not in the take gets the per-body hint, not a pose."""
    pts, bodies, _ = capture(n_frames=720, noise_m=0.0002, hidden=0.02, seed=7)
    src = tmp_path / "points.csv"
    write_points_csv(src, pts)
    absent = sim.rigid_body_motion(5, 2, fps=RATE, markers_per_body=4, seed=9)[1][4]
    defined = [sim.SimBody(b.name, b.id, displaced(b.markers_body) if i == 0
                           else b.markers_body, b.poses, b.marker_ids)
               for i, b in enumerate(bodies)]
    defined.append(sim.SimBody("absent", 99, absent.markers_body, absent.poses,
                               absent.marker_ids))
    cfg = write_config(tmp_path / "m.toml", defined)
    good = {}
    for mode in ("auto", "off"):
        out = tmp_path / f"poses_{mode}.csv"
        r = mocapd_cli("track", src, "--bodies", cfg, "--rate", RATE, "--out", out,
                       "--json", tmp_path / f"{mode}.json", *(["--refine-bodies", "off"]
                                                              if mode == "off" else []))
        assert r.code == 0, r.err
        table = read_poses_csv(out)
        good[mode] = [within(table, b, body.poses[:, :3, :3], body.poses[:, :3, 3],
                             slice(None)).mean() for b, body in enumerate(bodies)]
        assert not table.valid[:, -1].any()  # the absent body: never a false pose
        warnings = [ln for ln in r.err.splitlines() if ln.startswith("warning:")]
        assert len(warnings) == 1 and "'absent'" in warnings[0], r.err
        assert "never found" in warnings[0]
    assert good["auto"][0] >= 0.95, good
    assert good["off"][0] < 0.95, good  # the definition as given pulls the pose off
    # the bodies defined right are left as they were (the three-marker one, nearly in a
    # line, turns more than 1 deg about that line on 0.2 mm noise in a third of its frames)
    assert good["auto"][1:] == good["off"][1:], good
    import json
    figs = json.loads((tmp_path / "auto.json").read_text())
    refit = figs["bodies"][bodies[0].name]["refine"]
    assert refit["applied"] and refit["frames_used"] >= 10
    assert abs(refit["marker_shift_mm"][0] - 4.0) < 0.3  # the 4 mm it was off, found
    assert max(refit["marker_shift_mm"][1:]) < 0.3
    assert not any(figs["bodies"][b.name]["refine"]["applied"] for b in bodies[1:])
    assert len(figs["hints"]) == 1


def test_hint_names_the_tolerance_that_would_find_the_body(tmp_path, mocapd_cli):
    """With the refinement off, a body whose distances are 6 mm off is never found at the
    default 4 mm; the hint gives its closest fit and a tolerance that finds it, and that
    tolerance does."""
    pts, bodies, _ = capture(n_frames=240, noise_m=0.0002, hidden=0.0, strays=1, seed=11,
                             markers=(4,))
    src = tmp_path / "points.csv"
    write_points_csv(src, pts)
    b = bodies[0]
    cfg = write_config(tmp_path / "m.toml", [sim.SimBody(b.name, b.id, displaced(
        b.markers_body, by_m=0.006), b.poses, b.marker_ids)])
    out = tmp_path / "poses.csv"
    r = mocapd_cli("track", src, "--bodies", cfg, "--rate", RATE, "--out", out,
                   "--refine-bodies", "off")
    assert r.code == 0 and not read_poses_csv(out).valid.any()
    (line,) = [ln for ln in r.err.splitlines() if ln.startswith("warning:")]
    assert "never found" in line and "closest fit" in line and "--refine-bodies on" in line
    import re
    off_mm = float(re.search(r"off by up to ([\d.]+) mm", line).group(1))
    assert 5.0 < off_mm < 7.0  # the 6 mm, give or take the noise
    tol = re.search(r"--distance-tol-mm (\d+)", line).group(1)
    r = mocapd_cli("track", src, "--bodies", cfg, "--rate", RATE, "--out", out,
                   "--refine-bodies", "off", "--distance-tol-mm", tol)
    assert r.code == 0 and read_poses_csv(out).valid[:, 0].mean() > 0.95


# ---- a Motive format 1.0 take (y-up), faithful to the published layout ------------------

def test_motive_1_0_take_four_bodies_one_definition_off(tmp_path, mocapd_cli):
    """The issue's take, built faithfully (we do not have the real file): a format 1.0
    export, y-up, four bodies, one definition 4 mm off its markers. `mocapd track
    --bodies-from-file` at default settings poses all four in >= 95 % of Motive's tracked
    frames within 1 mm / 1 deg of Motive's poses (here the truth), in the z-up world its
    outputs say they are in; the MCAP written is z-up and says so."""
    src = tmp_path / "take.csv"
    bodies, tracked = write_motive_1_0(src)
    out, mcap_out = tmp_path / "poses.csv", tmp_path / "poses.mcap"
    r = mocapd_cli("track", src, "--bodies-from-file", "--out", out, "--json",
                   tmp_path / "f.json")
    assert r.code == 0, r.err
    assert "warning" not in r.err
    table = read_poses_csv(out)
    assert "world z-up" in out.read_text().splitlines()[0]
    motive = to_z_up(read_motive_csv(src))
    for b, body in enumerate(bodies):
        theirs = motive.poses[body.name]
        np.testing.assert_array_equal(theirs.valid, tracked[:, b])
        # Motive's poses turned to z-up are the simulator's z-up truth: the turn is right
        np.testing.assert_allclose(theirs.xyz_m[tracked[:, b]],
                                   body.poses[tracked[:, b], :3, 3], atol=1e-7)
        R = matrix_from_quaternion(theirs.quat_xyzw[tracked[:, b]])
        ok = within(table, b, R, theirs.xyz_m[tracked[:, b]], tracked[:, b])
        assert ok.mean() >= 0.95, (body.name, ok.mean())
    import json
    figs = json.loads((tmp_path / "f.json").read_text())
    assert [figs["bodies"][b.name]["refine"]["applied"] for b in bodies] == [
        True, False, False, False]
    assert figs["input"]["up_axis"] == "y"

    from mcap.reader import make_reader
    r = mocapd_cli("track", src, "--bodies-from-file", "--out", mcap_out)
    assert r.code == 0, r.err
    with open(mcap_out, "rb") as handle:
        reader = make_reader(handle)
        (meta,) = [m for m in reader.iter_metadata() if m.name == "mocapd"]
        first = {}
        topic = f"/mocap/{bodies[1].name}/pose"
        for _, _channel, message in reader.iter_messages(topics=[topic]):
            first = json.loads(message.data)
            break
    assert meta.metadata["up_axis"] == "z" and meta.metadata["source_up_axis"] == "y"
    assert meta.metadata["length_unit"] == "m"
    f0 = int(np.argmax(table.valid[:, 1]))
    np.testing.assert_allclose([first["pose"]["position"][a] for a in "xyz"],
                               table.xyz[f0, 1], atol=1e-6)


def test_every_mcap_says_its_world_is_z_up(tmp_path):
    """The MCAP writer (mocapd record's too) records its axes and units in a metadata
    record, and a caller's notes beside them."""
    from mcap.reader import make_reader

    from daemon.publish.mcap_poses import McapPoseWriter

    for extra in (None, {"source_up_axis": "y"}):
        path = tmp_path / "a.mcap"
        with McapPoseWriter(path, ["a"], metadata=extra) as w:
            w.write(0, np.array([True]), np.zeros((1, 3)), np.array([[0, 0, 0, 1.0]]))
        with open(path, "rb") as handle:
            (meta,) = [m for m in make_reader(handle).iter_metadata() if m.name == "mocapd"]
        assert meta.metadata["up_axis"] == "z" and meta.metadata["length_unit"] == "m"
        assert meta.metadata["world_frame"] == "world"
        assert meta.metadata.get("source_up_axis") == (extra or {}).get("source_up_axis")
