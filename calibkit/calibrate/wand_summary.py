"""The wand solve's report as one dict: the figures the command prints, writes with --json
and puts on its HTML page, each with the reason when it could not be computed.

Why a reason beside every missing figure: a real capture of 30-100 frames leaves some
figures without data (no frames held out, too few frames for a cell of the volume); a bare
null would read as a bug, a made-up number as a result. So a figure is a number where the
capture holds the data for it and null with `<figure>_reason` otherwise.
"""

from __future__ import annotations

import numpy as np

from calibkit.calibrate import intrinsic_prior, wand_report
from calibkit.calibrate.bundle import BundleResult
from calibkit.calibrate.wand import CaptureMonitor, WandObservations, WandSpec
from calibkit.core.camera import Rig

FIGURES = ("frames", "observations", "reprojection_rms_px", "wand_length_error_mean_mm",
           "wand_length_error_sd_mm", "wand_length_error_rms_mm", "mean_ray_distance_mm",
           "wand_length_variation_pct")
MIN_LENGTH_FRAMES = 2  # the fewest frames with both ends for a spread of the wand's length


def figures(e: dict, none_reason: str | None = None, has_length: bool = True) -> dict:
    """evaluate's figures for the report, each NaN one with its reason (`none_reason`: why
    there are no frames at all; has_length: False for a 1-marker wand)."""
    out = {k: e.get(k, float("nan")) for k in FIGURES}
    if none_reason is not None:
        out["reason"] = none_reason
        return out
    if not out["frames"]:
        out["reason"] = "no frame of these was seen by two cameras of the rig"
    n = int(e.get("length_frames", 0))
    if not np.isfinite(out["wand_length_variation_pct"]):
        out["wand_length_variation_reason"] = (
            "a 1-marker wand has no length" if not has_length else
            f"{n} frames with both wand ends reconstructed (it takes {MIN_LENGTH_FRAMES})")
    return out


def intrinsics_report(refined: np.ndarray, prior: Rig, sigmas: np.ndarray, source: list[str],
                      moved: list[dict], cov: dict | None, result: BundleResult,
                      decided: dict[int, dict]) -> dict:
    """Per camera: where the priors came from and their sigmas; whether its intrinsics were
    refined or kept and why (`decided`: wand_intrinsics.decide's rows for cameras whose
    intrinsics came without uncertainties, with `if_refined`: what refining moved); when
    refined, how far the wand moved them, how well it now knows them and the intrinsic
    step's views' residual RMS (per axis) in the joint solve where they took part."""
    rows = []
    for k, cam in enumerate(prior):
        row = {"name": cam.name, "prior_from": source[k],
               "prior_sigma": dict(zip(intrinsic_prior.CAL3DS2, sigmas[k].tolist(),
                                       strict=True)),
               "chosen": "refined" if refined[k] else "kept"}
        if k in decided:
            row.update({key: v for key, v in decided[k].items() if key != "camera"})
        elif refined[k]:
            row["why"] = f"refined within the priors from the {source[k]}"
        else:
            row["why"] = "kept as given (--fix-intrinsics, or a 1-marker wand)"
        if refined[k]:
            row.update({key: v for key, v in moved[k].items() if key != "name"})
            t = result.target
            if t is not None and np.any(t.obs_camera == k):
                sel = result.target_inlier & (t.obs_camera == k)
                row["views_rms_px"] = float(np.sqrt(np.mean(
                    result.target_residual_px[sel] ** 2))) if sel.any() else float("nan")
                row["views_points"] = int(sel.sum())
            if cov is not None and "intrinsic_std" in cov:
                row["std_after"] = dict(zip(intrinsic_prior.CAL3DS2,
                                            cov["intrinsic_std"][k].tolist(), strict=True))
        rows.append(row)
    return {"refined": bool(np.any(refined)), "cameras": rows}


def report(rig: Rig, spec: WandSpec, result: BundleResult, solved: dict, held: dict | None,
           cov: dict | None, found: dict, grade: str, reason: str, warnings: list[str],
           left_out: list[str], wand: WandObservations, intr: Rig, floor_given: bool,
           held_reason: str | None) -> dict:
    """Everything the command prints and writes; `held` None: no frames were held out
    (`held_reason` says why)."""
    monitor = CaptureMonitor(intr.names, [c.size for c in intr])
    monitor.add(wand)
    coverage = dict(zip(intr.names, monitor.coverage.tolist(), strict=True))
    cams = []
    for k, cam in enumerate(rig):
        row = {"name": cam.name, "observations": int(solved["camera_observations"][k]),
               "coverage": coverage[cam.name],
               "reprojection_rms_px": float(solved["camera_rms_px"][k]),
               "held_out_rms_px": float(held["camera_rms_px"][k]) if held is not None
               else float("nan"),
               "centre_m": cam.centre.tolist()}
        if cov is not None:
            row["position_std_mm"] = float(cov["position_std_total_m"][k] * 1000)
            row["orientation_std_deg"] = float(np.degrees(cov["orientation_std_total_rad"][k]))
        cams.append(row)
    n_out = int(np.sum(~result.inlier))
    return {
        "wand_spacing_m": list(spec.spacing_m),
        "cameras": cams,
        "solve": {**figures(solved, has_length=spec.n_markers > 1), "noise_px": result.noise_px,
                  "iterations": result.iterations, "time_s": result.time_s,
                  "cpu_s": result.cpu_s,
                  "outliers": n_out, "refine_intrinsics": result.options.refine_intrinsics},
        "held_out": figures(held, has_length=spec.n_markers > 1) if held is not None else
        figures({"frames": 0, "observations": 0}, held_reason),
        "uncertainty_reference_camera": None if cov is None else cov["reference_camera"],
        "checks": found, "grade": grade, "grade_reason": reason,
        "grade_thresholds": [{"grade": g, "held_out_rms_px": p, "wand_length_sd_pct": m}
                             for g, p, m in wand_report.GRADES],
        "systematic_thresholds_pct": dict(wand_report.SYSTEMATIC_GRADES),
        "intrinsic_sigma_grades": dict(wand_report.INTRINSIC_SIGMA_GRADES),
        "position_ppm_grades": dict(wand_report.POSITION_PPM_GRADES),
        "left_out_cameras": left_out, "warnings": warnings,
        "world_frame": "floor" if floor_given else "cameras (provisional: run calibkit floor)",
        "identification": {"frames_with_wand": dict(zip(intr.names,
                                                        wand.stats["frames_with_wand"],
                                                        strict=True)),
                           "ambiguous": dict(zip(intr.names, wand.stats["ambiguous"],
                                                 strict=True))},
    }
