"""Triangulation and rigid fits against the simulator's truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibkit.core.camera import Camera, Rig, look_at, rvec_from_rotation
from calibkit.core.geometry import RigArrays, _solve3, rigid_fit, triangulate
from calibkit.synthetic import sim


@pytest.fixture(scope="module")
def rig() -> Rig:
    return sim.make_rig(8, 4.0, seed=3)


def _labelled(rig: Rig, truth, noise_px: float, seed: int = 0):
    # every marker its own blob at its projection: these check the maths on labelled blobs
    obs = sim.observe(rig, truth, noise_px=noise_px, seed=seed, blobs="ideal")
    return obs.marker, obs.camera, obs.uv


def test_exact_projections_triangulate_exactly(rig) -> None:
    truth = sim.static_markers(40, 1, 4.0, seed=1)
    point, camera, uv = _labelled(rig, truth, 0.0)
    tri = triangulate(rig, point, camera, uv, n_points=40)
    ok = tri.n_cameras >= 2
    assert ok.sum() >= 38
    assert np.max(np.linalg.norm(tri.xyz[ok] - truth.xyz[ok], axis=1)) < 1e-9
    assert np.max(tri.reproj_px[ok]) < 1e-6
    assert np.max(tri.ray_dist_m[ok]) < 1e-9


def test_error_follows_the_pixel_noise(rig) -> None:
    """At sigma px of noise per axis, a point's reprojection figure (RMS over its n cameras
    of the 2D residual length) has E[r^2] = sigma^2 (2n - 3) / n: 3 of the 2n measurements
    are absorbed by the point. The 3D error is about sigma times depth/focal."""
    sigma = 0.5
    truth = sim.static_markers(200, 1, 4.0, seed=2)
    point, camera, uv = _labelled(rig, truth, sigma, seed=5)
    tri = triangulate(rig, point, camera, uv, n_points=200)
    n = tri.n_cameras.astype(float)
    ok = n >= 3
    expected = sigma * np.sqrt((2 * n[ok] - 3) / n[ok])
    ratio = np.sqrt(np.mean(tri.reproj_px[ok] ** 2) / np.mean(expected ** 2))
    assert 0.85 < ratio < 1.15
    err = np.linalg.norm(tri.xyz[ok] - truth.xyz[ok], axis=1)
    # depth ~ 3-5 m, f ~ 457 px: one pixel ~ 9 mm at 4 m; several cameras average it down
    assert np.sqrt(np.mean(err**2)) < sigma * 4.0 / 457 * 1.2


def test_reprojection_refinement_beats_the_ray_midpoint(rig) -> None:
    truth = sim.static_markers(300, 1, 4.0, seed=4)
    point, camera, uv = _labelled(rig, truth, 0.5, seed=6)
    linear = triangulate(rig, point, camera, uv, iterations=0, n_points=300)
    refined = triangulate(rig, point, camera, uv, iterations=3, n_points=300)
    ok = linear.n_cameras >= 2
    e_lin = np.linalg.norm(linear.xyz[ok] - truth.xyz[ok], axis=1)
    e_ref = np.linalg.norm(refined.xyz[ok] - truth.xyz[ok], axis=1)
    assert np.mean(e_ref**2) < np.mean(e_lin**2)
    assert np.all(refined.reproj_px[ok] <= linear.reproj_px[ok] + 1e-9)


def test_one_camera_or_behind_a_camera_is_nan() -> None:
    a = Camera("a", (640, 480), 500, 500, 320, 240)
    R, t = look_at([2.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    b = Camera("b", (640, 480), 500, 500, 320, 240, rvec=rvec_from_rotation(R), t=t)
    rig = Rig((a, b))
    p = np.array([[0.1, 0.05, 3.0]])
    uv_a, _ = a.project(p)
    uv_b, _ = b.project(p)
    # point 0 seen by both, point 1 by one camera only
    tri = triangulate(rig, [0, 0, 1], [0, 1, 0], np.vstack([uv_a, uv_b, uv_a]))
    assert np.allclose(tri.xyz[0], p[0], atol=1e-9)
    assert np.isnan(tri.xyz[1]).all() and tri.n_cameras[1] == 1
    # rays that meet behind camera a: a's pixel mirrored through its centre
    tri = triangulate(rig, [0, 0], [0, 1], np.vstack([[640 - uv_a[0, 0], 480 - uv_a[0, 1]],
                                                     uv_b]))
    assert not tri.ok[0] or np.all(a.to_camera(tri.xyz[:1])[:, 2] > 0)


def test_start_positions_and_given_rays_give_the_same_answer(rig) -> None:
    truth = sim.static_markers(30, 1, 4.0, seed=9)
    point, camera, uv = _labelled(rig, truth, 0.2, seed=1)
    plain = triangulate(rig, point, camera, uv, n_points=30)
    rays = RigArrays.from_rig(rig).rays(camera.astype(np.int64), uv)
    start = truth.xyz + 0.01
    start[3] = np.nan  # a row without a start falls back to the linear solution
    again = triangulate(rig, point, camera, uv, n_points=30, rays=rays, start=start,
                        iterations=5)
    ok = plain.ok
    assert np.allclose(plain.xyz[ok], again.xyz[ok], atol=1e-7)


def test_solve3_matches_numpy_and_flags_singular_systems() -> None:
    rng = np.random.default_rng(0)
    A = rng.normal(size=(50, 3, 3))
    b = rng.normal(size=(50, 3))
    A[7] = 0.0
    A[9, 2] = A[9, 1]  # rank 2
    x = _solve3(A, b)
    good = np.ones(50, dtype=bool)
    good[[7, 9]] = False
    assert np.allclose(x[good], np.linalg.solve(A[good], b[good][:, :, None])[:, :, 0])
    assert np.isnan(x[~good]).all()


@pytest.mark.parametrize("scale", [False, True])
def test_rigid_fit_recovers_the_transform(scale: bool) -> None:
    rng = np.random.default_rng(1)
    src = rng.normal(size=(12, 3))
    R = Rotation.from_rotvec([0.3, -1.2, 0.7]).as_matrix()
    s = 1.7 if scale else 1.0
    t = np.array([0.5, -2.0, 1.0])
    dst = s * src @ R.T + t + rng.normal(0, 1e-6, (12, 3))
    R_fit, t_fit, s_fit = rigid_fit(src, dst, scale=scale)
    assert np.allclose(R_fit, R, atol=1e-5)
    assert np.allclose(t_fit, t, atol=1e-5)
    assert abs(s_fit - s) < 1e-5


def test_rigid_fit_never_returns_a_mirror() -> None:
    """A planar set mapped to its mirror image: the best orthogonal map is a reflection;
    the fit must still return a proper rotation."""
    src = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]])
    dst = src * [1, 1, -1] + [[0, 0, 0.01], [0, 0, -0.01], [0, 0, 0.01], [0, 0, -0.01]]
    R, _, _ = rigid_fit(src, dst)
    assert np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)


@pytest.mark.parametrize("iterations", [0, 1, 3])
def test_compiled_triangulation_equals_the_numpy_reference(rig, iterations) -> None:
    truth = sim.static_markers(300, 1, 4.0, seed=11)
    point, camera, uv = _labelled(rig, truth, 0.5, seed=12)
    point = point.copy()
    point[:3] = 299  # three mislabelled blobs: a point whose rays do not meet
    keep = np.ones(len(point), dtype=bool)
    keep[np.flatnonzero(point == 5)[1:]] = False  # a point seen by one camera only
    start = np.where(np.arange(300)[:, None] % 2 == 0, truth.xyz + 0.02, np.nan)
    for s in (None, start):
        a = triangulate(rig, point[keep], camera[keep], uv[keep], iterations=iterations,
                        n_points=300, start=s, compiled=False)
        b = triangulate(rig, point[keep], camera[keep], uv[keep], iterations=iterations,
                        n_points=300, start=s, compiled=True)
        assert np.array_equal(a.ok, b.ok) and not a.ok[5]
        assert np.allclose(a.xyz[a.ok], b.xyz[b.ok], atol=1e-10, rtol=0)
        assert np.allclose(a.reproj_px[a.ok], b.reproj_px[b.ok], atol=1e-9, rtol=0)
        assert np.allclose(a.ray_dist_m[a.ok], b.ray_dist_m[b.ok], atol=1e-12, rtol=0)
