"""calibkit.calibrate.wand_shape: the shape uncertainty a wand solve predicts from its own
covariance, against the simulator's truth, and what the wand report says with it."""

from __future__ import annotations

import numpy as np
import pytest

from calibkit.calibrate import wand_shape
from calibkit.calibrate.wand_solve import calibrate
from calibkit.core.camera import BASLER_658x492_DIST, Rig
from calibkit.core.geometry import rigid_fit, triangulate
from calibkit.synthetic import sim

SPACING = (0.0, 0.2, 0.5)
NOISE_PX = 0.1


@pytest.fixture(scope="module")
def scene():
    rig = sim.make_rig(6, 4.0, size=(658, 492), dist=BASLER_658x492_DIST, seed=3)
    truth = sim.wand_motion(400, 100.0, 4.0, SPACING, seed=3)
    bare = Rig(tuple(c.replace(rvec=np.zeros(3), t=np.zeros(3)) for c in rig))
    return rig, truth, bare


def _box_error_mm(true_rig: Rig, rig: Rig, grid: np.ndarray) -> float:
    """Grid RMS (mm) of `rig` over `grid` after the best similarity: the quantity
    shape_uncertainty predicts."""
    point, camera, uv = wand_shape._views(true_rig, grid)
    xyz = triangulate(rig, point, camera, uv, n_points=len(grid), ray_distance=False).xyz
    ok = np.isfinite(xyz).all(axis=1)
    R, t, s = rigid_fit(xyz[ok], grid[ok], scale=True)
    return float(np.sqrt(np.mean(np.sum((s * xyz[ok] @ R.T + t - grid[ok]) ** 2, axis=1)))
                 * 1000.0)


def test_prediction_matches_the_error_against_the_truth(scene):
    """Exact intrinsics given: held, the rig's error is small and so is the prediction;
    refined from the wand alone, both grow many times over, and the prediction (one sigma,
    RMS over the draws) stays within a factor of two of the error the truth shows."""
    rig, truth, bare = scene
    box = wand_shape.wand_grid(rig, truth.xyz)
    assert len(box) > 100
    err = {False: [], True: []}
    pred = {False: [], True: []}
    known = []
    for draw in (11, 12, 13):
        obs = sim.observe(rig, truth, noise_px=NOISE_PX, seed=draw)
        for refine in (False, True):
            cal = calibrate(obs, bare, SPACING, refine_intrinsics=refine, seed=3)
            shape = cal.report["shape_uncertainty"]
            assert shape["intrinsics_refined"] is refine
            err[refine].append(_box_error_mm(rig, cal.rig, box))
            pred[refine].append(shape["grid_rms_mm"])
            if refine:
                known.append(shape["intrinsics_known_mm"])
                assert shape["intrinsics_part_mm"] > shape["intrinsics_known_mm"]
                # knowing one group of parameters helps, but less than knowing them all
                for group, mm in shape["if_known_mm"].items():
                    assert shape["intrinsics_known_mm"] < mm < shape["grid_rms_mm"], group

    def rms(v):
        return float(np.sqrt(np.mean(np.square(v))))
    for refine in (False, True):
        ratio = rms(err[refine]) / rms(pred[refine])
        assert 0.4 < ratio < 2.0, (refine, err[refine], pred[refine])
    assert rms(err[True]) > 3 * rms(err[False])
    assert rms(pred[True]) > 3 * rms(pred[False])
    # conditioning the refined solve on known intrinsics gives the held solve's figure
    assert 0.5 < rms(known) / rms(pred[False]) < 2.0


def test_report_says_what_the_capture_cannot_rule_out(scene):
    """The default keeps exact intrinsics given without uncertainties; the report says the
    shape uncertainty refining would have left and each kept camera's intrinsics' standard
    deviations from the wand alone. Refining all warns that only other views rule it out."""
    rig, truth, bare = scene
    obs = sim.observe(rig, truth, noise_px=NOISE_PX, seed=11)
    kept = calibrate(obs, bare, SPACING, seed=3)
    shape = kept.report["shape_uncertainty"]
    rows = kept.report["intrinsics"]["cameras"]
    assert all(r["chosen"] == "kept" for r in rows)
    assert shape["if_refined_mm"] > 3 * shape["grid_rms_mm"]
    assert "exact" in shape["note"]
    for r in rows:
        std = r["cannot_rule_out"]
        assert set(std) == set(wand_shape.NAMES)
        # the wand pins them better than the loose default prior (1 % focal, 5 px centre)
        # does, but not to nothing
        assert 0 < std["fx"] < 0.5 * 0.01 * rig[r["name"]].fx
        assert 0 < std["cx"] < 0.5 * 5.0
    refined = calibrate(obs, bare, SPACING, refine_intrinsics=True, seed=3)
    assert "if_refined_mm" not in refined.report["shape_uncertainty"]
    assert any("only so far" in w for w in refined.report["warnings"])
    assert not any("only so far" in w for w in kept.report["warnings"])


def test_no_box_no_figure(scene):
    """A solve whose points fill no volume two cameras see gives a reason, not a number."""
    rig, _, _ = scene
    assert len(wand_shape.wand_grid(rig, np.full((5, 3), np.nan))) == 0
