"""`calibkit demo`, the README's first command: the whole chain runs and its figures are true."""

from __future__ import annotations

import json


def test_demo_calibrates_reconstructs_and_tracks(tmp_path, calibkit_cli) -> None:
    out = tmp_path / "demo"
    # the simulated cameras open up to 0.3 s apart (as real ones do; the sets wait for
    # them): 240 frames at 240 fps leave most of a second with every camera
    res = calibkit_cli("demo", "--out", out, "--cameras", "4", "--wand-frames", "600",
                       "--track-frames", "240")
    assert res.code == 0, res.err
    # the chain as a user runs it, in order, each step from the previous step's estimate
    steps = ["calibkit sim rig", "calibkit intrinsic --sim", "calibkit extrinsic --projector",
             "calibkit wand --sim", "calibkit compare", "calibkit triangulate",
             "mocapd start --sim"]
    at = [res.out.index(step) for step in steps]
    assert at == sorted(at)
    world = str(out / "world.truth.toml")
    assert f"--intrinsics {out / 'intrinsics.toml'}" in res.out
    assert f"--rig {out / 'extrinsic.toml'} --dots {out / 'extrinsic.dots.npz'}" in res.out
    for line in res.out.splitlines():  # the truth goes only to the simulator and scorers
        if line.startswith("$ calibkit ") and world in line:
            assert "--sim-rig " + world in line or line.startswith(
                ("$ calibkit compare", "$ calibkit sim")), line
    assert "The intrinsics came from the monitor step" in res.out
    assert "gross errors" in res.out
    intr = json.loads((out / "intrinsic.json").read_text())["cameras"]
    assert len(intr) == 4 and all(abs(c["error"]["fx_rel"]) < 1e-3 for c in intr)
    cmp = json.loads((out / "compare.json").read_text())
    # 4 cameras, 600 wand frames at 0.1 px, from the monitor's intrinsics: about a mm
    assert cmp["grid_rms_mm"] < 2.0 and cmp["grid_gross_points"] == 0
    points = json.loads((out / "points.json").read_text())
    # scored in the true world frame, which the floor dots' 5 mm tape measurements place
    # to a few mm: the error is mostly that offset
    assert points["truth"]["recall_3"] > 0.95 and points["truth"]["error_mm_rms"] < 5.0
    track = json.loads((out / "track.json").read_text())
    assert track["frames"] == 240
    assert track["truth"]["position_error_mm_rms"] < 5.0
    assert track["truth"]["body_swaps"] == 0
    assert track["truth"]["tracking_rig"].startswith("calibrated:")  # the wand's rig
    # the bodies were defined live from the blobs, as a user would (not the simulator's)
    assert len(track["bodies_defined_live"]["bodies"]) == 3
    assert (out / "rt" / "sim-bodies.toml").exists()
    assert "defined live" in res.out and "defined from the markers mocapd tracks" in res.out
    assert all(b["defined_as"] for b in track["truth"]["bodies"].values())


def test_demo_rejects_a_tiny_rig(tmp_path, calibkit_cli) -> None:
    res = calibkit_cli("demo", "--out", tmp_path, "--cameras", "2")
    assert res.code == 2 and "--cameras >= 3" in res.err
