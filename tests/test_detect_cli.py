"""`calibkit detect` and `calibkit mask` as a user runs them."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from calibkit.cameras import Frame, FrameSource
from calibkit.synthetic.spots import render_spots, render_spots_float
from calibkit.synthetic.truthcheck import match_to_truth

SIZE = (320, 240)


def _scene(seed: int, n: int = 6):
    rng = np.random.default_rng(seed)
    cols = np.arange(n) * (SIZE[0] - 40) / n + 30
    uv = np.stack([cols + rng.uniform(-5, 5, n), rng.uniform(20, SIZE[1] - 20, n)], axis=1)
    return render_spots(SIZE, uv, 3.0, rng=seed), uv


def test_detect_one_image_table_json_and_preview(calibkit_cli, tmp_path):
    img, uv = _scene(1)
    cv2.imwrite(str(tmp_path / "cam.png"), img)
    res = calibkit_cli("detect", tmp_path / "cam.png", "--json", tmp_path / "b.json",
                       "--preview", tmp_path / "p.png")
    assert res.code == 0, res.err
    assert "6 blobs in cam" in res.out
    data = json.loads((tmp_path / "b.json").read_text())
    found = np.array([[b["u"], b["v"]] for b in data["blobs"]])
    det, tru = match_to_truth(found, uv)
    assert len(det) == len(uv) == len(found)
    assert np.sqrt(((found[det] - uv[tru]) ** 2).sum(axis=1).mean()) < 0.05
    assert {"u", "v", "area", "peak", "roundness", "bbox"} <= set(data["blobs"][0])
    preview = cv2.imread(str(tmp_path / "p.png"))
    assert preview.shape == (SIZE[1], SIZE[0], 3)
    # The boxes are drawn in green around each blob.
    x0, y0, x1, y1 = data["blobs"][0]["bbox"]
    assert preview[y0 - 1, x0 - 1, 1] > 150 and preview[y0 - 1, x0 - 1, 2] < 100


def test_detect_folder_gives_frames(calibkit_cli, tmp_path):
    truths = []
    for i in range(3):
        img, uv = _scene(10 + i)
        truths.append(uv)
        cv2.imwrite(str(tmp_path / f"f{i}.png"), img)
    res = calibkit_cli("detect", tmp_path, "--json", tmp_path / "out" / "b.json")
    assert res.code == 0, res.err
    data = json.loads((tmp_path / "out" / "b.json").read_text())
    assert [f["index"] for f in data["frames"]] == [0, 1, 2]
    for frame, uv in zip(data["frames"], truths, strict=True):
        found = np.array([[b["u"], b["v"]] for b in frame["blobs"]])
        assert len(match_to_truth(found, uv)[0]) == len(uv)
    assert "18 blobs in 3 frames" in res.out
    res = calibkit_cli("detect", tmp_path, "--frames", "2", "--json", tmp_path / "c.json")
    assert len(json.loads((tmp_path / "c.json").read_text())["frames"]) == 2


def test_filters_multi_and_fixed_threshold_options(calibkit_cli, tmp_path):
    truth = np.array([[100.0, 100.0], [106.6, 100.4], [200.0, 60.0]])  # two touching
    img = render_spots(SIZE, truth, 3.0, rng=3)
    cv2.imwrite(str(tmp_path / "t.png"), img)
    res = calibkit_cli("detect", tmp_path / "t.png", "--json", tmp_path / "a.json")
    assert len(json.loads((tmp_path / "a.json").read_text())["blobs"]) == 2
    res = calibkit_cli("detect", tmp_path / "t.png", "--multi", "--json", tmp_path / "m.json")
    assert res.code == 0, res.err
    assert len(json.loads((tmp_path / "m.json").read_text())["blobs"]) == 3
    res = calibkit_cli("detect", tmp_path / "t.png", "--max-area", "60", "--threshold", "30",
                       "--json", tmp_path / "f.json")
    data = json.loads((tmp_path / "f.json").read_text())
    assert data["threshold"] == 30 and len(data["blobs"]) == 1  # the merged pair is too big
    res = calibkit_cli("detect", tmp_path / "t.png", "--min-roundness", "0.8",
                       "--json", tmp_path / "r.json")
    assert len(json.loads((tmp_path / "r.json").read_text())["blobs"]) == 1


def test_hsv_option_labels_colours(calibkit_cli, tmp_path):
    red = render_spots_float(SIZE, [[80.0, 120.0]], 4.0, peak=220)
    green = render_spots_float(SIZE, [[240.0, 120.0]], 4.0, peak=220)
    img = np.clip(np.stack([red * 0 + 5, green + 5, red + 5], axis=2), 0, 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "c.png"), img)
    res = calibkit_cli("detect", tmp_path / "c.png", "--hsv", "50,80,60:70,255,255",
                       "--hsv", "170,80,60:10,255,255", "--json", tmp_path / "h.json")
    assert res.code == 0, res.err
    blobs = json.loads((tmp_path / "h.json").read_text())["blobs"]
    by_label = {b["label"]: (b["u"], b["v"]) for b in blobs}
    assert len(blobs) == 2
    assert np.allclose(by_label[0], (240, 120), atol=0.1)
    assert np.allclose(by_label[1], (80, 120), atol=0.1)


def test_mask_command_then_detect_with_it(calibkit_cli, tmp_path):
    rng = np.random.default_rng(4)
    lamp = render_spots_float(SIZE, [[50.0, 50.0]], 8.0, peak=250)
    for i in range(3):
        empty = np.clip(8 + lamp + rng.normal(0, 2, lamp.shape), 0, 255).astype(np.uint8)
        cv2.imwrite(str(tmp_path / f"empty{i}.png"), empty)
    res = calibkit_cli("mask", tmp_path, "--out", tmp_path / "mask.png", "--dilate", "3",
                       "--json", tmp_path / "mask.json")
    assert res.code == 0, res.err
    figures = json.loads((tmp_path / "mask.json").read_text())
    assert figures["frames"] == 3 and figures["areas"] == 1
    # A disc of radius ~8 px (+ blur above the threshold) grown by 3 px.
    assert np.pi * 9**2 < figures["masked_pixels"] < np.pi * 14**2
    img, uv = _scene(5)
    with_lamp = np.clip(img + lamp, 0, 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "scene.png"), with_lamp)
    res = calibkit_cli("detect", tmp_path / "scene.png", "--mask", tmp_path / "mask.png",
                       "--json", tmp_path / "d.json")
    assert res.code == 0, res.err
    found = np.array([[b["u"], b["v"]] for b in
                      json.loads((tmp_path / "d.json").read_text())["blobs"]])
    assert len(found) == len(match_to_truth(found, uv)[0]) == len(uv)


def test_sim_option_scores_against_truth(calibkit_cli, tmp_path, monkeypatch):
    # The command's --sim path with a stand-in scene (the simulator has its own tests).
    import calibkit.synthetic.frames as frames_module

    class Scene(FrameSource):
        camera = "cam0"
        truth_uv: dict = {}

        def __iter__(self):
            for i in range(2):
                img, self.truth_uv[i] = _scene(30 + i)
                yield Frame("cam0", i, i * 10_000_000, img)

    # the command imports sim_source when it runs (issue 31): patch it at its source
    monkeypatch.setattr(frames_module, "sim_source", lambda **kw: Scene())
    res = calibkit_cli("detect", "--sim", "--frames", "2", "--json", tmp_path / "s.json")
    assert res.code == 0, res.err
    truth = json.loads((tmp_path / "s.json").read_text())["truth"]
    assert truth["recall"] == 1.0 and truth["false_blobs"] == 0
    assert truth["centroid_rms_px"] < 0.05
    assert "recall 100.0%" in res.out


@pytest.mark.parametrize("args, message", [
    (["detect", "{tmp}/missing.png"], "not found"),
    (["detect", "{tmp}/img.png", "--threshold", "bright"], "--threshold"),
    (["detect", "{tmp}/img.png", "--threshold", "-5"], "--threshold"),
    (["detect", "{tmp}/img.png", "--hsv", "1,2,3"], "--hsv"),
    (["detect", "{tmp}/img.png", "--hsv", "200,0,0:10,255,255"], "HSV"),
    (["detect", "{tmp}/img.png", "--min-area", "50", "--max-area", "10"], "area"),
    (["detect", "{tmp}/img.png", "--frames", "0"], "--frames"),
    (["detect", "{tmp}/img.png", "--mask", "{tmp}/small.png"], "mask"),
    (["detect", "{tmp}/img.png", "--mask", "{tmp}/nomask.png"], "not found"),
    (["detect"], "SOURCE"),
    (["detect", "{tmp}/notes.txt"], "video"),
    (["mask", "{tmp}/missing", "--out", "{tmp}/m.png"], "not found"),
    (["mask", "{tmp}/img.png", "--out", "{tmp}/m.png", "--dilate", "-1"], "--dilate"),
])
def test_bad_input_is_one_line_and_exit_2(calibkit_cli, tmp_path, args, message):
    img, _ = _scene(0)
    cv2.imwrite(str(tmp_path / "img.png"), img)
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((10, 10), np.uint8))
    (tmp_path / "notes.txt").write_text("hello")
    res = calibkit_cli(*(a.format(tmp=tmp_path) for a in args))
    assert res.code == 2
    lines = res.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("calibkit: error:"), res.err
    assert message in lines[0]
    assert not (tmp_path / "m.png").exists()


def test_sim_with_the_simulator(calibkit_cli, tmp_path):
    res = calibkit_cli("detect", "--sim", "--markers", "30", "--seed", "3", "--json",
                       tmp_path / "s.json")
    assert res.code == 0, res.err
    data = json.loads((tmp_path / "s.json").read_text())
    assert data["camera"] == "cam0" and len(data["blobs"]) >= 10
    assert data["truth"]["recall"] >= 0.95 and data["truth"]["false_blobs"] == 0
    assert data["truth"]["centroid_rms_px"] < 0.2
    res = calibkit_cli("detect", "--sim", "--camera", "cam9")
    assert res.code == 2 and "no camera" in res.err
