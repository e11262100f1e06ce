"""Whether the wand refines intrinsics that came without uncertainties: the rig solved with
them held and refined, compared on what the capture itself can judge.

Why not always refine: intrinsics given without standard deviations (imported, nominal, or
exact) get only a loose prior (1 % focal, 5 px centre), and where the wand cannot tell a
principal point from a small turn of the camera, refining moves it anyway: given the exact
intrinsics of 6 strongly distorted cameras, the refined rig was 3.7 times further from the
truth than the held one, with the same held-out residual. Why not always hold: intrinsics
0.5 % / 2 px off warp the space by millimetres, which refining repairs.

So both are solved and a camera's intrinsics are refined only when that explains its
observations measurably better than holding them: the drop in its squared residuals on the
solved frames (points re-triangulated freely, in units of the noise) must exceed what
fitting 8 more parameters to noise alone gives at p = 0.001 (a likelihood-ratio test,
chi-square with 8 degrees of freedom), and the refined rig must not do worse on the frames
held out of the solve. Intrinsics that come with uncertainties (an intrinsic step) or with
the monitor's views are refined as before: their priors already say how far they may move.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from calibkit.calibrate import intrinsic_prior
from calibkit.core.camera import Rig

PARAMETERS = 8  # fx fy cx cy k1 k2 p1 p2 (skew and k3 are held)
P_VALUE = 1e-3  # the chance that noise alone passes the test
HELD_OUT_WORSE = 1.01  # refined may not leave the held-out RMS more than 1 % above held
OUTLIER_SIGMAS = 4.3  # residuals beyond this many noise sigmas are left out of the test
# a camera held inside a graph that refines others: priors this tight pin it (Cal3DS2 order)
HOLD_SIGMA = (1e-4, 1e-4, 1e-6, 1e-4, 1e-4, 1e-7, 1e-7, 1e-8, 1e-8)


def decide(held_fig: dict, refined_fig: dict, held_out_held: dict, held_out_refined: dict,
           noise_px: float, candidates: list[int], n_cams: int) -> tuple[np.ndarray, list[dict]]:
    """Which of the `candidates` cameras get their intrinsics refined, and per camera what
    the test saw. `held_fig`/`refined_fig`: wand_report.evaluate of the held and refined
    rigs on the same solved frames and labels (rows in the same order); `held_out_*`: the
    same on the held-out frames (0 frames when none were held out); noise_px: the image
    noise per axis (the refined solve's robust estimate)."""
    r_h, r_r = held_fig["residual_px"], refined_fig["residual_px"]
    cam = held_fig["residual_camera"]
    sigma = max(float(noise_px), 1e-6)
    sq_h = np.sum(r_h**2, axis=1) / sigma**2
    sq_r = np.sum(r_r**2, axis=1) / sigma**2
    use = np.isfinite(sq_h) & np.isfinite(sq_r) & (sq_h <= OUTLIER_SIGMAS**2) & \
        (sq_r <= OUTLIER_SIGMAS**2)
    drop = np.bincount(cam[use], sq_h[use] - sq_r[use], minlength=n_cams)
    limit = float(chi2.ppf(1.0 - P_VALUE, PARAMETERS))
    ho_h = np.asarray(held_out_held["camera_rms_px"], dtype=float)
    ho_r = np.asarray(held_out_refined["camera_rms_px"], dtype=float)
    refine = np.zeros(n_cams, dtype=bool)
    rows = []
    for k in candidates:
        better = bool(drop[k] > limit)
        judged = bool(np.isfinite(ho_h[k]) and np.isfinite(ho_r[k]))
        worse = judged and ho_r[k] > HELD_OUT_WORSE * ho_h[k]
        refine[k] = better and not worse
        if refine[k]:
            why = (f"refining explains its observations better than noise could "
                   f"(chi-square drop {drop[k]:.1f} > {limit:.1f})"
                   + ("" if judged else "; no held-out frames to confirm it"))
        elif better:
            why = (f"refining fitted the solved frames better (chi-square drop {drop[k]:.1f})"
                   f" but the held-out frames worse ({ho_r[k]:.3f} px against "
                   f"{ho_h[k]:.3f} px held): kept")
        else:
            why = (f"refining explains its observations no better than noise would "
                   f"(chi-square drop {drop[k]:.1f} <= {limit:.1f}): the capture cannot "
                   "tell, kept as given")
        rows.append({"camera": k, "chosen": "refined" if refine[k] else "kept", "why": why,
                     "chi2_drop": float(drop[k]), "chi2_limit": limit,
                     "held_out_rms_px_kept": float(ho_h[k]),
                     "held_out_rms_px_refined": float(ho_r[k])})
    return refine, rows


def what_refining_changed(given: Rig, refined: Rig, sigmas: np.ndarray) -> list[dict]:
    """Per camera, how far refining moved the intrinsics (intrinsic_prior.check_refined's
    figures), for the report of a camera whose intrinsics were kept."""
    rows, _ = intrinsic_prior.check_refined(given, refined, sigmas)
    return rows


def mixed_sigmas(sigmas: np.ndarray, refine: np.ndarray) -> np.ndarray:
    """The prior sigmas with the cameras not refined pinned (HOLD_SIGMA)."""
    out = np.array(sigmas, dtype=np.float64, copy=True)
    out[~refine] = HOLD_SIGMA
    return out
