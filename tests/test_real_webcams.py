"""Correspondence and triangulation at default settings on a real 4-webcam ChArUco session
(issue 28), scored with the corners' ids, which only the scorer reads."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from calibkit.core.errors import UserError
from calibkit.core.geometry import triangulate
from calibkit.core.recording import save_observations
from calibkit.synthetic.caliscope_session import (
    caliscope_spacing,
    classify_lost,
    load_session,
    score_board,
    spacing_pairs,
)
from calibkit.vision.correspondence import CorrespondenceConfig
from calibkit.vision.gates import estimate_residual
from calibkit.vision.reconstruct import reconstruct

SESSION = Path(__file__).resolve().parents[1] / "fixtures" / "caliscope_4cam"
SPACING_TARGET_MM = 0.80  # the recording tool's own figure, as issue 28 states it


@pytest.fixture(scope="module")
def session():
    return load_session(SESSION)


@pytest.fixture(scope="module")
def defaults(session):
    """`calibkit triangulate`'s path at its defaults: no residual in the rig, so measured."""
    return reconstruct(session.rig, session.obs, CorrespondenceConfig(), None, False, set())


def _labelled_residual_px(session) -> float:
    """The rig's residual with the ids: every corner seen by >= 3 cameras triangulated from
    all its blobs, RMS of the blobs' reprojection errors (the calibrations' definition)."""
    obs = session.obs
    _, point, count = np.unique(obs.frame * 10**7 + session.corner, return_inverse=True,
                                return_counts=True)
    cam = obs.camera.astype(np.int64)
    tri = triangulate(session.rig, point, cam, obs.uv, iterations=3, n_points=len(count))
    keep = count[point] >= 3
    xyz = tri.xyz[point[keep]]
    err = np.array([np.linalg.norm(session.rig[int(c)].project(x[None])[0][0] - uv)
                    for c, x, uv in zip(cam[keep], xyz, obs.uv[keep], strict=True)])
    return float(np.sqrt(np.mean(err**2)))


def test_the_estimate_gets_no_ids(session) -> None:
    assert session.obs.marker is None
    assert len(session.obs) == 1725 and len(session.rig) == 4  # rows of xy.csv, by hand
    assert session.square_m() == pytest.approx(0.054, abs=1e-6)  # charuco.toml: 5.4 cm


def test_defaults_recover_97_percent_of_corners_seen_by_3_cameras(session, defaults) -> None:
    points = defaults.points
    score = score_board(session, points.frame, points.rows, points.xyz)
    assert score.corners_seen_3 == 460  # counted by hand from xy.csv
    assert defaults.residual.source == "estimated from data"
    assert score.recovered_fraction >= 0.97, score.as_dict()
    assert score.ghost_fraction <= 0.005
    # every blob used at most once
    used = points.rows[points.rows >= 0]
    assert len(np.unique(used)) == len(used)


def test_spacing_no_worse_than_the_recording_tools(session, defaults) -> None:
    points = defaults.points
    score = score_board(session, points.frame, points.rows, points.xyz)
    assert score.spacing_pairs >= 550  # most of the frames' adjacent pairs, not a chosen few
    assert score.spacing_mm_rms <= SPACING_TARGET_MM
    # caliscope's own points on the same adjacent pairs, each corner the mean of its pairs
    pairs, theirs_mm, _ = caliscope_spacing(session, spacing_pairs(session, points.frame,
                                                                    points.rows))
    assert pairs == score.spacing_pairs
    assert score.spacing_mm_rms <= theirs_mm


def test_the_residual_measured_on_the_data_is_not_censored_by_its_own_gates(session) -> None:
    """The cause of the lost corners: measured through the gates it sets, the residual
    settled 30 % below the one the ids give; measured through a wider reprojection gate it
    is close to it, and the old estimate loses more than 3 % of the corners."""
    labelled = _labelled_residual_px(session)
    now = estimate_residual(session.rig, session.obs)
    before = estimate_residual(session.rig, session.obs, rounds=3, reproj_widen=1.0)
    assert now.px == pytest.approx(labelled, rel=0.2)
    assert before.px < 0.8 * labelled
    old = reconstruct(session.rig, session.obs, CorrespondenceConfig(), before.px, False, set())
    score = score_board(session, old.points.frame, old.points.rows, old.points.xyz)
    assert score.recovered_fraction < 0.97
    # every corner lost that way has a blob beyond the reprojection gate: the gate, not time
    lost = classify_lost(session, score.lost, old.config.epipolar_px,
                         old.config.max_reproj_px)
    assert lost and all("reprojection gate" in c.cause for c in lost)


def test_triangulate_command_on_the_session(session, defaults, tmp_path, calibkit_cli) -> None:
    session.rig.save(tmp_path / "rig.toml")
    save_observations(tmp_path / "blobs.csv", session.obs)
    res = calibkit_cli("triangulate", "--rig", tmp_path / "rig.toml", "--from",
                       tmp_path / "blobs.csv", "--out", tmp_path / "points.csv", "--json",
                       tmp_path / "fig.json")
    assert res.code == 0, res.err
    assert "estimated from data" in res.err
    fig = json.loads((tmp_path / "fig.json").read_text())
    assert fig["points"] == len(defaults.points.frame)
    assert fig["residual"]["px"] == pytest.approx(defaults.residual.px, rel=1e-3)  # CSV digits


def test_a_broken_session_is_one_user_error(tmp_path) -> None:
    broken = tmp_path / "session"
    shutil.copytree(SESSION, broken)
    xy = broken / "calibration" / "extrinsic" / "xy.csv"
    text = xy.read_text().splitlines()
    xy.write_text("\n".join([text[0].replace("img_loc_x", "u")] + text[1:]) + "\n")
    with pytest.raises(UserError, match="no column img_loc_x"):
        load_session(broken)
    xy.write_text("\n".join(text[:2] + [text[2].replace(text[2].split(",")[6], "nan")]) + "\n")
    with pytest.raises(UserError, match="not finite"):
        load_session(broken)
