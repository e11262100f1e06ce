"""Marker detection against the true centres of rendered spots."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibkit.core.errors import UserError
from calibkit.synthetic.spots import render_spots, render_spots_float
from calibkit.synthetic.truthcheck import match_to_truth
from calibkit.vision.detect import (
    Blobs,
    DetectorConfig,
    background_level,
    detect,
    detect_reference,
    label_pixels,
)
from calibkit.vision.detect_regions import label_pixels_with
from calibkit.vision.detect_threshold import estimate_background
from calibkit.vision.masks import build_mask, load_mask, save_mask

SIZE = (640, 480)


def spread_out(n: int, rng, size=SIZE, sep_px: float = 14.0, margin: float = 8.0):
    """n centres at least sep_px apart (markers that do not touch)."""
    pts: list[np.ndarray] = []
    while len(pts) < n:
        p = rng.uniform([margin, margin], [size[0] - margin, size[1] - margin])
        if all(np.hypot(*(p - q)) > sep_px for q in pts):
            pts.append(p)
    return np.array(pts)


def expected_centroid_sigma(radius, peak, noise_dn, window_px):
    """Per-axis centroid noise of an intensity-weighted mean over a square window."""
    half = (window_px - 1) / 2
    xs = np.arange(window_px) - half
    sum_x2 = window_px * np.sum(xs**2)
    flux = np.pi * radius**2 * peak
    return noise_dn * np.sqrt(sum_x2) / flux


def test_centroids_match_truth_within_the_noise():
    rng = np.random.default_rng(1)
    errors, n_true, n_false = [], 0, 0
    for f in range(6):
        uv = spread_out(40, rng)
        img = render_spots(SIZE, uv, 3.0, peak=200, noise_sigma=2.0, rng=f)
        blobs = detect(img)
        det, tru = match_to_truth(blobs.uv, uv, max_dist_px=1.0)
        errors.append(blobs.uv[det] - uv[tru])
        n_true += len(uv)
        n_false += len(blobs) - len(det)
        assert len(det) == len(uv)
    err = np.concatenate(errors)
    rms = np.sqrt((err**2).sum(axis=1).mean())
    # Read noise 2 DN and shot noise (~2 DN at the spot) over a ~13 px window.
    sigma = expected_centroid_sigma(3.0, 200, np.hypot(2.0, 1.0), 13)
    assert rms < 2.0 * np.sqrt(2) * sigma
    assert rms < 0.05
    # No systematic offset: the mean error is within a few standard errors of zero.
    assert np.all(np.abs(err.mean(axis=0)) < 4 * sigma / np.sqrt(len(err)) + 0.003)
    assert n_false == 0


@pytest.mark.parametrize("radius", [1.2, 2.0, 4.0, 7.0])
def test_noise_free_centroids_are_exact(radius):
    # Without noise the only error left is the method's own bias (skirt cut, pixel locking).
    rng = np.random.default_rng(int(radius * 10))
    uv = spread_out(30, rng, sep_px=4 * radius + 12)
    img = render_spots(SIZE, uv, radius, peak=180, noise_sigma=0.0, shot_gain=0.0)
    blobs = detect(img)
    det, tru = match_to_truth(blobs.uv, uv)
    assert len(det) == len(uv) == len(blobs)
    assert np.abs(blobs.uv[det] - uv[tru]).max() < 0.01


def test_area_peak_bbox_and_roundness_describe_the_spot():
    img = render_spots((64, 64), [[30.4, 28.6]], 4.0, peak=150, noise_sigma=0.0,
                       shot_gain=0.0, background=8)
    b = detect(img, DetectorConfig(threshold=40))
    assert len(b) == 1
    # Pixels above 40 DN: the disc of radius ~4 blurred, cut at 32/150 of its height.
    assert abs(b.area[0] - np.pi * 4.0**2) < 0.3 * np.pi * 4.0**2
    assert b.peak[0] == img.max()
    x0, y0, x1, y1 = b.bbox[0]
    above = np.argwhere(img > 40)
    assert (x0, y0, x1, y1) == (above[:, 1].min(), above[:, 0].min(),
                                above[:, 1].max(), above[:, 0].max())
    assert b.roundness[0] > 0.97


def test_pure_noise_gives_no_blobs_and_the_background_is_measured():
    img = render_spots(SIZE, np.zeros((0, 2)), 3.0, background=12.0, noise_sigma=2.5,
                       shot_gain=0.0, rng=3)
    level, sigma = background_level(img)
    assert level == pytest.approx(12.0, abs=0.2)
    assert sigma == pytest.approx(np.hypot(2.5, 0.29), rel=0.1)  # read noise + rounding
    assert len(detect(img)) == 0


def test_filters_reject_a_big_reflection_and_a_line_glint():
    rng = np.random.default_rng(4)
    uv = spread_out(12, rng, size=(640, 240), margin=20)
    img = render_spots((640, 480), uv, 3.0, rng=4).astype(np.float64)
    reflection = render_spots_float((640, 480), [[320, 380]], 25.0, peak=240)
    glint = np.zeros((480, 640), np.uint8)
    cv2.line(glint, (60, 300), (140, 330), 200, 2, cv2.LINE_AA)
    img = np.clip(img + reflection + cv2.GaussianBlur(glint, (5, 5), 0.7), 0, 255)
    img = img.astype(np.uint8)

    everything = detect(img)
    assert len(everything) == len(uv) + 2
    kept = detect(img, DetectorConfig(max_area=1000, min_roundness=0.5))
    det, tru = match_to_truth(kept.uv, uv)
    assert len(kept) == len(det) == len(uv)
    # Each filter alone removes exactly its own artefact.
    assert len(detect(img, DetectorConfig(max_area=1000))) == len(uv) + 1
    assert len(detect(img, DetectorConfig(min_roundness=0.5))) == len(uv) + 1
    assert len(detect(img, DetectorConfig(min_area=1000))) == 1  # only the reflection


def test_hsv_ranges_each_find_their_colour():
    rng = np.random.default_rng(5)
    centres = spread_out(9, rng, size=(320, 240), sep_px=25, margin=12)
    colours = {"red": (0, 0, 1), "green": (0, 1, 0), "blue": (1, 0, 0)}  # BGR weights
    names = list(colours)
    which = np.arange(9) % 3
    img = np.zeros((240, 320, 3))
    for k, name in enumerate(names):
        sig = render_spots_float((320, 240), centres[which == k], 3.0, peak=220)
        img += sig[:, :, None] * np.array(colours[name])[None, None, :]
    img = np.clip(img + 6 + rng.normal(0, 1.5, img.shape), 0, 255).astype(np.uint8)
    red = ((170, 80, 60), (10, 255, 255))  # wraps around hue 0
    green = ((50, 80, 60), (70, 255, 255))
    blobs = detect(img, DetectorConfig(hsv_ranges=(red, green)))
    for label, k in ((0, 0), (1, 1)):
        found = blobs.select(blobs.label == label)
        det, tru = match_to_truth(found.uv, centres[which == k])
        assert len(found) == len(det) == 3
        assert np.abs(found.uv[det] - centres[which == k][tru]).max() < 0.1
    assert not np.any(blobs.label == 2)
    # Blue spots match neither range.
    det, _ = match_to_truth(blobs.uv, centres[which == 2], max_dist_px=3)
    assert len(det) == 0
    with pytest.raises(UserError):
        detect(img[:, :, 0], DetectorConfig(hsv_ranges=(red,)))


def test_masks_hide_what_they_cover_and_round_trip(tmp_path):
    rng = np.random.default_rng(6)
    lamp = render_spots_float(SIZE, [[500, 100], [120, 400]], [12.0, 5.0], peak=[250, 120])
    empty = np.clip(8 + lamp + rng.normal(0, 2, lamp.shape), 0, 255).astype(np.uint8)
    mask = build_mask([empty, empty], dilate_px=3)
    assert mask[100, 500] and mask[400, 120] and not mask[240, 320]
    save_mask(tmp_path / "mask.png", mask)
    loaded = load_mask(tmp_path / "mask.png", size=SIZE)
    assert np.array_equal(loaded, mask)
    with pytest.raises(UserError):
        load_mask(tmp_path / "mask.png", size=(320, 240))
    with pytest.raises(UserError):
        load_mask(tmp_path / "missing.png")

    uv = spread_out(20, rng)
    uv = uv[~mask[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)]]
    hidden = np.array([[505.0, 97.0]])  # a marker under the lamp's mask
    sig = render_spots_float(SIZE, np.vstack([uv, hidden]), 3.0, peak=200)
    img = np.clip(8 + lamp + sig + rng.normal(0, 2, lamp.shape), 0, 255).astype(np.uint8)
    unmasked = detect(img)
    assert len(unmasked) >= len(uv) + 2  # the lamps show up as blobs
    blobs = detect(img, DetectorConfig(mask=mask))
    det, tru = match_to_truth(blobs.uv, uv)
    assert len(blobs) == len(det) == len(uv)
    inside = mask[np.rint(blobs.uv[:, 1]).astype(int), np.rint(blobs.uv[:, 0]).astype(int)]
    assert not inside.any()
    assert np.sqrt(((blobs.uv[det] - uv[tru]) ** 2).sum(axis=1).mean()) < 0.05
    with pytest.raises(UserError):
        detect(img[:100], DetectorConfig(mask=mask))


def test_multi_threshold_separates_touching_spots():
    rng = np.random.default_rng(7)
    errors = []
    for trial in range(10):
        a = rng.uniform(28, 36, size=2)
        angle = rng.uniform(0, np.pi)
        b = a + 6.6 * np.array([np.cos(angle), np.sin(angle)])  # rims ~0.6 px apart
        truth = np.array([a, b])
        img = render_spots((72, 72), truth, 3.0, peak=rng.uniform(150, 220, 2), rng=trial)
        single = detect(img)
        assert len(single) == 1  # one threshold merges them
        multi = detect(img, DetectorConfig(mode="multi"))
        det, tru = match_to_truth(multi.uv, truth)
        assert len(multi) == len(det) == 2
        errors.append(multi.uv[det] - truth[tru])
    err = np.concatenate(errors)
    # The light of the overlapping skirts is shared out by symmetric templates; without
    # that each centroid is pulled ~0.3 px towards its neighbour (and ~3 px for the merged
    # blob of one threshold).
    assert np.sqrt((err**2).sum(axis=1).mean()) < 0.08
    assert np.abs(err).max() < 0.25


def test_multi_threshold_keeps_isolated_spots_exact_and_uneven_lighting():
    rng = np.random.default_rng(8)
    uv = spread_out(30, rng)
    peaks = rng.uniform(40, 250, len(uv))  # dim and bright markers in one frame
    img = render_spots(SIZE, uv, 3.0, peak=peaks, noise_sigma=2.0, rng=8)
    blobs = detect(img, DetectorConfig(mode="multi"))
    det, tru = match_to_truth(blobs.uv, uv)
    assert len(det) == len(uv) == len(blobs)
    err = blobs.uv[det] - uv[tru]
    assert np.sqrt((err**2).sum(axis=1).mean()) < 0.06


def test_spots_at_the_image_border_and_tiny_images():
    img = render_spots((40, 30), [[0.6, 15.0], [39.2, 0.4], [20.0, 15.0]], 3.0, rng=9)
    blobs = detect(img)
    assert len(blobs) == 3
    assert np.all((blobs.uv >= -0.5) & (blobs.uv <= [39.5, 29.5]))
    det, tru = match_to_truth(blobs.uv, [[20.0, 15.0]])
    assert len(det) == 1 and np.abs(blobs.uv[det[0]] - [20.0, 15.0]).max() < 0.06
    assert len(detect(np.zeros((5, 7), np.uint8))) == 0
    for empty in (np.zeros((5, 0), np.uint8), np.zeros((0, 5), np.uint8)):
        assert len(detect(empty)) == len(detect(empty, DetectorConfig(threshold=3))) == 0
    one = render_spots((9, 9), [[4.2, 3.9]], 2.0, noise_sigma=0.0, shot_gain=0.0)
    b = detect(one, DetectorConfig(threshold=40))  # the window fills the image
    assert len(b) == 1 and np.abs(b.uv[0] - [4.2, 3.9]).max() < 0.05


def test_colour_images_and_16_bit_images_are_converted():
    uv = np.array([[30.3, 20.8], [70.6, 50.1]])
    gray = render_spots((100, 80), uv, 3.0, noise_sigma=0.0, shot_gain=0.0)
    bgr = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    assert np.allclose(detect(bgr).uv, detect(gray).uv)
    deep = gray.astype(np.uint16) * 256
    b16 = detect(deep)
    det, tru = match_to_truth(b16.uv, uv)
    assert len(det) == 2 and np.abs(b16.uv[det] - uv[tru]).max() < 0.01


def test_labelling_matches_opencv_on_random_shapes():
    rng = np.random.default_rng(10)
    for _ in range(40):
        h, w = rng.integers(1, 40), rng.integers(1, 60)
        binary = rng.random((h, w)) < rng.uniform(0.1, 0.6)
        pix = np.flatnonzero(binary)
        labels, n = label_pixels(pix, w)
        count, ref = cv2.connectedComponents(binary.astype(np.uint8), connectivity=8)
        assert n == count - 1
        pairs = set(zip(labels.tolist(), (ref.reshape(-1)[pix]).tolist(), strict=True))
        assert len(pairs) == n  # the same partition
        # Labels are numbered in raster order of each region's first pixel.
        first = [labels[np.flatnonzero(labels == k)[0]] for k in range(n)]
        assert first == sorted(first)


def test_compiled_labelling_equals_the_numpy_reference():
    rng = np.random.default_rng(16)
    for _ in range(40):
        h, w = int(rng.integers(1, 50)), int(rng.integers(1, 90))
        pix = np.flatnonzero(rng.random((h, w)) < rng.uniform(0.05, 0.7))
        labels, n = label_pixels(pix, w)
        ref_labels, ref_n = label_pixels_with(pix, w, None)
        assert n == ref_n and np.array_equal(labels, ref_labels)


def test_compiled_multi_threshold_equals_the_numpy_reference():
    rng = np.random.default_rng(17)
    for _ in range(6):
        img, mask = random_scene(rng)
        for config in (DetectorConfig(mode="multi"), DetectorConfig(mode="multi", mask=mask)):
            assert_same_blobs(detect(img, config), detect_reference(img, config))


def test_u_shapes_and_spirals_are_one_region():
    img = np.zeros((20, 20), bool)
    img[2:15, 2] = img[2:15, 10] = img[14, 2:11] = True  # U
    img[2, 14:19] = img[2:18, 18] = img[17, 12:19] = img[6:18, 12] = img[6, 12:16] = True
    pix = np.flatnonzero(img)
    labels, n = label_pixels(pix, 20)
    assert n == 2


def test_config_validation_is_a_user_error():
    for bad in ({"threshold": "high"}, {"threshold": -3}, {"min_area": 10, "max_area": 5},
                {"min_roundness": 1.5}, {"mode": "adaptive"},
                {"hsv_ranges": (((200, 0, 0), (10, 255, 255)),)},
                {"hsv_ranges": (((0, 200, 0), (10, 100, 255)),)}):
        with pytest.raises(UserError):
            DetectorConfig(**bad)


def test_blobs_table_helpers():
    b = Blobs(np.array([[1.0, 2.0], [3.0, 4.0]]), [5, 6], [100, 200], [[0, 1, 2, 3]] * 2,
              [0.9, 0.8], [0, 1])
    assert len(b.select(b.label == 1)) == 1
    both = Blobs.concatenate([b, b])
    assert len(both) == 4 and both.uv.shape == (4, 2)
    rec = b.to_records()
    assert rec[1] == {"u": 3.0, "v": 4.0, "area": 6.0, "peak": 200.0, "roundness": 0.8,
                      "bbox": [0, 1, 2, 3], "label": 1}


def test_sloping_background_is_fitted_as_a_plane():
    # A lamp's skirt or vignetting: 0.5 DN/px across the spot. A constant background would
    # pull the centroid ~0.07 px uphill; the ring's plane fit removes that.
    rng = np.random.default_rng(11)
    yy, xx = np.mgrid[0:100, 0:100]
    errors = []
    for _ in range(30):
        c = rng.uniform(40, 60, size=2)
        sig = render_spots_float((100, 100), c[None], 3.0, peak=200)
        img = np.clip(np.rint(sig + 8 + 0.5 * xx + 0.2 * yy + rng.normal(0, 2, sig.shape)),
                      0, 255).astype(np.uint8)
        level, sigma = background_level(img)
        assert sigma == pytest.approx(np.hypot(2.0, 0.29), rel=0.15)  # the gradient is not noise
        b = detect(img)
        det, tru = match_to_truth(b.uv, c[None])
        assert len(det) == 1
        errors.append(b.uv[det[0]] - c)
    err = np.array(errors)
    assert np.abs(err.mean(axis=0)).max() < 0.015
    assert np.sqrt((err**2).sum(axis=1).mean()) < 0.04


def assert_same_blobs(got: Blobs, ref: Blobs, tol_px: float = 1e-9):
    assert len(got) == len(ref)
    assert np.array_equal(got.area, ref.area)
    assert np.array_equal(got.peak, ref.peak)
    assert np.array_equal(got.bbox, ref.bbox)
    assert np.array_equal(got.label, ref.label)
    assert np.abs(got.uv - ref.uv).max(initial=0.0) <= tol_px
    assert np.abs(got.roundness - ref.roundness).max(initial=0.0) <= 1e-6
    assert got.threshold == ref.threshold


def random_scene(rng, size=(160, 120)):
    """Spots of random size and brightness, some touching, some cut by the image edge, on a
    sloping background with noise; a mask over a random rectangle and a random lamp."""
    w, h = size
    n = int(rng.integers(3, 25))
    uv = rng.uniform([-2, -2], [w + 1, h + 1], size=(n, 2))
    angle = rng.uniform(0, np.pi, n // 3)
    step = rng.uniform(5.5, 7.5, (n // 3, 1)) * np.stack([np.cos(angle), np.sin(angle)], 1)
    uv = np.vstack([uv, uv[: n // 3] + step])  # touching neighbours of the first third
    radius = rng.uniform(0.8, 5.0)
    img = render_spots_float(size, uv, radius, peak=rng.uniform(40, 250, len(uv)))
    yy, xx = np.mgrid[0:h, 0:w]
    img = img + rng.uniform(0, 20) + rng.uniform(-0.3, 0.3) * xx + rng.uniform(-0.3, 0.3) * yy
    img += render_spots_float(size, rng.uniform([0, 0], [w, h])[None], 12.0, peak=200)
    img = np.clip(np.rint(img + rng.normal(0, rng.uniform(0, 3), img.shape)), 0, 255)
    mask = np.zeros((h, w), bool)
    x0, y0 = rng.integers(0, w - 10), rng.integers(0, h - 10)
    mask[y0:y0 + rng.integers(3, 40), x0:x0 + rng.integers(3, 60)] = True
    return img.astype(np.uint8), mask


def test_compiled_path_equals_the_numpy_reference_on_random_scenes():
    # Everything the compiled kernels do (candidate pixels, runs and regions, the windowed
    # background-subtracted moments) must give the numpy reference's blobs exactly: the
    # sums are of integers times half-integers, so centroids agree to rounding.
    rng = np.random.default_rng(12)
    n_blobs = 0
    for _ in range(40):
        img, mask = random_scene(rng)
        for config in (DetectorConfig(), DetectorConfig(mask=mask),
                       DetectorConfig(threshold=float(rng.uniform(10, 80)), mask=mask,
                                      min_roundness=0.3, max_area=300),
                       DetectorConfig(min_area=0, window_margin_px=int(rng.integers(0, 4)))):
            got, ref = detect(img, config), detect_reference(img, config)
            assert_same_blobs(got, ref)
            n_blobs += len(got)
        deep = img.astype(np.uint16) * 257 + rng.integers(0, 200, img.shape).astype(np.uint16)
        assert_same_blobs(detect(deep), detect_reference(deep))
        level = background_level(img, mask)
        assert level == pytest.approx(estimate_background(img, mask, None), abs=1e-12)
    assert n_blobs > 1000  # the scenes did hold blobs to compare


def test_compiled_regions_equal_the_reference_on_noise_of_any_shape():
    # Narrow and odd-sized images: runs that end at row ends and chunk boundaries, regions
    # that wrap nowhere, windows that fill the image.
    rng = np.random.default_rng(13)
    for _ in range(60):
        h, w = int(rng.integers(1, 40)), int(rng.integers(2, 140))
        img = rng.integers(0, 256, (h, w)).astype(np.uint8)
        config = DetectorConfig(threshold=float(rng.integers(0, 255)), min_area=0,
                                max_area=1e9)
        assert_same_blobs(detect(img, config), detect_reference(img, config))
    # Salt and pepper: thousands of runs, more than the first guess at the run table holds.
    noise = rng.integers(0, 256, (200, 300)).astype(np.uint8)
    config = DetectorConfig(threshold=200, min_area=0, max_area=1e9)
    many = detect(noise, config)
    assert len(many) > 3000  # regions, so more runs still
    assert_same_blobs(many, detect_reference(noise, config))
    flat = np.full((30, 70), 9, np.uint8)  # nothing above the threshold
    assert len(detect(flat)) == len(detect_reference(flat)) == 0
    assert len(detect(np.full((8, 8), 255, np.uint8), DetectorConfig(threshold=255))) == 0


def test_compiled_hsv_ranges_equal_the_numpy_reference():
    rng = np.random.default_rng(14)
    red = ((170, 80, 60), (10, 255, 255))
    green = ((50, 80, 60), (70, 255, 255))
    n_blobs = 0
    for _ in range(10):
        gray, mask = random_scene(rng)
        tint = rng.uniform(0, 1, (3, 3))[rng.integers(0, 3, gray.shape)]  # a colour per pixel
        bgr = np.clip(gray[:, :, None] * (0.3 + tint), 0, 255).astype(np.uint8)
        for config in (DetectorConfig(hsv_ranges=(red, green)),
                       DetectorConfig(hsv_ranges=(green,), mask=mask, min_roundness=0.2)):
            got, ref = detect(bgr, config), detect_reference(bgr, config)
            assert np.isnan(got.threshold) and np.isnan(ref.threshold)
            got.threshold = ref.threshold = 0.0
            assert_same_blobs(got, ref)
            n_blobs += len(got)
    assert n_blobs > 100


def test_threads_detecting_at_once_get_their_own_results():
    # Cameras detect in their own threads and the kernels release the GIL: nothing may be
    # shared between calls (a scratch image would let windows see other frames' blobs).
    # The frames show the same dense spots shifted a little, so every window of one frame
    # holds spots of the others.
    from concurrent.futures import ThreadPoolExecutor

    rng = np.random.default_rng(15)
    uv = spread_out(150, rng, size=(320, 240), sep_px=12.0)
    frames = [render_spots((320, 240), uv + 0.9 * k, 3.0, rng=k) for k in range(6)]
    alone = [detect(img) for img in frames]
    with ThreadPoolExecutor(3) as pool:
        for _ in range(20):
            for got, ref in zip(pool.map(detect, frames), alone, strict=True):
                assert_same_blobs(got, ref, tol_px=0.0)
