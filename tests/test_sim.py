"""The simulator keeps its promises: what it reports agrees with the truth it knows."""

from __future__ import annotations

import numpy as np
import pytest

from calibkit.core.errors import UserError
from calibkit.core.observations import Truth
from calibkit.synthetic import blobs, sim


@pytest.fixture(scope="module")
def rig():
    return sim.make_rig(6, 4.0, seed=1)


def test_rig_cameras_all_see_the_volume(rig) -> None:
    assert rig.names == [f"cam{i}" for i in range(6)]
    lo, hi = sim.volume_box(4.0)
    centre = (lo + hi) / 2
    for cam in rig:
        uv, front = cam.project(centre[None])
        assert front[0] and cam.in_image(uv)[0]
        assert np.linalg.norm(cam.centre[:2]) > 2.0  # on the walls, outside the volume
    with pytest.raises(UserError, match="--cameras must be between 2 and 32"):
        sim.make_rig(1)
    with pytest.raises(UserError, match="--volume"):
        sim.make_rig(4, 20.0)


def test_noise_free_observations_are_the_projections(rig) -> None:
    truth = sim.static_markers(30, 2, 4.0, seed=2)
    obs = sim.observe(rig, truth, blobs="ideal")
    assert obs.marker is not None and np.all(obs.marker >= 0)
    for c, cam in enumerate(rig):
        mine = obs.camera == c
        xyz = truth.xyz[(truth.frame == 0)][obs.marker[mine & (obs.frame == 0)]]
        uv, _ = cam.project(xyz)
        assert np.allclose(uv, obs.uv[mine & (obs.frame == 0)], atol=1e-9)


def test_noise_dropouts_and_ghosts_have_the_requested_statistics(rig) -> None:
    truth = sim.static_markers(50, 40, 4.0, seed=3)
    # every marker its own blob, so each noisy blob has one clean twin
    clean = sim.observe(rig, truth, seed=4, blobs="ideal")
    noisy = sim.observe(rig, truth, noise_px=0.5, dropout=0.25, ghosts_per_camera=3.0, seed=4,
                        blobs="ideal")
    real = noisy.marker >= 0
    assert abs(real.sum() / len(clean) - 0.75) < 0.02
    n_frames = len(np.unique(truth.frame))
    assert abs((~real).sum() / (len(rig) * n_frames) - 3.0) < 0.3
    # noise: match each noisy blob to its clean twin
    key_c = clean.frame * 10_000 + clean.camera * 100 + clean.marker
    key_n = noisy.frame[real] * 10_000 + noisy.camera[real] * 100 + noisy.marker[real]
    idx = np.searchsorted(key_c, key_n)
    diff = noisy.uv[real] - clean.uv[np.argsort(key_c)][idx] if not np.all(
        np.diff(key_c) > 0) else noisy.uv[real] - clean.uv[idx]
    assert abs(diff.std() - 0.5) < 0.02 and abs(diff.mean()) < 0.02
    # same seed, same data; another seed, other data
    again = sim.observe(rig, truth, noise_px=0.5, dropout=0.25, ghosts_per_camera=3.0, seed=4,
                        blobs="ideal")
    assert np.array_equal(again.uv, noisy.uv)
    merged = [sim.observe(rig, truth, noise_px=0.5, dropout=0.25, ghosts_per_camera=3.0,
                          seed=4) for _ in range(2)]
    assert np.array_equal(merged[0].uv, merged[1].uv)
    other = sim.observe(rig, truth, noise_px=0.5, dropout=0.25, ghosts_per_camera=3.0, seed=5)
    assert len(other) != len(noisy) or not np.array_equal(other.uv, noisy.uv)


def test_unsynchronised_cameras_see_the_marker_where_it_was_at_their_time(rig) -> None:
    fps = 100.0
    frames = np.arange(20)
    xyz = np.stack([0.5 * frames / fps, np.zeros(20), np.full(20, 1.0)], axis=1)  # 0.5 m/s
    truth = Truth(frames, np.zeros(20), xyz)
    offsets = np.array([0.0, 2e6, 5e6, 0, 0, 0])  # ns: cam1 2 ms late, cam2 5 ms late
    obs = sim.observe(rig, truth, fps=fps, clock_offset_ns=offsets)
    for c in (0, 1, 2):
        rows = (obs.camera == c) & (obs.frame == 10)
        assert obs.t_ns[rows][0] == round(10 * 1e7 + offsets[c])
        at = np.array([[0.5 * (0.1 + offsets[c] * 1e-9), 0.0, 1.0]])
        uv, _ = rig[c].project(at)
        assert np.allclose(obs.uv[rows], uv, atol=1e-6)


def test_wand_keeps_its_spacing_and_stays_in_the_volume() -> None:
    truth = sim.wand_motion(500, 100.0, 4.0, (0.0, 0.2, 0.5), seed=1)
    xyz = truth.xyz.reshape(500, 3, 3)
    assert np.allclose(np.linalg.norm(xyz[:, 1] - xyz[:, 0], axis=1), 0.2, atol=1e-12)
    assert np.allclose(np.linalg.norm(xyz[:, 2] - xyz[:, 0], axis=1), 0.5, atol=1e-12)
    # collinear
    assert np.allclose(np.cross(xyz[:, 1] - xyz[:, 0], xyz[:, 2] - xyz[:, 0]), 0, atol=1e-12)
    lo, hi = sim.volume_box(4.0)
    assert np.all(truth.xyz >= lo - 0.3) and np.all(truth.xyz <= hi + 0.3)
    # a hand's motion: smooth, under a few m/s
    speed = np.linalg.norm(np.diff(xyz, axis=0), axis=2) * 100.0  # every marker, m/s
    assert speed.max() < 4.0


def test_rigid_bodies_are_rigid_distinct_and_follow_their_poses() -> None:
    truth, bodies = sim.rigid_body_motion(4, 200, 100.0, 4.0, [3, 4, 5, 6], seed=2)
    signatures = []
    for body in bodies:
        rows = np.isin(truth.marker, body.marker_ids)
        xyz = truth.xyz[rows].reshape(200, len(body.marker_ids), 3)
        world = np.einsum("fij,kj->fki", body.poses[:, :3, :3], body.markers_body) + \
            body.poses[:, None, :3, 3]
        assert np.allclose(xyz, world, atol=1e-12)
        d = np.linalg.norm(xyz[:, :, None] - xyz[:, None], axis=3)
        assert np.allclose(d, d[0], atol=1e-9)  # rigid
        iu = np.triu_indices(len(body.marker_ids), 1)
        signatures.append(np.sort(d[0][iu]))
        assert np.min(np.diff(signatures[-1])) > 0.002  # distinct distances within a body
    assert len({len(s) for s in signatures}) == 4


def test_projector_dots_land_on_the_floor_and_the_table() -> None:
    projector = sim.make_projector(4.0, seed=0)
    table = sim.Table(-0.5, 0.5, -0.3, 0.3, 0.75)
    gx, gy = np.meshgrid(np.linspace(0, 1279, 20), np.linspace(0, 799, 12))
    dots = np.stack([gx.ravel(), gy.ravel()], axis=1)
    xyz, plane = sim.projector_scene(projector, dots, table)
    assert np.any(plane == 1) and np.any(plane == 0)
    assert np.allclose(xyz[plane == 0, 2], 0.0, atol=1e-9)
    assert np.allclose(xyz[plane == 1, 2], 0.75, atol=1e-9)
    on = xyz[plane == 1]
    assert np.all((on[:, 0] >= -0.5) & (on[:, 0] <= 0.5) & (on[:, 1] >= -0.3)
                  & (on[:, 1] <= 0.3))
    # the projector sees its own dots where it drew them
    uv, _ = projector.project(xyz[plane >= 0])
    assert np.allclose(uv, dots[plane >= 0], atol=1e-6)


def test_motion_blur_smears_the_spot_along_its_path() -> None:
    from calibkit.vision.detect import DetectorConfig, detect

    cam = sim.make_rig(4, 4.0, seed=0)[0]
    start = np.array([[0.0, 0.0, 1.0]])
    # 40 mm of travel during the exposure: several pixels at this distance
    end = start + [[0.0, 0.0, 0.04]]
    image, uv, visible = sim.render_frame(cam, start, xyz_end=end, seed=1, noise_sigma=1.0)
    still, uv_still, _ = sim.render_frame(cam, start, seed=1, noise_sigma=1.0)
    path_px = np.linalg.norm(cam.project(end)[0] - cam.project(start)[0])
    assert path_px > 2.0 and visible[0]
    # the true centre is the middle of the path
    assert np.allclose(uv[0], (cam.project(end)[0][0] + cam.project(start)[0][0]) / 2,
                       atol=0.02)
    blobs = detect(image, DetectorConfig())
    still_blobs = detect(still, DetectorConfig())
    assert len(blobs) == 1 and np.linalg.norm(blobs.uv[0] - uv[0]) < 0.1
    assert blobs.roundness[0] < still_blobs.roundness[0] - 0.1  # elongated
    assert blobs.peak[0] < still_blobs.peak[0]  # spread over more pixels


def test_nearer_markers_and_bodies_hide_markers_behind_them() -> None:
    cam = sim.make_rig(4, 4.0, seed=0)[0]
    direction = np.array([0.0, 0.0, 1.0]) - cam.centre
    direction /= np.linalg.norm(direction)
    near = cam.centre + 2.0 * direction
    far = cam.centre + 3.0 * direction
    aside = cam.centre + 3.0 * direction + [0.0, 0.0, 0.3]
    _, _, visible = sim.render_frame(cam, np.array([near, far, aside]), seed=0)
    assert visible.tolist() == [True, False, True]
    # a 10 cm sphere (an arm) between the camera and `aside` hides it, and nothing else
    arm = np.array([[*(cam.centre + 1.5 * (aside - cam.centre) / 3.0), 0.1]])
    _, _, visible = sim.render_frame(cam, np.array([near, aside]), occluders=arm, seed=0)
    assert visible.tolist() == [True, False]


def test_sim_unsync_option_offsets_each_camera(tmp_path, calibkit_cli) -> None:
    from calibkit.core.recording import load_observations

    res = calibkit_cli("sim", "static", "--cameras", "4", "--frames", "3", "--unsync-ms",
                       "8", "--out", tmp_path / "u.mcrec")
    assert res.code == 0, res.err
    obs, _ = load_observations(tmp_path / "u.mcrec")
    t1 = np.array([obs.t_ns[(obs.frame == 1) & (obs.camera == c)][0] for c in range(4)])
    offsets = t1 - 1e7  # 100 fps: frame 1 at 10 ms
    assert np.all(offsets >= 0) and np.all(offsets < 8e6) and len(set(offsets.tolist())) == 4
    res = calibkit_cli("sim", "static", "--cameras", "4", "--unsync-ms", "-1", "--out",
                       tmp_path / "v.mcrec")
    assert res.code == 2 and "must not be negative" in res.err


# ---- blobs as a detector makes them ------------------------------------------------------------

def _raster(uv, radius, depth, peak, step=0.01):
    """Reference by brute force: paint the discs on a fine grid, nearest on top, and measure
    each connected lit region as a threshold detector would (brightness-weighted centroid,
    area). -> list of (centroid (2,), area px^2), sorted by u."""
    from scipy import ndimage

    lo = (uv - radius[:, None]).min(axis=0) - 1
    hi = (uv + radius[:, None]).max(axis=0) + 1
    gu = np.arange(lo[0], hi[0], step)
    gv = np.arange(lo[1], hi[1], step)
    U, V = np.meshgrid(gu, gv)
    light = np.zeros(U.shape)
    z = np.full(U.shape, np.inf)
    for k in np.argsort(-depth):  # far first, the nearer painted over it
        inside = (U - uv[k, 0]) ** 2 + (V - uv[k, 1]) ** 2 < radius[k] ** 2
        light[inside], z[inside] = peak[k], depth[k]
    labels, n = ndimage.label(light > 0)
    out = []
    for lab in range(1, n + 1):
        m = labels == lab
        w = light[m]
        out.append((np.array([np.sum(w * U[m]), np.sum(w * V[m])]) / w.sum(),
                    m.sum() * step * step))
    return sorted(out, key=lambda b: b[0][0])


def test_merged_and_partly_covered_blobs_match_the_painted_discs() -> None:
    """Overlapping discs: one blob at the painted image's weighted centroid with the union's
    area; apart: untouched. Grid of 0.01 px: centroids agree to ~1e-3 px, areas to ~1 %."""
    rng = np.random.default_rng(0)
    for trial in range(12):
        k = 2 if trial < 8 else 3
        uv = rng.uniform(0, 3.0, (k, 2))
        radius = rng.uniform(0.8, 2.0, k)
        depth = rng.uniform(2.0, 4.0, k)
        peak = rng.uniform(60, 255, k)
        got = blobs.merge_blobs(np.zeros(k, dtype=np.int64), uv, radius, depth, peak)
        want = _raster(uv, radius, depth, peak)
        assert len(got.uv) == len(want)
        order = np.argsort(got.uv[:, 0])
        for (c, a), g in zip(want, order, strict=True):
            assert np.linalg.norm(got.uv[g] - c) < 0.01
            assert abs(got.area_px[g] - a) < 0.02 * a
            assert got.area_px[g] >= np.pi * radius[got.group == g].max() ** 2 - 1e-9


def test_a_partly_covered_marker_shifts_away_from_the_nearer_one() -> None:
    """A multi-threshold detector keeps two overlapping spots apart while each centre is
    uncovered: the nearer one stays where it is, the farther one's centroid is its visible
    part's, pushed away from the nearer disc (checked on painted discs of its own)."""
    uv = np.array([[10.0, 10.0], [11.6, 10.0]])
    radius = np.array([1.0, 1.0])
    depth = np.array([2.0, 3.0])  # the first is nearer
    got = blobs.merge_blobs(np.zeros(2, dtype=np.int64), uv, radius, depth,
                          np.array([200.0, 200.0]), separate=True)
    assert len(got.uv) == 2
    first, second = got.group
    assert np.allclose(got.uv[first], uv[0], atol=1e-12)
    shift = got.uv[second] - uv[1]
    assert shift[0] > 0.05 and abs(shift[1]) < 1e-9  # away from the nearer disc
    # only the farther disc's visible part, painted alone
    (c, a), = _raster(uv[1:], radius[1:], depth[1:], np.array([200.0]))
    gu, gv = np.meshgrid(np.arange(8, 14, 0.01), np.arange(8, 12, 0.01))
    vis = ((gu - 11.6) ** 2 + (gv - 10) ** 2 < 1) & ((gu - 10) ** 2 + (gv - 10) ** 2 >= 1)
    assert abs(got.uv[second][0] - gu[vis].mean()) < 0.01
    assert abs(got.area_px[second] - vis.sum() * 1e-4) < 0.02
    # the centre covered: it has no maximum of its own, one blob
    uv[1, 0] = 10.7
    got = blobs.merge_blobs(np.zeros(2, dtype=np.int64), uv, radius, depth,
                          np.array([200.0, 200.0]), separate=True)
    assert len(got.uv) == 1


def test_two_markers_crossing_in_one_camera_merge_while_they_overlap(rig) -> None:
    """A marker passes in front of another on camera 0's line of sight: camera 0 reports
    one blob where the painted discs' centroid is while their discs overlap, two at the
    projections when apart; cameras that see them apart report two all along."""
    cam = rig[0]
    back = np.array([0.3, -0.2, 1.0])
    ray = back - cam.centre
    ray /= np.linalg.norm(ray)
    across = np.cross(ray, [0.0, 0.0, 1.0])
    across /= np.linalg.norm(across)
    n = 41
    front0 = cam.centre + 0.7 * (back - cam.centre)
    front = front0 + np.linspace(-0.05, 0.05, n)[:, None] * across  # 10 cm across the ray
    xyz = np.stack([np.broadcast_to(back, (n, 3)), front], axis=1)
    truth = Truth(np.repeat(np.arange(n), 2), np.tile([0, 1], n), xyz.reshape(-1, 3))
    obs = sim.observe(rig, truth, fps=100.0)
    assert obs.meta["blobs"] == "threshold" and obs.meta["merged_blobs"] > 0
    uv, _ = cam.project(xyz.reshape(-1, 3))
    uv = uv.reshape(n, 2, 2)
    depth = cam.to_camera(xyz.reshape(-1, 3))[:, 2].reshape(n, 2)
    radius = sim.MARKER_RADIUS_M * cam.fx / depth
    merged_frames = 0
    for f in range(n):
        mine = (obs.camera == 0) & (obs.frame == f)
        apart = np.linalg.norm(uv[f, 0] - uv[f, 1]) >= radius[f].sum()
        if apart:
            assert mine.sum() == 2
            got = obs.uv[mine][np.argsort(obs.marker[mine])]
            assert np.allclose(got, uv[f], atol=1e-9)
        else:
            merged_frames += 1
            assert mine.sum() == 1
            peak = np.clip(255.0 * np.minimum(1.0, (2.5 / depth[f]) ** 2), 40, 255)
            want = _raster(uv[f], radius[f], depth[f], peak)
            assert len(want) == 1
            assert np.linalg.norm(obs.uv[mine][0] - want[0][0]) < 0.01
            assert obs.marker[mine][0] == 1  # the nearer marker gives most of the light
            assert obs.area[mine][0] >= np.pi * radius[f].max() ** 2 * 0.999
    assert 3 <= merged_frames < n - 10
    others = obs.camera != 0
    assert np.all(np.bincount(obs.frame[others] * len(rig) + obs.camera[others])[
        np.unique(obs.frame[others] * len(rig) + obs.camera[others])] == 2)
    # switched off: every marker its own blob at its projection
    clean = sim.observe(rig, truth, fps=100.0, blobs="ideal")
    assert clean.meta["merged_blobs"] == 0 and len(clean) == 2 * n * len(rig)
    with pytest.raises(UserError, match="--blobs must be one of"):
        sim.observe(rig, truth, blobs="merged")
