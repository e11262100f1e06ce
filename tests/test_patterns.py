"""Dot schedules and decoding: Gray codes with parity, dropped and noisy frames, neighbours."""

from __future__ import annotations

import numpy as np
import pytest

from projector.patterns import (
    ROLE_BIT,
    ROLE_OFF,
    ROLE_ON,
    check_by_neighbours,
    code_bits,
    coded_schedule,
    decode_levels,
    gray_decode,
    gray_encode,
    identify_by_neighbours,
    raster_schedule,
)


def test_gray_code_round_trip_and_neighbours_differ_by_one_bit():
    n = np.arange(5000)
    g = gray_encode(n)
    assert np.array_equal(gray_decode(g), n)
    flips = np.array([bin(int(v)).count("1") for v in g[1:] ^ g[:-1]])
    assert np.all(flips == 1)
    bits = code_bits(n, 13)
    assert np.all(bits.sum(axis=1) % 2 == 0)  # parity makes every code even


def test_coded_schedule_frames_spell_each_dot_code():
    sch = coded_schedule((640, 400), step_px=40, shifts=2, radius_px=4, predict=False)
    assert len(sch.layers) == 4
    n0 = len(sch.layers[0])
    assert sch.n_bits == int(np.ceil(np.log2(max(len(layer) for layer in sch.layers))))
    frames = [sch.frames[i] for i in sch.layer_frames(0)]
    assert [f.role for f in frames[:2]] == [ROLE_ON, ROLE_OFF]
    assert all(f.role == ROLE_BIT for f in frames[2:]) and len(frames) == 2 + sch.n_bits + 1
    # rebuild every dot's code from which frames show it
    shown = np.zeros((n0, sch.n_bits + 1), bool)
    for f in frames[2:]:
        shown[f.ids - sch.layers[0][0], f.bit] = True
    assert np.array_equal(shown, code_bits(np.arange(n0), sch.n_bits))
    xy = sch.points_xy
    assert xy.min() >= 4 and xy[:, 0].max() <= 639 - 4 and xy[:, 1].max() <= 399 - 4
    assert len(np.unique(np.round(xy, 6), axis=0)) == len(xy)  # layers never coincide
    # layers are offset by half a step
    d = sch.points_xy[sch.layers[1][0]] - sch.points_xy[sch.layers[0][0]]
    np.testing.assert_allclose(d, [20.0, 0.0])


def test_predicted_layers_take_one_frame_each():
    coded = coded_schedule((1920, 1080), 80, 2, 6, predict=False)
    fast = coded_schedule((1920, 1080), 80, 2, 6, predict=True)
    assert len(fast.frames) == len(coded.layer_frames(0)) + 3
    assert len(fast.frames) < len(coded.frames) / 3


def test_raster_schedule_one_dot_per_frame():
    sch = raster_schedule((320, 240), step_px=40, radius_px=3)
    assert len(sch.frames) == len(sch.points_xy)
    assert all(len(f.xy) == 1 for f in sch.frames)


def _levels(n_codes, n_bits, rng, noise=3.0, on=150.0, off=20.0):
    idx = rng.permutation(n_codes)
    bits = code_bits(idx, n_bits)
    gain = rng.uniform(0.5, 1.0, len(idx))  # vignetting: each dot its own brightness
    lv_on = off + gain * (on - off) + rng.normal(0, noise, len(idx))
    lv_off = off + rng.normal(0, noise, len(idx))
    lv = off + gain[:, None] * (on - off) * bits + rng.normal(0, noise, bits.shape)
    return idx, lv_on, lv_off, lv


def test_decode_noisy_levels():
    rng = np.random.default_rng(0)
    idx, on, off, lv = _levels(300, 9, rng)
    dec = decode_levels(on, off, lv, 300)
    assert dec.ok.all() and np.array_equal(dec.index, idx)
    assert not dec.restored.any()


def test_decode_restores_one_dropped_frame_from_parity():
    rng = np.random.default_rng(1)
    idx, on, off, lv = _levels(300, 9, rng)
    for col in range(lv.shape[1]):  # whichever frame was dropped
        dropped = lv.copy()
        dropped[:, col] = np.nan
        dec = decode_levels(on, off, dropped, 300)
        assert dec.ok.all() and np.array_equal(dec.index, idx)
        assert dec.restored.all()


def test_decode_rejects_rather_than_guesses():
    rng = np.random.default_rng(2)
    idx, on, off, lv = _levels(300, 9, rng)
    two = lv.copy()
    two[:, [1, 4]] = np.nan  # two frames dropped: not recoverable
    assert not decode_levels(on, off, two, 300).ok.any()
    # a bit confidently wrong (a reflection lit it): the parity check catches it
    flipped = lv.copy()
    flipped[:, 3] = np.where(lv[:, 3] > 0.5 * (on + off), off, on)
    dec = decode_levels(on, off, flipped, 300)
    assert not dec.ok.any()
    # an ambiguous bit (half-lit) is an erasure, restored from the parity
    half = lv.copy()
    half[:, 5] = 0.5 * (on + off)
    dec = decode_levels(on, off, half, 300)
    assert dec.ok.all() and np.array_equal(dec.index, idx)
    # a dot with no contrast (outside the screen) is rejected
    flat = decode_levels(off + 2.0, off, lv, 300)
    assert not flat.ok.any()


@pytest.mark.parametrize("noise", [0.0, 15.0])
def test_decode_under_noise(noise):
    rng = np.random.default_rng(3)
    idx, on, off, lv = _levels(500, 9, rng, noise=noise)
    dec = decode_levels(on, off, lv, 500)
    wrong = np.sum(dec.index[dec.ok] != idx[dec.ok])
    if noise == 0.0:
        assert dec.ok.all() and wrong == 0
    else:
        # heavy noise (SNR ~ 4 on the dimmest dots): most still decode, and the parity
        # bit keeps wrong ids to a few per cent (check_by_neighbours removes those)
        assert dec.ok.mean() > 0.8 and wrong <= 0.03 * dec.ok.sum()


def _to_image(xy):
    """A smooth, distorted projective map screen -> image (as a tilted monitor gives)."""
    H = np.array([[0.26, 0.03, 40.0], [-0.02, 0.25, 30.0], [1.2e-5, -2.0e-5, 1.0]])
    p = np.column_stack([xy, np.ones(len(xy))]) @ H.T
    uv = p[:, :2] / p[:, 2:]
    c = np.array([320.0, 240.0])
    r2 = np.sum(((uv - c) / 500.0) ** 2, axis=1, keepdims=True)
    return c + (uv - c) * (1 - 0.15 * r2)


def test_identify_shifted_layer_by_neighbours():
    sch = coded_schedule((1920, 1080), 80, 2, 6)
    ref = sch.layers[0]
    rng = np.random.default_rng(4)
    ref_uv = _to_image(sch.points_xy[ref]) + rng.normal(0, 0.05, (len(ref), 2))
    for layer in (1, 2, 3):
        ids = sch.layers[layer]
        seen = rng.random(len(ids)) < 0.9  # some dots not detected
        uv = _to_image(sch.points_xy[ids[seen]]) + rng.normal(0, 0.05, (seen.sum(), 2))
        stray = rng.uniform(0, 640, (20, 2))  # reflections
        got = identify_by_neighbours(sch.points_xy[ref], ref_uv, sch.points_xy[ids],
                                     np.vstack([uv, stray]))
        truth = np.nonzero(seen)[0]
        named = got[: len(uv)]
        assert np.mean(named == truth) > 0.95
        assert np.all((named == truth) | (named == -1))  # never a wrong name
        far = np.linalg.norm(stray[:, None] - uv[None], axis=2).min(axis=1) > 3.0
        assert np.all(got[len(uv):][far] == -1)


def test_check_by_neighbours_catches_wrong_ids():
    sch = coded_schedule((1920, 1080), 80, 1, 6)
    xy = sch.points_xy
    rng = np.random.default_rng(5)
    uv = _to_image(xy) + rng.normal(0, 0.05, xy.shape)
    named = xy.copy()
    wrong = rng.choice(len(xy), 15, replace=False)
    named[wrong] = xy[rng.permutation(wrong)]  # 15 dots decoded as each other
    named[wrong[0]] = xy[(wrong[0] + 1) % len(xy)]  # and one as its own neighbour
    ok = check_by_neighbours(named, uv)
    assert not ok[wrong].any()
    right = np.setdiff1d(np.arange(len(xy)), wrong)
    assert ok[right].mean() > 0.97
