"""The GTSAM bundle adjustment against the simulator's truth: poses, intrinsics, k3, wand
lengths, outliers, floor-plane and surveyed points, and its uncertainty figures.

The observations' identities come from the simulator here (marker ids), so these tests
measure the solve alone; identification and initialisation are tested in test_wand.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from calibkit.calibrate import bundle
from calibkit.calibrate.wand import WandSpec
from calibkit.core.camera import Rig
from calibkit.core.geometry import rigid_fit
from calibkit.core.observations import Truth
from calibkit.synthetic import sim

SPACING = (0.0, 0.2, 0.5)
NOISE = 0.2


def _labelled(rig: Rig, truth: Truth, noise: float, seed: int, point_offset: int = 0):
    """Observations with their true point numbers: (point, camera, uv, point (frame, marker))."""
    obs = sim.observe(rig, truth, noise_px=noise, seed=seed)
    key = obs.frame * 1000 + obs.marker
    tkey = truth.frame * 1000 + truth.marker
    order = np.argsort(tkey)
    point = order[np.searchsorted(tkey[order], key)]
    return point + point_offset, obs.camera.astype(np.int64), obs.uv


def _perturbed(rig: Rig, seed: int, rot_rad: float = 0.01, shift_m: float = 0.03) -> Rig:
    rng = np.random.default_rng(seed)
    cams = []
    for cam in rig:
        centre = cam.centre + rng.normal(0, shift_m, 3)
        rvec = cam.rvec + rng.normal(0, rot_rad, 3)
        c = cam.replace(rvec=rvec)
        cams.append(c.replace(t=-c.R @ centre))
    return Rig(tuple(cams), meta=dict(rig.meta))


def _wand_data(rig: Rig, start: Rig, frames: int = 300, noise: float = NOISE, seed: int = 0):
    spec = WandSpec(SPACING)
    truth = sim.wand_motion(frames, 100.0, 4.0, SPACING, seed)
    point, camera, uv = _labelled(rig, truth, noise, seed)
    rng = np.random.default_rng(seed + 1)
    xyz0 = truth.xyz + rng.normal(0, 0.01, truth.xyz.shape)
    pairs, lengths = spec.edges()
    # truth rows are (frame, marker) in order with all 3 markers per frame
    base = np.arange(0, len(truth.xyz), 3)
    edge = np.concatenate([np.stack([base + a, base + b], axis=1) for a, b in pairs])
    length = np.repeat(lengths, len(base))
    return bundle.BundleData(start, point, camera, uv, xyz0, edge, length), truth


@pytest.fixture(scope="module")
def solved():
    rig = sim.make_rig(4, 4.0, seed=5)
    data, truth = _wand_data(rig, _perturbed(rig, 5))
    result = bundle.solve(data, bundle.BundleOptions(noise_px=0.5))
    return rig, data, truth, result


def _aligned_centre_errors(result_rig: Rig, true_rig: Rig) -> np.ndarray:
    """Camera centre errors after the best rigid motion (no scale: the wand sets it)."""
    est, true = result_rig.centres(), true_rig.centres()
    R, t, _ = rigid_fit(est, true)
    return np.linalg.norm(est @ R.T + t - true, axis=1)


def test_solve_recovers_the_rig(solved):
    rig, data, _truth, result = solved
    # residuals: the injected noise less what the fit absorbs: each frame's wand has 7 free
    # parameters (9 coordinates, 2 independent distances: collinear ones are dependent)
    inl = result.residual_px[result.inlier]
    rms_axis = float(np.sqrt(np.mean(inl**2)))
    n_meas, n_frames = 2 * len(inl), len(data.xyz) // 3
    expected = NOISE * np.sqrt((n_meas - 7 * n_frames - 6 * len(rig)) / n_meas)
    assert 0.93 * expected < rms_axis < 1.07 * expected
    err = _aligned_centre_errors(result.rig, rig)
    # 0.2 px at ~3 m with f ~ 457 px is ~1.3 mm per ray; hundreds of frames average it down
    assert err.max() < 2e-3
    # the scale comes from the wand: distances between cameras match the truth
    d_est = np.linalg.norm(result.rig.centres()[:, None] - result.rig.centres()[None], axis=2)
    d_true = np.linalg.norm(rig.centres()[:, None] - rig.centres()[None], axis=2)
    iu = np.triu_indices(len(rig), 1)
    assert np.allclose(d_est[iu] / d_true[iu], 1.0, atol=5e-4)
    # no observation is lost when there are no outliers
    assert result.inlier.mean() > 0.995


def test_uncertainty_matches_the_errors(solved):
    rig, _data, _truth, result = solved
    cov = bundle.camera_covariances(result)
    ref = bundle.BundleOptions().reference_camera
    std = cov["position_std_m"]
    assert std[ref].max() < 1e-5  # the gauge: held at the reference camera
    others = [k for k in range(len(rig)) if k != ref]
    assert np.all(std[others] > 1e-5) and np.all(std[others] < 5e-3)
    # errors relative to the reference camera are of the size the covariance says
    est_rel = result.rig.centres() - result.rig.centres()[ref]
    true_rel = rig.centres() - rig.centres()[ref]
    R, _, _ = rigid_fit(est_rel, true_rel)
    err = np.abs(est_rel @ R.T - true_rel)[others]
    assert np.sqrt(np.mean(err**2)) < 4 * np.sqrt(np.mean(std[others] ** 2))


def test_outliers_are_dropped_and_the_solve_holds():
    rig = sim.make_rig(4, 4.0, seed=6)
    data, _ = _wand_data(rig, _perturbed(rig, 6), frames=250, seed=6)
    rng = np.random.default_rng(0)
    bad = rng.random(len(data.obs_uv)) < 0.05
    data.obs_uv[bad] += rng.uniform(8, 30, (int(bad.sum()), 2)) * rng.choice([-1, 1], (
        int(bad.sum()), 2))
    result = bundle.solve(data, bundle.BundleOptions(noise_px=0.5))
    assert np.mean(~result.inlier[bad]) > 0.99  # the gross errors are flagged
    assert np.mean(result.inlier[~bad]) > 0.99  # and the good rows kept
    assert _aligned_centre_errors(result.rig, rig).max() < 3e-3


def test_refine_intrinsics_recovers_focal_and_centre():
    rig = sim.make_rig(4, 4.0, seed=7)
    data, _ = _wand_data(rig, _perturbed(rig, 7), frames=400, seed=7)
    wrong = Rig(tuple(c.replace(fx=c.fx * 1.01, fy=c.fy * 1.01, cx=c.cx + 3.0) for c in
                      data.rig))
    fixed = bundle.solve(bundle.BundleData(**{**data.__dict__, "rig": wrong}))
    refined = bundle.solve(bundle.BundleData(**{**data.__dict__, "rig": wrong}),
                           bundle.BundleOptions(refine_intrinsics=True))
    rms = lambda r: float(np.sqrt(np.mean(r.residual_px[r.inlier] ** 2)))  # noqa: E731
    assert rms(refined) < 1.1 * NOISE
    assert rms(fixed) > rms(refined)
    for est, true in zip(refined.rig, rig, strict=True):
        assert abs(est.fx / true.fx - 1) < 0.004  # from 1 % off
        assert est.dist[4] == true.dist[4]  # k3 is never refined
    # the principal point trades off against rotation and tangential distortion, so a wand
    # moves it only part of the way back (from 3 px off), as its prior allows
    assert np.mean([abs(e.cx - t.cx) for e, t in zip(refined.rig, rig, strict=True)]) < 2.5


def test_k3_is_honoured_though_cal3ds2_lacks_it():
    """With k3 the solve does as well as on the same scene without k3, and better than
    ignoring it."""
    dist = np.array([-0.1, 0.05, 0.001, -0.001, 0.08])
    rig = sim.make_rig(4, 4.0, seed=8, dist=dist)
    data, _ = _wand_data(rig, _perturbed(rig, 8), frames=200, seed=8)
    plain = sim.make_rig(4, 4.0, seed=8, dist=dist * [1, 1, 1, 1, 0])
    data0, _ = _wand_data(plain, _perturbed(plain, 8), frames=200, seed=8)
    ignored = Rig(tuple(c.replace(dist=c.dist * [1, 1, 1, 1, 0]) for c in data.rig))
    result = bundle.solve(data)
    baseline = bundle.solve(data0)
    wrong = bundle.solve(bundle.BundleData(**{**data.__dict__, "rig": ignored}))
    rms = lambda r: float(np.sqrt(np.mean(r.residual_px[r.inlier] ** 2)))  # noqa: E731
    assert abs(rms(result) - rms(baseline)) < 0.02 * rms(baseline)
    assert all(c.dist[4] == 0.08 for c in result.rig)
    err, err0 = _aligned_centre_errors(result.rig, rig), _aligned_centre_errors(
        baseline.rig, plain)
    assert np.max(np.abs(err - err0)) < 5e-4
    assert _aligned_centre_errors(wrong.rig, rig).max() > 2 * err.max()


def _projector_points(rig: Rig, seed: int):
    """Dots a ceiling projector casts on the floor and on a table, seen by the cameras."""
    projector = sim.make_projector(4.0, seed=seed)
    u, v = np.meshgrid(np.linspace(100, 1180, 10), np.linspace(100, 700, 7))
    table = sim.Table(-0.5, 0.5, -0.4, 0.4, 0.75)
    xyz, plane = sim.projector_scene(projector, np.stack([u.ravel(), v.ravel()], axis=1), table)
    ok = plane >= 0
    xyz, plane = xyz[ok], plane[ok]
    truth = Truth(np.zeros(len(xyz)), np.arange(len(xyz)), xyz)
    return truth, plane, table


def test_floor_and_table_dots_fix_the_world_frame():
    rig = sim.make_rig(4, 4.0, seed=9)
    data, _ = _wand_data(rig, rig, frames=250, seed=9)
    dots, plane, table = _projector_points(rig, 9)
    p, c, uv = _labelled(rig, dots, NOISE, 9, point_offset=len(data.xyz))
    # start in a wrong frame: tilted by 1 degree and 5 cm too high
    from calibkit.calibrate.floor import transform_points, transform_rig
    from calibkit.core.camera import rotation_from_rvec

    A, b = rotation_from_rvec([0.015, -0.01, 0.0]), np.array([0.0, 0.0, 0.05])
    start = transform_rig(rig, A, b)
    normal = np.tile([0.0, 0.0, 1.0], (len(dots.xyz), 1))
    offset = np.where(plane == 1, table.height_m, 0.0)
    full = bundle.BundleData(
        start, np.concatenate([data.obs_point, p]), np.concatenate([data.obs_camera, c]),
        np.concatenate([data.obs_uv, uv]),
        np.concatenate([transform_points(data.xyz, A, b), transform_points(dots.xyz, A, b)]),
        data.edge, data.edge_length_m, plane_point=np.arange(len(dots.xyz)) + len(data.xyz),
        plane_normal=normal, plane_offset_m=offset)
    result = bundle.solve(full)
    # the dots end up on their planes, and the cameras at their true heights and tilts
    z = result.xyz[len(data.xyz):, 2]
    seen = np.isfinite(z)
    assert seen.sum() > 20
    assert np.max(np.abs(z[seen] - offset[seen])) < 3e-3
    assert np.max(np.abs(result.rig.centres()[:, 2] - rig.centres()[:, 2])) < 3e-3
    for est, true in zip(result.rig, rig, strict=True):
        up_est, up_true = est.R[:, 2], true.R[:, 2]  # world z in camera coordinates
        assert np.degrees(np.arccos(np.clip(up_est @ up_true, -1, 1))) < 0.05


def test_surveyed_points_fix_the_frame_absolutely():
    rig = sim.make_rig(4, 4.0, seed=10)
    data, truth = _wand_data(rig, _perturbed(rig, 10, shift_m=0.05), frames=250, seed=10)
    known = np.linspace(0, len(truth.xyz) - 3, 6).astype(int) // 3 * 3  # spread out
    data.known_point, data.known_xyz = known, truth.xyz[known]
    result = bundle.solve(data, bundle.BundleOptions(known_sigma_m=1e-4))
    # no alignment: the frame is the surveyed points' (a few mm from their noise)
    assert np.max(np.linalg.norm(result.rig.centres() - rig.centres(), axis=1)) < 5e-3
