"""`calibkit demo`, the README's first command: the whole chain runs and its figures are true."""

from __future__ import annotations

import json


def test_demo_calibrates_reconstructs_and_tracks(tmp_path, calibkit_cli) -> None:
    out = tmp_path / "demo"
    res = calibkit_cli("demo", "--out", out, "--cameras", "4", "--wand-frames", "600",
                       "--track-frames", "60")
    assert res.code == 0, res.err
    for step in ("calibkit wand --sim", "calibkit compare", "calibkit triangulate",
                 "mocapd start --sim"):
        assert step in res.out
    cmp = json.loads((out / "compare.json").read_text())
    assert cmp["grid_rms_mm"] < 1.0  # a wand calibration from nothing, against the truth
    points = json.loads((out / "points.json").read_text())
    assert points["truth"]["recall_3"] > 0.95 and points["truth"]["error_mm_rms"] < 3.0
    track = json.loads((out / "track.json").read_text())
    assert track["frames"] == 60
    assert track["truth"]["position_error_mm_rms"] < 3.0
    assert track["truth"]["body_swaps"] == 0


def test_demo_rejects_a_tiny_rig(tmp_path, calibkit_cli) -> None:
    res = calibkit_cli("demo", "--out", tmp_path, "--cameras", "2")
    assert res.code == 2 and "--cameras >= 3" in res.err
