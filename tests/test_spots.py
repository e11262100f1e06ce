"""Spot rendering: exact centres and fluxes, realistic noise, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from calibkit.synthetic.spots import render_spots, render_spots_float


def _centroid(image: np.ndarray, background: float) -> np.ndarray:
    img = image.astype(np.float64) - background
    ys, xs = np.indices(img.shape)
    return np.array([(img * xs).sum(), (img * ys).sum()]) / img.sum()


@pytest.mark.parametrize("radius", [1.0, 2.0, 3.0, 4.5, 8.0])
def test_noise_free_centroid_is_the_centre(radius):
    rng = np.random.default_rng(int(radius * 10))
    for _ in range(20):
        centre = rng.uniform(30, 34, size=2)
        img = render_spots((64, 64), centre[None], radius, peak=200, background=8,
                           noise_sigma=0.0, shot_gain=0.0)
        assert img.dtype == np.uint8 and img.shape == (64, 64)
        # Rounding to whole DN moves the centroid by ~1e-3 px at most.
        assert np.abs(_centroid(img, 8.0) - centre).max() < 0.01


def test_flux_is_the_disc_area_times_peak():
    # Area-integrated: the sum of a spot is pi r^2 peak whatever its sub-pixel phase.
    rng = np.random.default_rng(3)
    for _ in range(30):
        centre, radius = rng.uniform(20, 21, size=2), rng.uniform(0.8, 6.0)
        img = render_spots_float((48, 48), centre[None], radius, peak=100.0, blur_px=0.7)
        assert img.sum() == pytest.approx(np.pi * radius**2 * 100.0, rel=0.01)
        assert np.abs(_centroid(img, 0.0) - centre).max() < 0.005


def test_hard_disc_is_area_coverage():
    # Without blur, a pixel deep inside the disc is exactly `peak`, one outside exactly 0,
    # and an edge pixel holds its covered fraction.
    img = render_spots_float((20, 20), [[10.0, 10.0]], 4.5, peak=100.0, blur_px=0.0)
    assert img[10, 10] == pytest.approx(100.0, abs=1e-3)
    assert img[10, 16] == pytest.approx(0.0, abs=1e-6)
    # Pixel (10, 14.5 -> 14) spans x in [13.5, 14.5]: the disc edge at 14.5 covers ~all of
    # its central row but its corners are cut off.
    assert 80.0 < img[10, 14] < 100.0
    assert img.sum() == pytest.approx(np.pi * 4.5**2 * 100.0, rel=0.01)


def test_noise_has_the_requested_statistics():
    img = render_spots((400, 300), np.zeros((0, 2)), 3.0, background=40.0, noise_sigma=2.0,
                       shot_gain=0.1, rng=5)
    vals = img.astype(np.float64)
    # Read noise 2 DN and shot noise var 0.1 * 40 = 4: sigma sqrt(8); rounding adds 1/12.
    expected = np.sqrt(4.0 + 4.0 + 1.0 / 12.0)
    assert vals.mean() == pytest.approx(40.0, abs=0.05)
    assert vals.std() == pytest.approx(expected, rel=0.02)


def test_same_rng_same_image_and_different_seed_differs():
    uv = np.array([[10.3, 12.7], [30.1, 5.5]])
    a = render_spots((48, 32), uv, [2.0, 3.0], rng=np.random.default_rng(7))
    b = render_spots((48, 32), uv, [2.0, 3.0], rng=np.random.default_rng(7))
    c = render_spots((48, 32), uv, [2.0, 3.0], rng=np.random.default_rng(8))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_clipping_edges_and_overlap():
    # A very bright spot saturates at 255; spots off the image edge or outside it are cut,
    # not wrapped; overlapping spots add.
    img = render_spots((32, 32), [[16, 16], [-1.5, 10], [100, 100]], 3.0, peak=1000,
                       noise_sigma=0.0, shot_gain=0.0)
    assert img[16, 16] == 255
    assert img[10, 0] > 100 and img[10, 31] == 8
    sig = render_spots_float((32, 32), [[16, 16], [16, 16]], 3.0, peak=[50.0, 70.0])
    one = render_spots_float((32, 32), [[16, 16]], 3.0, peak=120.0)
    assert np.allclose(sig, one, atol=1e-3)
