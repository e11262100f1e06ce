"""The camera model against OpenCV, over whole images and strong distortion."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from calibkit.core.camera import (
    BASLER_658x492_DIST,
    Camera,
    Rig,
    look_at,
    rotation_from_rvec,
    rvec_from_rotation,
)

# OpenCV's default undistortPoints stops after 5 fixed-point steps; ask it to converge so
# the comparison measures our model, not its iteration count.
CV_CONVERGED = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 1000, 1e-15)


def basler(rvec=(0.1, -0.2, 0.05), t=(0.1, 0.2, 3.0)) -> Camera:
    """The measured 658x492 Basler lens: k1 = -0.38, k2 = 0.16."""
    return Camera("basler", (658, 492), 525.0, 523.0, 331.2, 243.7, 0.0,
                  BASLER_658x492_DIST, rvec, t)


def image_grid(cam: Camera, n: int = 40) -> np.ndarray:
    u = np.linspace(-0.5, cam.width - 0.5, n)
    v = np.linspace(-0.5, cam.height - 0.5, n)
    return np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)


@st.composite
def cameras(draw) -> Camera:
    """Cameras as users have them: webcams to machine-vision lenses, any pose, OpenCV's
    distortion within the range where the model is monotonic over the image."""
    w = draw(st.integers(320, 2048))
    # sensors from 2:1 to square (4:3, 16:9, ...): with f >= w / 2 the image corner stays
    # within normalised radius 1.41 (a 110 degree diagonal), where lenses follow this model;
    # a 320x1277 sensor at f = 165 px (150 degrees) made the terms cancel catastrophically
    h = int(round(w * draw(st.floats(0.5, 1.0))))
    f = draw(st.floats(0.5, 2.0)) * w
    aspect = draw(st.floats(0.98, 1.02))
    cx = w / 2 + draw(st.floats(-0.05, 0.05)) * w
    cy = h / 2 + draw(st.floats(-0.05, 0.05)) * h
    k1 = draw(st.floats(-0.4, 0.2))
    k2 = draw(st.floats(-0.05, 0.2))
    p1, p2 = draw(st.floats(-2e-3, 2e-3)), draw(st.floats(-2e-3, 2e-3))
    k3 = draw(st.floats(-0.02, 0.02))
    assume(_monotonic_over_image((k1, k2, k3), np.hypot(w, h) / 2 / min(f, f * aspect)))
    rvec = np.array([draw(st.floats(-3.0, 3.0)) for _ in range(3)])
    t = np.array([draw(st.floats(-5.0, 5.0)) for _ in range(3)])
    return Camera("c", (w, h), f, f * aspect, cx, cy, 0.0, (k1, k2, p1, p2, k3), rvec, t)


def _monotonic_over_image(k: tuple[float, float, float], corner_radius: float) -> bool:
    """True when the radial mapping r -> r (1 + k1 r^2 + k2 r^4 + k3 r^6) still rises well past
    the image corner: a real lens does; a fold-over inside the image is not a lens."""
    k1, k2, k3 = k
    r = np.linspace(0.0, 4.0, 4001)
    r2 = r * r
    slope = 1 + 3 * k1 * r2 + 5 * k2 * r2**2 + 7 * k3 * r2**3
    turn = r[np.argmax(slope < 0.1)] if np.any(slope < 0.1) else r[-1]
    reach = turn * (1 + k1 * turn**2 + k2 * turn**4 + k3 * turn**6)
    return bool(reach > 1.2 * corner_radius)


def _points_in_front(cam: Camera, n: int, rng) -> np.ndarray:
    """World points in front of the camera, spread over (and a little past) its image."""
    pix = rng.uniform([0, 0], [cam.width, cam.height], size=(n, 2))
    normalised = cam.undistort(pix)
    depth = rng.uniform(0.3, 10.0, size=n)
    pc = np.concatenate([normalised * depth[:, None], depth[:, None]], axis=1)
    return (pc - cam.t) @ cam.R  # R^T (pc - t)


@settings(max_examples=60, deadline=None)
@given(cameras(), st.integers(0, 2**32 - 1))
def test_project_matches_opencv(cam: Camera, seed: int) -> None:
    points = _points_in_front(cam, 300, np.random.default_rng(seed))
    ours, in_front = cam.project(points)
    ref, _ = cv2.projectPoints(points, cam.rvec, cam.t, cam.K, cam.dist)
    assert in_front.all()
    assert np.max(np.abs(ours - ref.reshape(-1, 2))) < 1e-9


@settings(max_examples=60, deadline=None)
@given(cameras())
def test_undistort_matches_opencv_over_whole_image(cam: Camera) -> None:
    pix = image_grid(cam, 25)
    ours = cam.undistort(pix)
    ref = cv2.undistortPoints(pix.reshape(-1, 1, 2), cam.K, cam.dist,
                              criteria=CV_CONVERGED).reshape(-1, 2)
    # compare in pixels: normalised error times the focal length
    assert np.max(np.abs(ours - ref)) * max(cam.fx, cam.fy) < 1e-6


def test_strong_barrel_distortion_round_trip_and_opencv() -> None:
    cam = basler()
    pix = image_grid(cam, 60)
    normalised = cam.undistort(pix)
    assert np.max(np.abs(cam.normalised_to_pixels(normalised) - pix)) < 1e-9
    ref = cv2.undistortPoints(pix.reshape(-1, 1, 2), cam.K, cam.dist,
                              criteria=CV_CONVERGED).reshape(-1, 2)
    assert np.max(np.abs(normalised - ref)) * cam.fx < 1e-6
    # OpenCV's default (5 iterations) is measurably off in these corners; we are not.
    default = cv2.undistortPoints(pix.reshape(-1, 1, 2), cam.K, cam.dist).reshape(-1, 2)
    assert np.max(np.abs(default - ref)) * cam.fx > 1e-3


def test_project_marks_points_behind_camera() -> None:
    cam = basler(rvec=(0, 0, 0), t=(0, 0, 0))
    pix, in_front = cam.project(np.array([[0.1, 0.0, 2.0], [0.1, 0.0, -2.0], [0, 0, 0]]))
    assert in_front.tolist() == [True, False, False]
    assert np.all(np.isfinite(pix))


def test_rays_pass_through_the_projected_points() -> None:
    cam = basler()
    rng = np.random.default_rng(1)
    points = _points_in_front(cam, 500, rng)
    pix, _ = cam.project(points)
    origins, dirs = cam.rays(pix)
    assert np.allclose(origins, cam.centre)
    assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0)
    v = points - origins
    off_ray = v - np.sum(v * dirs, axis=1, keepdims=True) * dirs
    assert np.max(np.linalg.norm(off_ray, axis=1)) < 1e-9
    assert np.all(np.sum(v * dirs, axis=1) > 0)  # the ray points towards the scene


def test_skew_projects_and_undistorts_consistently() -> None:
    cam = basler().replace(skew=1.5)
    pix = image_grid(cam, 20)
    assert np.max(np.abs(cam.normalised_to_pixels(cam.undistort(pix)) - pix)) < 1e-9
    # skew shifts u by skew * y_distorted
    n = np.array([[0.1, 0.2]])
    d = cam.distort(n)
    expected_u = cam.fx * d[0, 0] + 1.5 * d[0, 1] + cam.cx
    assert cam.normalised_to_pixels(n)[0, 0] == pytest.approx(expected_u, abs=1e-12)


def test_centre_and_look_at() -> None:
    R, t = look_at([4.0, -3.0, 2.5], [0.0, 0.0, 1.0])
    assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
    K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
    cam = Camera.from_matrices("c", (640, 480), K, R=R, t=t)
    assert np.allclose(cam.centre, [4.0, -3.0, 2.5])
    pix, _ = cam.project(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 3.0]]))
    assert np.allclose(pix[0], [319.5, 239.5])  # the target is at the image centre
    assert pix[1, 1] < pix[0, 1]  # a point above the target is higher in the image


def test_rotation_vector_round_trip() -> None:
    rng = np.random.default_rng(3)
    for rvec in rng.normal(size=(50, 3)):
        R = rotation_from_rvec(rvec)
        assert np.allclose(rotation_from_rvec(rvec_from_rotation(R)), R, atol=1e-12)
        assert np.allclose(R, cv2.Rodrigues(rvec)[0], atol=1e-12)
    assert np.allclose(rotation_from_rvec(np.zeros(3)), np.eye(3))


def test_camera_is_immutable_and_rig_finds_by_name() -> None:
    cam = basler()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cam.fx = 3.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        cam.t[0] = 1.0
    rig = Rig((cam, cam.replace(name="b", t=(0, 0, 4.0))))
    assert rig["b"].t[2] == 4.0 and rig.index("basler") == 0 and rig.names == ["basler", "b"]
    with pytest.raises(ValueError):
        Rig((cam, cam))
