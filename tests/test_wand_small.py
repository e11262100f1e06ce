"""The wand solve on real-sized captures (2-4 cameras, 30-100 frames, few or no frames held
out), a wand of unknown length, degenerate input, intrinsics refined only where the capture
shows it pays, and the grade's structure checks, against the simulator's truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibkit.calibrate import wand_report, wand_systematics
from calibkit.calibrate.compare import compare_rigs
from calibkit.calibrate.wand_solve import calibrate
from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.observations import Observations
from calibkit.core.recording import save_observations
from calibkit.synthetic import sim
from calibkit.synthetic.miscalibrate import off_intrinsics

WAND_M = 0.7  # the true wand; the solve is told (0, 1) and that its length is unknown
NOISE_PX = 0.7  # a hand-digitised capture


def _small(n_cams: int, frames: int, seed: int, noise_px: float = NOISE_PX):
    """A small capture of a 2-end wand (pinhole cameras) and its bare intrinsics."""
    rig = sim.make_rig(n_cams, 4.0, dist=(0, 0, 0, 0, 0), seed=seed)
    truth = sim.wand_motion(frames, 5.0, 4.0, (0.0, WAND_M), seed=seed)
    obs = sim.observe(rig, truth, noise_px=noise_px, seed=seed, blobs="ideal")
    bare = Rig(tuple(c.replace(rvec=np.zeros(3), t=np.zeros(3)) for c in rig))
    return rig, obs, bare


def _true_length_variation_pct(rig: Rig, obs: Observations) -> float:
    """The wand-length variation the true rig gives on the same blobs (true end labels):
    what noise alone leaves."""
    from calibkit.core.geometry import triangulate

    lab = obs.select(obs.marker >= 0)
    keys, pid = np.unique(lab.frame * 2 + lab.marker, return_inverse=True)
    xyz = triangulate(rig, pid, lab.camera.astype(np.int64), lab.uv, n_points=len(keys),
                      ray_distance=False).xyz
    ends = np.full((keys.max() // 2 + 1, 2, 3), np.nan)
    ends[keys // 2, keys % 2] = xyz
    length = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
    length = length[np.isfinite(length)]
    return float(100 * np.std(length, ddof=1) / np.mean(length))


@pytest.mark.parametrize("n_cams,frames,seed", [(2, 40, 0), (3, 30, 1), (3, 50, 0),
                                                (4, 30, 0), (4, 100, 1)])
def test_small_captures_start_from_pairwise_geometry_and_solve(n_cams, frames, seed):
    rig, obs, bare = _small(n_cams, frames, seed)
    cal = calibrate(obs, bare, (0.0, 1.0), length_known=False, seed=seed)
    # every camera placed from nothing; the shape right to a few mm at 0.7 px over 4 m,
    # and the scale the unknown wand's: 0.7 m per unit of --spacing
    assert cal.rig.names == rig.names
    cmp = compare_rigs(rig, cal.rig, align=True)
    assert cmp["grid_rms_mm"] < 15.0
    assert cmp["alignment"]["scale"] == pytest.approx(WAND_M, rel=0.01)
    # the wand-length variation is the noise's, not the calibration's
    report = cal.report
    truth_pct = _true_length_variation_pct(rig, obs)
    assert report["solve"]["wand_length_variation_pct"] < 1.6 * truth_pct + 0.1
    assert report["scale"]["known"] is False and "scale is unknown" in report["grade_reason"]
    # exact intrinsics without uncertainties: the capture cannot improve on them, kept
    assert all(c["chosen"] == "kept" for c in report["intrinsics"]["cameras"])


def test_every_figure_is_a_number_or_says_why_not():
    rig, obs, bare = _small(3, 50, 0)
    for holdout in (0.1, 0.0):
        cal = calibrate(obs, bare, (0.0, 1.0), length_known=False, holdout=holdout)
        report = json.loads(json.dumps(cal.report, default=lambda v: np.asarray(v).tolist()))
        syst = report["systematic"]
        for key in ("volume", "radius", "region", "trend"):
            pct = syst[f"{key}_pct"]
            assert (pct is not None and np.isfinite(pct)) != (f"{key}_reason" in syst), key
        # 50 frames: too few to hold whole regions of the volume out, enough for the rest
        assert "region_reason" in syst and np.isfinite(syst["trend_pct"])
        held = report["held_out"]
        if holdout == 0:
            assert held["frames"] == 0 and "--holdout 0" in held["reason"]
            assert "none were held out" in report["grade_reason"]
            assert "--holdout 0" in syst["region_reason"]
        else:
            assert held["frames"] == 5 and "reason" not in held
            assert np.isfinite(held["wand_length_variation_pct"])


def test_unknown_length_is_the_known_solve_scaled():
    rig, obs, bare = _small(3, 50, 2)
    free = calibrate(obs, bare, (0.0, 1.0), length_known=False, seed=2)
    metres = calibrate(obs, bare, (0.0, WAND_M), seed=2)
    assert metres.report["scale"] == {"known": True, "source": "wand length",
                                      "wand_length_m": pytest.approx(WAND_M)}
    # the same rig up to scale: scale-free figures agree, positions scale by the length
    cmp = compare_rigs(metres.rig, free.rig, align=True)
    assert cmp["alignment"]["scale"] == pytest.approx(WAND_M, rel=1e-3)
    assert cmp["grid_rms_mm"] < 0.5
    for key in ("wand_length_variation_pct", "reprojection_rms_px"):
        assert free.report["solve"][key] == pytest.approx(metres.report["solve"][key],
                                                          rel=0.02)


def _nan_rows(obs: Observations) -> Observations:
    out = obs.select(np.ones(len(obs), dtype=bool))
    out.uv = out.uv.copy()
    out.uv[::7] = np.nan  # cells not digitised
    return out


def _collinear(seed: int):
    """A wand moved along one line, never turning: no parallax to place a camera by."""
    rig = sim.make_rig(3, 4.0, dist=(0, 0, 0, 0, 0), seed=seed)
    s = np.linspace(-0.5, 0.5, 40)[:, None]
    centre = np.array([0.0, 0.0, 1.0]) + s * np.array([1.0, 0.0, 0.0])
    ends = np.stack([centre - [0, 0.35, 0], centre + [0, 0.35, 0]], axis=1)
    from calibkit.core.observations import Truth

    truth = Truth(np.repeat(np.arange(40), 2), np.tile([0, 1], 40), ends.reshape(-1, 3))
    return rig, sim.observe(rig, truth, noise_px=0.5, seed=seed, blobs="ideal")


def _degenerate_cases():
    rig, obs, bare = _small(2, 30, 4)
    one_frame = obs.select(obs.frame == obs.frame[0])
    one_camera = obs.select(obs.camera == 0)
    rig3, obs3, bare3 = _small(3, 40, 5)
    crig, cobs = _collinear(6)
    cbare = Rig(tuple(c.replace(rvec=np.zeros(3), t=np.zeros(3)) for c in crig))
    empty = obs.select(np.zeros(len(obs), dtype=bool))
    all_nan = obs.select(np.ones(len(obs), dtype=bool))
    all_nan.uv = np.full_like(all_nan.uv, np.nan)
    few = obs.select(obs.frame < obs.frame.min() + 12)
    return {"2 cameras, 1 frame": (one_frame, bare), "all frames in one camera":
            (one_camera, bare), "collinear wand positions": (cobs, cbare),
            "NaN rows": (_nan_rows(obs3), bare3), "no rows": (empty, bare),
            "every row NaN": (all_nan, bare), "2 cameras, 12 frames": (few, bare),
            "2 cameras, 30 frames": (obs, bare)}


@pytest.mark.parametrize("case", list(_degenerate_cases()))
@pytest.mark.parametrize("holdout", [0.0, 0.1])
def test_degenerate_captures_solve_or_say_why_in_one_line(case, holdout):
    obs, bare = _degenerate_cases()[case]
    try:
        cal = calibrate(obs, bare, (0.0, 1.0), length_known=False, holdout=holdout)
    except UserError as exc:
        assert len(str(exc).splitlines()) == 1 and len(str(exc)) > 20
        return
    # solved: every figure a number or NaN with its reason, and a grade with a reason
    report = cal.report
    assert report["grade"] in ("excellent", "good", "usable", "poor", "failed")
    assert report["grade_reason"]
    for key in ("volume", "radius", "region", "trend"):
        assert np.isfinite(report["systematic"][f"{key}_pct"]) or \
            f"{key}_reason" in report["systematic"]


def test_nan_rows_are_left_out_not_solved():
    rig, obs, bare = _small(3, 40, 5)
    cal = calibrate(obs, bare, (0.0, 1.0), length_known=False)
    holed = calibrate(_nan_rows(obs), bare, (0.0, 1.0), length_known=False)
    assert np.isfinite(holed.report["solve"]["reprojection_rms_px"])
    assert holed.report["solve"]["observations"] < cal.report["solve"]["observations"]
    assert compare_rigs(rig, holed.rig, align=True)["grid_rms_mm"] < 15.0


# ---- intrinsics refined only where the capture shows it pays -----------------------------

@pytest.fixture(scope="module")
def strong_lenses():
    """6 machine-vision cameras with strong distortion, 500 frames of a 3-marker wand."""
    from calibkit.core.camera import BASLER_658x492_DIST

    rig = sim.make_rig(6, 4.0, size=(658, 492), dist=BASLER_658x492_DIST, seed=8)
    truth = sim.wand_motion(500, 100.0, 4.0, (0.0, 0.2, 0.5), seed=8)
    obs = sim.observe(rig, truth, noise_px=0.1, seed=8)
    bare = Rig(tuple(c.replace(rvec=np.zeros(3), t=np.zeros(3)) for c in rig))
    return rig, obs, bare


def test_exact_intrinsics_without_uncertainties_are_kept(strong_lenses):
    rig, obs, bare = strong_lenses
    fixed = calibrate(obs, bare, (0.0, 0.2, 0.5), refine_intrinsics=False, seed=1)
    auto = calibrate(obs, bare, (0.0, 0.2, 0.5), seed=1)
    rows = auto.report["intrinsics"]["cameras"]
    assert all(r["chosen"] == "kept" and "cannot tell" in r["why"] for r in rows), rows
    # what refining would have changed is reported beside the choice
    assert all(np.isfinite(r["if_refined"]["centre_change_px"]) for r in rows)
    grid_fixed = compare_rigs(rig, fixed.rig)["grid_rms_mm"]
    assert compare_rigs(rig, auto.rig)["grid_rms_mm"] <= 1.1 * grid_fixed
    assert auto.rig.quality["intrinsics_refined"] is False


def test_wrong_intrinsics_without_uncertainties_are_refined(strong_lenses):
    rig, obs, bare = strong_lenses
    off = off_intrinsics(bare, 0.005, 2.0, 0.005, np.random.default_rng(3))
    auto = calibrate(obs, off, (0.0, 0.2, 0.5), seed=1)
    forced = calibrate(obs, off, (0.0, 0.2, 0.5), refine_intrinsics=True, seed=1)
    held = calibrate(obs, off, (0.0, 0.2, 0.5), refine_intrinsics=False, seed=1)
    assert all(r["chosen"] == "refined" for r in auto.report["intrinsics"]["cameras"])
    grid = {k: compare_rigs(rig, c.rig)["grid_rms_mm"] for k, c in
            (("auto", auto), ("forced", forced), ("held", held))}
    assert grid["auto"] <= 1.1 * grid["forced"] and grid["auto"] < 0.5 * grid["held"], grid


# ---- the grade's structure checks --------------------------------------------------------

def test_trend_sees_a_length_error_that_follows_position():
    rng = np.random.default_rng(0)
    n = 60
    centre = rng.uniform(-1.5, 1.5, (n, 3))
    radius = rng.uniform(0, 1, n)
    noise = rng.normal(0, 1.0, n)  # mm
    flat = {"frame_length_error_mm": noise, "frame_centre_m": centre, "frame_radius": radius}
    warped = dict(flat, frame_length_error_mm=noise + 1.0 * centre[:, 2])  # 1 mm per m of z
    s_flat = wand_systematics.systematics([flat], None, 0.5, 0.1)
    s_warp = wand_systematics.systematics([warped], None, 0.5, 0.1)
    assert s_flat["trend_mm"] < 0.4
    # the warp's own RMS over these heights: 1 mm/m x sd(z) = 0.87 mm
    assert s_warp["trend_mm"] == pytest.approx(np.std(centre[:, 2]), rel=0.35)
    assert s_warp["volume_grid"] != list(wand_systematics.VOLUME_CELLS)  # 60 frames: coarser
    few = wand_systematics.systematics([dict(flat, frame_length_error_mm=noise[:5],
                                             frame_centre_m=centre[:5],
                                             frame_radius=radius[:5])], None, 0.5, 0.1)
    assert all(f"{k}_reason" in few and not np.isfinite(few[f"{k}_pct"])
               for k in ("volume", "radius", "region", "trend"))


def test_grade_catches_intrinsics_moved_many_prior_sigmas():
    held = {"reprojection_rms_px": 0.12, "wand_length_error_sd_mm": 0.4}
    found = {"ok": True}
    syst = {"volume_pct": 0.0, "radius_pct": 0.0, "region_pct": float("nan"),
            "trend_pct": 0.0}
    row = {"name": "cam2", "largest_change_parameter": "cx"}
    assert wand_report.grade(held, found, 0.5, syst, [dict(row, largest_change_sigmas=1.0)]
                             )[0] == "excellent"
    name, why = wand_report.grade(held, found, 0.5, syst,
                                  [dict(row, largest_change_sigmas=4.0)])
    assert name == "good" and "cam2's cx" in why
    assert wand_report.grade(held, found, 0.5, syst, [dict(row, largest_change_sigmas=9.0)]
                             )[0] == "usable"


def test_refined_intrinsics_the_file_was_overconfident_about_are_not_excellent(strong_lenses):
    """Intrinsics 0.5 % / 2 px off that claim the uncertainty of a monitor calibration: the
    wand repairs them, moving them many of the file's sigmas, and the grade says the file's
    values could not be trusted rather than 'excellent'."""
    rig, obs, bare = strong_lenses
    off = off_intrinsics(bare, 0.005, 2.0, 0.0, np.random.default_rng(4))
    std = {"fx": 0.03, "fy": 0.03, "cx": 0.04, "cy": 0.04, "skew": 0.0, "k1": 1e-4,
           "k2": 1e-4, "p1": 1e-5, "p2": 1e-5, "k3": 0.0}
    claimed = Rig(off.cameras, {"intrinsic": {n: {"std": std} for n in off.names}})
    cal = calibrate(obs, claimed, (0.0, 0.2, 0.5), seed=1)
    moved = max(r["largest_change_sigmas"] for r in cal.report["intrinsics"]["cameras"])
    assert moved > wand_report.INTRINSIC_SIGMA_GRADES[0][1]
    # capped by the move (at best good), and by how loosely 500 frames then determine the
    # cameras (the reason names the first cap that set the grade)
    assert cal.report["grade"] != "excellent", cal.report["grade_reason"]
    assert "prior sigmas" in cal.report["grade_reason"] or "ppm" in cal.report["grade_reason"]


def test_held_intrinsics_off_show_as_structure_on_a_small_capture():
    """0.5 % / 2 px off and held, 3 cameras, 100 frames at 0.2 px: the pixels fit, the
    wand's length follows its place in the volume, and the grade is not excellent."""
    rig, obs, bare = _small(3, 100, 3, noise_px=0.2)
    off = off_intrinsics(bare, 0.005, 2.0, 0.0, np.random.default_rng(5))
    cal = calibrate(obs, off, (0.0, WAND_M), refine_intrinsics=False, seed=3)
    good = calibrate(obs, bare, (0.0, WAND_M), refine_intrinsics=False, seed=3)
    worst = max(cal.report["systematic"][k] for k in ("volume_pct", "radius_pct",
                                                      "trend_pct"))
    assert worst > 2 * max(good.report["systematic"][k] for k in ("volume_pct", "radius_pct",
                                                                  "trend_pct"))
    assert cal.report["grade"] not in ("excellent",), cal.report["grade_reason"]


# ---- the command ---------------------------------------------------------------------

def test_cli_small_capture_of_unknown_length(calibkit_cli, tmp_path):
    rig, obs, bare = _small(3, 50, 0)
    save_observations(tmp_path / "obs.csv", obs)
    bare.save(tmp_path / "intr.toml")
    out = tmp_path / "rig.toml"
    r = calibkit_cli("wand", "--from", tmp_path / "obs.csv", "--intrinsics",
                     tmp_path / "intr.toml", "--spacing", "0,1", "--wand-length", "unknown",
                     "--holdout", "0", "--out", out, "--json", tmp_path / "w.json",
                     "--no-plots")
    assert r.code == 0, r.err
    report = json.loads((tmp_path / "w.json").read_text())
    assert report["held_out"]["reprojection_rms_px"] is None
    assert "--holdout 0" in report["held_out"]["reason"]
    assert report["systematic"]["region_pct"] is None and report["systematic"]["region_reason"]
    assert report["scale"]["known"] is False
    assert "scale: unknown" in r.out and "not computable" in r.out
    page = (tmp_path / "rig.report.html").read_text()
    assert "scale unknown" in page and "--holdout 0" in page and 'id="intrinsics"' in page
    assert Rig.load(out).quality["scale"] == "unknown"
    # metres from --wand-length: the same rig 0.7 times the size
    r = calibkit_cli("wand", "--from", tmp_path / "obs.csv", "--intrinsics",
                     tmp_path / "intr.toml", "--spacing", "0,1", "--wand-length", "0.7",
                     "--holdout", "0", "--out", tmp_path / "m.toml", "--no-plots")
    assert r.code == 0, r.err
    a, b = Rig.load(out), Rig.load(tmp_path / "m.toml")
    assert compare_rigs(b, a, align=True)["alignment"]["scale"] == pytest.approx(0.7, rel=1e-3)


@pytest.mark.parametrize("value", ["-1", "abc", "0", "nan"])
def test_cli_bad_wand_length_is_one_line(calibkit_cli, tmp_path, value):
    rig, obs, bare = _small(2, 20, 0)
    save_observations(tmp_path / "obs.csv", obs)
    bare.save(tmp_path / "intr.toml")
    r = calibkit_cli("wand", "--from", tmp_path / "obs.csv", "--intrinsics",
                     tmp_path / "intr.toml", "--spacing", "0,1", "--wand-length", value,
                     "--out", tmp_path / "rig.toml")
    assert r.code == 2 and "Traceback" not in r.err
    assert len(r.err.strip().splitlines()) == 1 and "--wand-length" in r.err
    assert not (tmp_path / "rig.toml").exists()


def test_an_lframe_sets_the_scale_of_a_wand_of_unknown_length():
    from calibkit.calibrate import floor
    from calibkit.calibrate.wand_scale import lframe_scale
    from calibkit.core.observations import Truth

    rig, obs, bare = _small(3, 50, 7)
    corners = floor.LFrame().points()  # at the true origin, long arm along x
    truth = Truth(np.repeat(np.arange(10), 3), np.tile(np.arange(3), 10),
                  np.tile(corners, (10, 1)))
    floor_obs = sim.observe(rig, truth, noise_px=0.3, seed=7, blobs="ideal")
    cal = calibrate(obs, bare, (0.0, 1.0), length_known=False, seed=7,
                    scale_from=lambda r: lframe_scale(r, floor_obs),
                    world=lambda r, _x: floor.world_from_recording(r, floor_obs, "lframe"))
    scale = cal.report["scale"]
    assert scale["known"] and scale["source"].startswith("L-frame")
    assert scale["wand_length_m"] == pytest.approx(WAND_M, rel=0.02)
    assert "scale is unknown" not in cal.report["grade_reason"]
    # metres in the L-frame's frame, which is the true one here: compared as they stand
    err = np.linalg.norm(cal.rig.centres() - rig.centres(), axis=1)
    assert err.max() < 0.1, err
    assert compare_rigs(rig, cal.rig, align=True)["alignment"]["scale"] == \
        pytest.approx(1.0, abs=0.02)
    # a floor recording without an L-frame cannot set the scale: one line
    empty = sim.observe(rig, Truth(np.zeros(1, int), np.zeros(1, int), corners[:1]),
                        seed=7, blobs="ideal")
    with pytest.raises(UserError, match="--wand-length"):
        lframe_scale(cal.rig, empty)


def test_grade_catches_a_rig_the_capture_determines_poorly():
    held = {"reprojection_rms_px": 0.12, "wand_length_error_sd_mm": 0.4}
    syst = {"volume_pct": 0.0, "radius_pct": 0.0, "region_pct": 0.0, "trend_pct": 0.0}
    assert wand_report.grade(held, {"ok": True}, 0.5, syst, None, "held-out",
                             ("cam1", 70.0))[0] == "excellent"
    name, why = wand_report.grade(held, {"ok": True}, 0.5, syst, None, "held-out",
                                  ("cam1", 900.0))
    assert name == "good" and "cam1" in why and "900 ppm" in why
    assert wand_report.grade(held, {"ok": True}, 0.5, syst, None, "held-out",
                             ("cam1", 5000.0))[0] == "usable"
    assert wand_report.grade(held, {"ok": True}, 0.5, syst, None, "held-out",
                             ("cam1", float("nan")))[0] == "excellent"


def test_small_capture_reports_how_well_it_determines_the_cameras():
    """50 frames, 3 cameras, 0.7 px: the solve's own uncertainty is large, and said."""
    rig, obs, bare = _small(3, 50, 0)
    cal = calibrate(obs, bare, (0.0, 1.0), length_known=False)
    det = cal.report["position_ppm"]
    assert det["camera"] in rig.names and det["ppm"] > wand_report.POSITION_PPM_GRADES[0][1]
    assert cal.report["grade"] != "excellent"
