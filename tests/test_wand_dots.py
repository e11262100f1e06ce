"""`calibkit wand --dots`: the projector's floor and table dots solved with the wand."""

from __future__ import annotations

import json

import pytest

from calibkit.calibrate.compare import compare_rigs
from calibkit.core.camera import Rig


@pytest.fixture(scope="module")
def extrinsic_run(tmp_path_factory):
    """An extrinsic calibration on the simulator, from the monitor step's intrinsics, and a
    wand capture with the same true rig."""
    import sys

    from calibkit.cli import app
    from calibkit.clitools import run_app

    folder = tmp_path_factory.mktemp("ex")
    for argv in (["intrinsic", "--sim", "--camera", "all", "--no-render", "--views", "4",
                  "--step", "120", "--rig", folder / "intr.toml"],
                 ["extrinsic", "--projector", "--sim", "--intrinsics", folder / "intr.toml",
                  "--out", folder / "ex.toml"],
                 ["sim", "wand", "--rig", folder / "ex.truth.toml", "--frames", "500",
                  "--out", folder / "w.mcrec"]):
        old = sys.argv
        sys.argv = ["calibkit", *map(str, argv)]
        try:
            run_app(app, "calibkit")
        except SystemExit as exc:
            assert not exc.code
        finally:
            sys.argv = old
    return folder


def test_dots_keep_the_tape_frame_and_the_wand_sharpens_the_rig(extrinsic_run,
                                                                calibkit_cli) -> None:
    f = extrinsic_run
    # the monitor's intrinsics kept: the poses and the frame are what is tested here
    res = calibkit_cli("wand", "--from", f / "w.mcrec", "--rig", f / "ex.toml", "--dots",
                       f / "ex.dots.npz", "--fix-intrinsics", "--out", f / "final.toml",
                       "--json", f / "w.json")
    assert res.code == 0, res.err
    truth, before, after = (Rig.load(f / n) for n in ("ex.truth.toml", "ex.toml",
                                                      "final.toml"))
    # the world frame stays the projector's (no re-alignment needed) ...
    absolute = compare_rigs(truth, after, align=False)
    assert max(c["position_mm"] for c in absolute["cameras"]) < 10.0
    assert absolute["grid_rms_mm"] <= compare_rigs(truth, before, align=False)["grid_rms_mm"]
    # ... and the rig's own shape is the wand's: far better than the dots alone
    assert compare_rigs(truth, after)["grid_rms_mm"] < 0.5 * compare_rigs(
        truth, before)["grid_rms_mm"]
    assert json.loads((f / "w.json").read_text())["grade"] in ("excellent", "good")


def test_dots_need_the_extrinsic_poses(extrinsic_run, calibkit_cli) -> None:
    f = extrinsic_run
    res = calibkit_cli("wand", "--from", f / "w.mcrec", "--intrinsics", f / "ex.toml",
                       "--dots", f / "ex.dots.npz", "--out", f / "x.toml")
    assert res.code == 2 and "--dots needs --rig" in res.err
    res = calibkit_cli("wand", "--from", f / "w.mcrec", "--rig", f / "ex.toml", "--dots",
                       f / "missing.npz", "--out", f / "x.toml")
    assert res.code == 2 and "no such file" in res.err
