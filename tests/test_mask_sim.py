"""`calibkit mask --sim`: a mask built from a simulated camera's frames with static
reflections, scored against where the simulator put the reflections and where the markers
image; and `calibkit detect --sim --reflections` with and without it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibkit.synthetic.frames import empty_volume, sim_camera, sim_source
from calibkit.synthetic.reflections import make_reflections, marker_discs, score_mask
from calibkit.vision.masks import build_mask, load_mask


@pytest.mark.parametrize("seed, camera", [(0, "0"), (4, "cam3")])
@pytest.mark.slow  # a whole run of the command
def test_mask_covers_the_reflections_and_not_the_markers(calibkit_cli, tmp_path, seed, camera):
    out, js = tmp_path / "mask.png", tmp_path / "mask.json"
    r = calibkit_cli("mask", "--sim", "--out", out, "--json", js, "--seed", seed, "--camera",
                     camera, "--reflections", 12)
    assert r.code == 0, r.err
    mask = load_mask(out)
    # the truth, read here from the simulator, not from the command's own figures
    cam = sim_camera(int(camera) if camera.isdigit() else camera, seed)
    refl = make_reflections(cam, 12, seed)
    h, w = mask.shape
    assert (w, h) == cam.size
    yy, xx = np.mgrid[0:h, 0:w]
    for (u, v), radius in zip(refl.uv, refl.radius_px, strict=True):
        disc = (xx - u) ** 2 + (yy - v) ** 2 <= radius ** 2
        assert mask[disc].all(), f"reflection at ({u:.0f}, {v:.0f}) r {radius:.1f} not masked"
    # no marker's image is touched, and the mask is made of the reflections only: nothing
    # masked farther than the dilation and the blur's skirt from a reflection
    uv, mradius = marker_discs(cam, sim_source(n_markers=40, camera=cam.name,
                                               seed=seed).xyz[0])
    assert len(uv) > 20
    for (u, v), radius in zip(uv, mradius, strict=True):
        assert not mask[(xx - u) ** 2 + (yy - v) ** 2 <= radius ** 2].any()
    near = np.zeros_like(mask)
    for (u, v), radius in zip(refl.uv, refl.radius_px, strict=True):
        near |= (xx - u) ** 2 + (yy - v) ** 2 <= (radius + 4 + 3) ** 2
    assert not (mask & ~near).any()
    data = json.loads(js.read_text())
    assert data["truth"]["reflections_covered"] == 12 and data["truth"]["markers_touched"] == 0
    assert "against the simulator's truth: 12/12 reflections" in r.out


@pytest.mark.slow  # a whole run of the command
def test_the_score_sees_a_bad_mask(calibkit_cli, tmp_path):
    """A threshold under the background masks everything: the score says so."""
    js = tmp_path / "m.json"
    r = calibkit_cli("mask", "--sim", "--out", tmp_path / "m.png", "--threshold", 5, "--json",
                     js)
    assert r.code == 0, r.err
    truth = json.loads(js.read_text())["truth"]
    assert truth["markers_hidden"] == truth["markers"] > 20


@pytest.mark.slow  # renders frames (EGL, spots)
def test_one_frame_and_no_dilation_miss_the_flicker():
    """Why the defaults: dim reflections' edges flicker with the noise; one frame, no
    dilation leaves some of their pixels out, 30 frames and 4 px catch them all."""
    cam = sim_camera(0, 0)
    refl = make_reflections(cam, 12, 0)
    none = np.zeros((0, 2))
    one = build_mask([next(iter(empty_volume(1, 0, 0, 12))).image], dilate_px=0)
    many = build_mask([f.image for f in empty_volume(30, 0, 0, 12)], dilate_px=4)
    assert score_mask(one, refl, none, np.zeros(0))["reflection_pixels_covered"] < 1.0
    assert score_mask(many, refl, none, np.zeros(0))["reflection_pixels_covered"] == 1.0


@pytest.mark.slow  # a whole run of the command
def test_detect_with_the_mask_drops_the_reflections_only(calibkit_cli, tmp_path):
    out, mask_json = tmp_path / "mask.png", tmp_path / "mask.json"
    assert calibkit_cli("mask", "--sim", "--out", out, "--reflections", 10, "--json",
                        mask_json).code == 0
    # in this scene one marker images inside a lamp: no mask can keep that one
    lost = json.loads(mask_json.read_text())["truth"]["markers_hidden"]
    figures = []
    for extra in ((), ("--mask", out)):
        js = tmp_path / "d.json"
        r = calibkit_cli("detect", "--sim", "--reflections", 10, "--json", js, *extra)
        assert r.code == 0, r.err
        figures.append(json.loads(js.read_text())["truth"])
    bare, masked = figures
    assert bare["false_blobs"] >= 8  # the reflections (two may merge or sit off a marker)
    assert masked["false_blobs"] == 0
    # the mask costs no marker: the one inside a lamp is lost with or without it
    assert masked["found"] == bare["found"] >= bare["markers"] - lost and lost <= 1


@pytest.mark.parametrize("args, words", [
    (("--out", "m.png"), "give a SOURCE or --sim"),
    (("--sim",), "--out"),
    (("x.png", "--sim", "--out", "m.png"), "not both"),
    (("--sim", "--out", "m.png", "--reflections", -1), "--reflections"),
    (("--sim", "--out", "m.png", "--camera", "cam99"), "no camera"),
])
def test_mask_mistakes_are_one_line(calibkit_cli, tmp_path, monkeypatch, args, words):
    monkeypatch.chdir(tmp_path)
    r = calibkit_cli("mask", *args)
    assert r.code == 2 and words in r.err and len(r.err.strip().splitlines()) == 1, r.err
    assert not (tmp_path / "m.png").exists()
