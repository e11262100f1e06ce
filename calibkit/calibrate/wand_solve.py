"""The wand calibration from blobs to a graded rig: identify, hold frames out, initialise,
bundle-adjust, set the world frame, evaluate. `calibrate_wand` is the one entry point the
command line and the demo call; each step lives in its own module.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from calibkit.calibrate import (
    bundle,
    floor,
    intrinsic_prior,
    wand_intrinsics,
    wand_report,
    wand_shape,
    wand_summary,
)
from calibkit.calibrate.extrinsic_solve import join_bundle_data
from calibkit.calibrate.plane_views import PlaneViews
from calibkit.calibrate.wand import (
    WandObservations,
    WandSpec,
    identify,
    initial_poses,
    point_index,
    wand_lengths,
)
from calibkit.core.camera import Rig, rotation_from_rvec
from calibkit.core.errors import UserError
from calibkit.core.geometry import RigArrays, triangulate
from calibkit.core.observations import Observations

MIN_WAND_FRAMES = 10  # a camera that sees the wand fewer times is left out, with a warning
MIN_SOLVE_FRAMES = 10  # a capture this small after the hold-out solves all its frames


@dataclass(eq=False)
class WandCalibration:
    rig: Rig
    report: dict
    wand: WandObservations  # identified markers, cameras numbered as the recording's
    solved: dict  # wand_report.evaluate figures on the frames solved
    held: dict  # ... and on the frames held out
    bundle: bundle.BundleResult
    held_frames: np.ndarray  # the frames kept out of the solve


def _ordered_intrinsics(obs: Observations, intrinsics: Rig) -> Rig:
    names = set(intrinsics.names)
    missing = [n for n in obs.camera_names if n not in names]
    if missing:
        raise UserError(f"camera '{missing[0]}' of the recording has no intrinsics in the rig "
                        f"file (it has {', '.join(intrinsics.names)})")
    return Rig(tuple(intrinsics[n] for n in obs.camera_names), dict(intrinsics.quality),
               dict(intrinsics.meta))


def _edges(pinfo: np.ndarray, spec: WandSpec) -> tuple[np.ndarray, np.ndarray]:
    """Point pairs of the same frame joined by the wand, and their lengths."""
    pairs, lengths = spec.edges()
    key = pinfo[:, 0] * spec.n_markers + pinfo[:, 1]
    E, L = [], []
    for (a, b), d in zip(pairs.tolist(), lengths.tolist(), strict=True):
        ia = np.flatnonzero(pinfo[:, 1] == a)
        want = pinfo[ia, 0] * spec.n_markers + b
        pos = np.minimum(np.searchsorted(key, want), max(0, len(key) - 1))
        ok = key[pos] == want
        E.append(np.stack([ia[ok], pos[ok]], axis=1))
        L.append(np.full(int(ok.sum()), d))
    return np.concatenate(E).reshape(-1, 2), np.concatenate(L)


def labelled_wand_data(rig: Rig, obs: Observations, spacing_m) -> bundle.BundleData:
    """Bundle input for wand blobs that carry their marker labels (the simulator's truth):
    for benchmarks and tests that want the solve without the identification step. Cameras
    are the rig's, numbered as in `obs`."""
    spec = WandSpec(tuple(spacing_m))
    pidx, pinfo = point_index(obs, spec.n_markers)
    cam = obs.camera.astype(np.int64)
    xyz = triangulate(rig, pidx, cam, obs.uv, n_points=len(pinfo), ray_distance=False).xyz
    edge, length = _edges(pinfo, spec)
    return bundle.BundleData(rig, pidx, cam, obs.uv, xyz, edge, length)


def calibrate(obs: Observations, intrinsics: Rig, spacing_m, initial: Rig | None = None,
              refine_intrinsics: bool | None = None, holdout: float = 0.1, seed: int = 0,
              world: Callable[[Rig, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
              options: bundle.BundleOptions | None = None, progress=None,
              extra: Callable[[Rig], bundle.BundleData] | None = None,
              target_views: PlaneViews | None = None,
              length_known: bool = True,
              scale_from: Callable[[Rig], float] | None = None) -> WandCalibration:
    """Everything: see calibrate_wand. `extra(start_rig)` gives more points to solve with
    (the projector's floor and table dots: calibkit.calibrate.extrinsic_solve.bundle_data),
    joined to the wand's; their plane and position priors then hold the world frame, so it needs
    `initial` poses already in that frame (from calibkit extrinsic). `options` sets the
    bundle adjustment's other knobs; the intrinsics' priors
    (calibkit.calibrate.intrinsic_prior, from the rig file's quality.intrinsic) are set here.
    refine_intrinsics: True refines every camera's, False holds them, None (the default)
    refines those that come with uncertainties or views and decides for the others
    (calibkit.calibrate.wand_intrinsics). `target_views` (calibkit.calibrate.plane_views, the
    intrinsic step's monitor views) join the graph when the intrinsics are refined: a camera
    with views gets them in place of the prior from its intrinsic step's standard deviations
    (a loose prior stays). length_known False: the wand's length is unknown; the rig comes
    out in units of `spacing_m` (scale-free) and the report says so, unless
    `scale_from(rig)` gives metres per unit (calibkit.calibrate.wand_scale.lframe_scale)."""
    if extra is not None and initial is None:
        raise UserError("points on known planes need initial poses in the world frame: give "
                        "--rig (e.g. from calibkit extrinsic)")
    if extra is not None and not length_known:
        raise UserError("--dots hold the world frame in metres, which a wand of unknown "
                        "length contradicts: give --wand-length")
    spec = WandSpec(tuple(spacing_m))
    intr = _ordered_intrinsics(obs, intrinsics)
    obs = obs.select(np.isfinite(obs.uv).all(axis=1))  # cells not digitised
    if len(obs) == 0:
        raise UserError("the recording holds no blob positions (every row is empty or NaN)")
    wand = identify(obs, spec, intr)
    warnings: list[str] = []
    per_cam = np.bincount(wand.camera[wand.marker == 0], minlength=len(intr))
    never = [intr[c].name for c in range(len(intr)) if per_cam[c] < MIN_WAND_FRAMES]
    for name in never:
        warnings.append(f"camera {name} saw the wand in {per_cam[intr.index(name)]} frames "
                        f"(fewer than {MIN_WAND_FRAMES}): left out, not calibrated")
    keep_cams = [c for c in range(len(intr)) if intr[c].name not in never]
    if len(keep_cams) < 2:
        seen = ", ".join(f"{n} {k}" for n, k in zip(intr.names, per_cam.tolist(), strict=True))
        raise UserError(f"fewer than two cameras saw the wand in {MIN_WAND_FRAMES} frames or "
                        f"more (frames with the wand: {seen}); capture longer, or check "
                        "--spacing")
    sub = Rig(tuple(intr[c] for c in keep_cams), dict(intr.quality), dict(intr.meta))
    seen_by_kept = wand.select(np.isin(wand.camera, keep_cams))
    # the start from every frame (it is only where the solve begins), then the frames held
    # out of the solve: some at random, some in whole regions of the volume
    start, missing = _start(seen_by_kept, keep_cams, intr, sub, spec, initial)
    for name in missing:
        warnings.append(f"camera {name} could not be placed (it shares too few wand "
                        "sightings with the others): left out, not calibrated")
    camera_of = np.full(len(intr), -1)
    for k, name in enumerate(start.names):
        camera_of[intr.index(name)] = k
    frames = wand.frames()
    placed = _two_marker_labels(wand, start, camera_of) if spec.n_markers == 2 else wand
    held_random, held_region = wand_report.hold_out(
        frames, _frame_centres(placed, start, camera_of, spec, frames), holdout, seed)
    held_frames = np.union1d(held_random, held_region)
    if len(held_frames) and len(frames) - len(held_frames) < MIN_SOLVE_FRAMES:
        warnings.append(f"no frames held out: the capture's {len(frames)} wand frames are "
                        f"too few to keep any out of the solve (it takes {MIN_SOLVE_FRAMES} "
                        "solved)")
        held_random = held_region = held_frames = frames[:0]
    prior = Rig(tuple(intr[n] for n in start.names), dict(intr.quality))
    sigmas, prior_source = intrinsic_prior.prior_sigmas(intrinsics, start.names)
    if refine_intrinsics is not False and spec.n_markers < 2:
        refine_intrinsics = False
        warnings.append("intrinsics held: a 1-marker wand has no length to check them against")
    target = _target_data(target_views, prior) if refine_intrinsics is not False else None
    if target is not None:
        for k in np.unique(target.obs_camera).tolist():
            sigmas[k] = intrinsic_prior.default_sigmas(prior[k])
            prior_source[k] = "intrinsic step's views"
    # a 2-marker wand started from midpoints is labelled again with the solved poses and
    # solved once more: the start's labels are wrong where its poses were a little off
    passes = 2 if spec.n_markers == 2 and initial is None else 1

    def solve(refine: bool, prior_sigma: np.ndarray) -> tuple[bundle.BundleResult,
                                                               WandObservations]:
        return _solve_passes(wand, start, prior, camera_of, held_frames, spec, passes,
                             refine, prior_sigma, target if refine else None, extra,
                             options, progress)

    candidates = [k for k in range(len(prior)) if prior_source[k] == "default"] \
        if refine_intrinsics is None else []
    refine = np.full(len(prior), refine_intrinsics is not False)
    decided: dict[int, dict] = {}
    if_refined = None  # every camera refined, where the default kept some: for the report
    if not candidates:
        result, wand = solve(bool(refine.any()), sigmas)
    else:
        (result, wand), refined = solve(False, sigmas), solve(True, sigmas)
        train = np.setdiff1d(frames, held_frames)
        figs = [wand_report.evaluate(r.rig, refined[1], spec, f, camera_of)
                for r in (result, refined[0]) for f in (train, held_frames)]
        choice, rows = wand_intrinsics.decide(figs[0], figs[2], figs[1], figs[3],
                                              refined[0].noise_px, candidates, len(prior))
        refine[candidates] = choice[candidates]
        changes = wand_intrinsics.what_refining_changed(prior, refined[0].rig, sigmas)
        decided = {row["camera"]: {**row, "if_refined": {k: v for k, v in
                                                         changes[row["camera"]].items()
                                                         if k != "name"}} for row in rows}
        if_refined = None if refine.all() else refined[0]
        if refine.all():
            result, wand = refined
        elif refine.any():
            result, wand = solve(True, wand_intrinsics.mixed_sigmas(sigmas, refine))
    intrinsics_moved: list[dict] = [{} for _ in prior]
    if refine.any():
        intrinsics_moved, _ = intrinsic_prior.check_refined(prior, result.rig, sigmas)
        ks = np.flatnonzero(refine)
        warnings.extend(intrinsic_prior.check_refined(
            Rig(tuple(prior[k] for k in ks)), Rig(tuple(result.rig[k] for k in ks)),
            sigmas[ks])[1])
    # the world frame
    if world is None and extra is not None:  # the extra points' priors set the frame
        def world(_rig, _xyz):
            return np.eye(3), np.zeros(3)
    unit_m = 1.0  # metres per unit of the solve: 1 unless an unknown wand is scaled
    solved_rig = result.rig
    scaled = scale_from is not None and not length_known
    if scaled:
        unit_m = float(scale_from(result.rig))
        solved_rig = Rig(tuple(c.replace(t=c.t * unit_m) for c in result.rig))
        spec = WandSpec(tuple(v * unit_m for v in spec.spacing_m))
    A, b = (world or floor.frame_from_cameras)(solved_rig, result.xyz * unit_m)
    rig = floor.transform_rig(solved_rig, A, b)
    solved = wand_report.evaluate(rig, wand, spec, np.setdiff1d(frames, held_frames), camera_of)
    held = wand_report.evaluate(rig, wand, spec, held_frames, camera_of) if len(held_frames) \
        else None
    region = wand_report.evaluate(rig, wand, spec, held_region, camera_of) if len(held_region) \
        else None
    syst = wand_report.systematics([solved] if held is None else [solved, held], region,
                                   spec.length_m, holdout if len(held_frames) else 0.0)
    try:
        cov = bundle.camera_covariances(result)
        cov["position_std_total_m"] = cov["position_std_total_m"] * unit_m
    except RuntimeError as exc:  # an indeterminate system: say so rather than fail
        warnings.append(f"no uncertainty: the marginals failed ({str(exc).splitlines()[0]})")
        cov = None
    found = wand_report.checks(rig, solved["xyz"], solved["behind_share"])
    shape, shape_warnings = wand_shape.section(result, unit_m, if_refined)
    warnings.extend(shape_warnings)
    for k, row in decided.items():  # what this capture cannot rule out in a kept camera
        row["cannot_rule_out"] = shape.get("cannot_rule_out", {}).get(prior[k].name)
    moved_rows = [dict(m, name=prior[k].name) for k, m in enumerate(intrinsics_moved)
                  if refine[k] and m]
    determined = _position_ppm(rig, cov)
    grade, reason = wand_report.grade(solved if held is None else held, found, spec.length_m,
                                      syst, moved_rows,
                                      "held-out" if held is not None else "solved",
                                      determined)
    if held is None:
        reason += " (graded on the solved frames: none were held out, so over-fitting cannot show)"
    if not length_known and not scaled:
        reason += ("; the scale is unknown (no --wand-length): distances are in units of the "
                   "wand's length as --spacing gives it, and the grade is scale-free")
    held_reason = None if held is not None else (
        "no frames held out (--holdout 0)" if holdout <= 0 else
        f"the capture's {len(frames)} wand frames are too few to hold any out")
    report = wand_summary.report(rig, spec, result, solved, held, cov, found, grade, reason,
                                 warnings, never + missing, wand, intr, world is not None,
                                 held_reason)
    report["systematic"] = syst
    report["shape_uncertainty"] = shape
    report["position_ppm"] = {"camera": determined[0], "ppm": determined[1]} \
        if determined else {"camera": None, "ppm": float("nan"),
                            "reason": "no uncertainty (the marginals failed)"}
    report["held_out"]["random_frames"] = int(len(held_random))
    report["held_out"]["region_frames"] = int(len(held_region))
    report["intrinsics"] = wand_summary.intrinsics_report(refine, prior, sigmas, prior_source,
                                                          intrinsics_moved, cov, result,
                                                          decided)
    report["scale"] = _scale_report(spec, length_known) if not scaled else {
        "known": True, "source": "L-frame (the wand's length unknown)",
        "wand_length_m": spec.length_m, "metres_per_unit": unit_m}
    quality = {"reprojection_rms_px": report["solve"]["reprojection_rms_px"],
               "held_out_rms_px": report["held_out"]["reprojection_rms_px"],
               "wand_length_error_sd_mm": report["held_out"]["wand_length_error_sd_mm"],
               "wand_length_variation_pct": report["solve"]["wand_length_variation_pct"],
               "mean_ray_distance_mm": report["held_out"]["mean_ray_distance_mm"],
               "length_variation_volume_pct": syst["volume_pct"],
               "length_variation_radius_pct": syst["radius_pct"],
               "intrinsics_refined": bool(refine.any()),
               "intrinsics_refined_cameras": [c.name for c, r in zip(prior, refine,
                                                                     strict=True) if r],
               "scale": report["scale"]["source"],
               "grade": grade}
    quality = {k: v for k, v in quality.items() if not (isinstance(v, float)
                                                         and not np.isfinite(v))}
    if isinstance(intrinsics.quality.get("intrinsic"), dict):
        quality["intrinsic"] = intrinsics.quality["intrinsic"]  # where they came from
    meta = {"source": "calibkit wand", "wand_spacing_m": list(spec.spacing_m),
            "world_frame": report["world_frame"]}
    rig = Rig(rig.cameras, quality, {**{k: v for k, v in intrinsics.meta.items()
                                        if k in ("volume_m",)}, **meta})
    return WandCalibration(rig, report, wand, solved, solved if held is None else held,
                           result, held_frames)


def _position_ppm(rig: Rig, cov: dict | None) -> tuple[str, float] | None:
    """The camera known least well relative to its distance from the reference camera, and
    that standard deviation in ppm of the distance (scale-free)."""
    if cov is None:
        return None
    ref = rig.centres()[rig.index(cov["reference_camera"])]
    dist = np.linalg.norm(rig.centres() - ref, axis=1)
    ppm = np.where(dist > 0, 1e6 * cov["position_std_total_m"] / np.maximum(dist, 1e-12),
                   np.nan)
    if not np.isfinite(ppm).any():
        return None
    k = int(np.nanargmax(ppm))
    return rig[k].name, float(ppm[k])


def _scale_report(spec: WandSpec, length_known: bool) -> dict:
    if spec.n_markers < 2:
        return {"known": True, "source": "the --rig file's camera baseline (1-marker wand)"}
    if length_known:
        return {"known": True, "source": "wand length",
                "wand_length_m": spec.length_m}
    return {"known": False, "source": "unknown",
            "unit": f"the wand's end-to-end length is {spec.length_m:g} units (--spacing); "
                    "give --wand-length M to have metres",
            "reason": "the wand's length is unknown (--wand-length unknown)"}


def _start(seen: WandObservations, keep_cams: list[int], intr: Rig, sub: Rig, spec: WandSpec,
           initial: Rig | None) -> tuple[Rig, list[str]]:
    """Initial poses: the --rig file's, else from pairwise geometry (a 2-marker wand from
    the midpoints of its ends, which look alike)."""
    if initial is not None:
        absent = [n for n in sub.names if n not in set(initial.names)]
        if absent:
            raise UserError(f"camera '{absent[0]}' is not in the --rig file")
        return Rig(tuple(sub[n].replace(rvec=initial[n].rvec, t=initial[n].t)
                         for n in sub.names)), []
    local = _renumber(seen, keep_cams, len(intr))
    try:
        if spec.n_markers == 2:
            return _two_marker_start(local, sub, spec)
        return initial_poses(local, sub, spec)
    except cv2.error as exc:  # OpenCV on degenerate input (too few or collinear points)
        raise UserError("the wand views give no relative pose between the cameras (OpenCV: "
                        f"{str(exc).strip().splitlines()[-1]}): wave the wand through more "
                        "of the volume") from None


def _solve_passes(raw: WandObservations, start: Rig, prior: Rig, camera_of: np.ndarray,
                  held_frames: np.ndarray, spec: WandSpec, passes: int, refine: bool,
                  sigmas: np.ndarray, target, extra, options, progress
                  ) -> tuple[bundle.BundleResult, WandObservations]:
    """The bundle adjustment on the frames not held out, `passes` times (a 2-marker wand's
    ends labelled again with each pass's poses); the result and the wand as labelled."""
    wand = raw
    for _ in range(passes):
        if spec.n_markers == 2:
            wand = _two_marker_labels(raw, start, camera_of)
        train = wand.select(~np.isin(wand.frame, held_frames))
        tw = train.select(camera_of[train.camera] >= 0)
        cam = camera_of[tw.camera]
        if len(np.unique(cam)) < len(start):
            raise UserError("a camera has no wand observations left to solve with: capture "
                            "longer")
        pidx, pinfo = point_index(tw, spec.n_markers)
        tri = triangulate(start, pidx, cam, tw.uv, n_points=len(pinfo), ray_distance=False)
        edge, length = _edges(pinfo, spec) if spec.n_markers > 1 else (np.zeros((0, 2)), [])
        data = bundle.BundleData(start, pidx, cam, tw.uv, tri.xyz, edge, length)
        if extra is not None:
            data = join_bundle_data(data, extra(start))
        data.target = target
        opts = dataclasses.replace(
            options or bundle.BundleOptions(reference_camera=int(np.argmax(
                np.bincount(cam, minlength=len(start))))),
            refine_intrinsics=refine, intrinsic_sigma=tuple(map(tuple, sigmas.tolist())),
            standardise=extra is None)
        try:
            result = bundle.solve(data, opts, progress)
        except RuntimeError as exc:  # GTSAM: an indeterminate system (too little data)
            raise UserError(f"the bundle adjustment failed ({str(exc).splitlines()[0]}): a "
                            "camera sees too few wand markers; capture longer") from None
        if not np.isfinite(result.noise_px):
            raise UserError("the bundle adjustment kept no wand marker seen by two cameras: "
                            "capture longer, with the wand where two cameras see it")
        # the next pass starts from these poses; its intrinsics' priors stay the file's
        start = Rig(tuple(p.replace(rvec=c.rvec, t=c.t)
                          for p, c in zip(prior, result.rig, strict=True)))
    return result, wand


def _target_data(views: PlaneViews | None, rig: Rig) -> bundle.TargetData | None:
    """The intrinsic step's views of the cameras of `rig` as bundle input (None when it
    has none)."""
    if views is None:
        return None
    sub = views.cameras(rig.names)
    if len(sub) == 0:
        return None
    R = np.stack([rotation_from_rvec(r) for r in sub.view_rvec]).reshape(-1, 3, 3)
    return bundle.TargetData(sub.camera, sub.view, sub.xyz, sub.uv, R, sub.view_tvec.copy())


def _frame_centres(wand: WandObservations, rig: Rig, camera_of: np.ndarray, spec: WandSpec,
                   frames: np.ndarray) -> np.ndarray:
    """Each frame's wand centre triangulated with `rig` (NaN where fewer than two cameras
    saw a marker): where in the volume the frame was, to hold out whole regions."""
    w = wand.select(camera_of[wand.camera] >= 0)
    pidx, pinfo = point_index(w, spec.n_markers)
    xyz = triangulate(rig, pidx, camera_of[w.camera], w.uv, n_points=len(pinfo),
                      ray_distance=False).xyz
    ok = np.isfinite(xyz[:, 0])
    f = np.searchsorted(frames, pinfo[ok, 0])
    n = np.bincount(f, minlength=len(frames))
    with np.errstate(invalid="ignore"):
        return np.stack([np.bincount(f, xyz[ok, k], len(frames)) for k in range(3)],
                        axis=1) / np.where(n > 0, n, np.nan)[:, None]


def calibrate_wand(observations: Observations, intrinsics_rig: Rig, wand_spacing_m,
                   initial_rig: Rig | None = None, refine_intrinsics: bool = True,
                   holdout: float = 0.1, seed: int = 0, world=None) -> tuple[Rig, dict]:
    """Calibrate a rig from a wand capture: (the rig, the report's figures).

    observations: unlabelled blobs (a recording); intrinsics_rig: every camera's
    intrinsics (poses ignored); wand_spacing_m: marker positions along the wand, e.g.
    (0, 0.2, 0.5); initial_rig: start from its poses instead of from nothing;
    world(rig, xyz) -> (A, b): the world frame (floor.frame_from_*), else a provisional one
    from the cameras' up direction.
    """
    cal = calibrate(observations, intrinsics_rig, wand_spacing_m, initial_rig,
                    refine_intrinsics, holdout, seed, world)
    return cal.rig, cal.report


def _two_marker_start(wand: WandObservations, sub: Rig, spec: WandSpec
                      ) -> tuple[Rig, list[str]]:
    """Initial poses for a 2-marker wand, whose ends look alike: the image midpoint of the
    two blobs (nearly the image of the wand's middle) is the same point whichever end is
    which, so the poses come from the midpoints; then the ends are labelled with those
    poses and the wand's length gives the scale."""
    pairs = wand.select(np.lexsort((wand.marker, wand.camera, wand.frame)))
    mid = WandObservations(pairs.camera_names, pairs.camera_sizes, pairs.frame[0::2],
                           pairs.camera[0::2], np.zeros(len(pairs) // 2, dtype=np.int32),
                           0.5 * (pairs.uv[0::2] + pairs.uv[1::2]))
    start, missing = initial_poses(mid, sub, WandSpec((0.0,)), unscaled=True)
    camera_of = np.array([start.names.index(n) if n in start.names else -1
                          for n in sub.names])
    labelled = _two_marker_labels(pairs, start, camera_of)
    pidx, pinfo = point_index(labelled, 2)
    xyz = triangulate(start, pidx, camera_of[labelled.camera], labelled.uv,
                      n_points=len(pinfo), ray_distance=False).xyz
    lengths = wand_lengths(xyz, pinfo, spec)
    lengths = lengths[np.isfinite(lengths)]
    if len(lengths) < 5:
        raise UserError("too few 2-marker wand frames seen by two cameras to find the scale")
    scale = spec.length_m / float(np.median(lengths))
    return Rig(tuple(c.replace(t=c.t * scale) for c in start)), missing


def _renumber(wand: WandObservations, keep: list[int], n: int) -> WandObservations:
    local = np.full(n, -1)
    local[keep] = np.arange(len(keep))
    w = wand.select(local[wand.camera] >= 0)
    w.camera = local[w.camera].astype(np.int32)
    return w


def _two_marker_labels(wand: WandObservations, rig: Rig, camera_of: np.ndarray
                       ) -> WandObservations:
    """Label a 2-marker wand's ends consistently across cameras: per frame, the first
    camera's labels stand; every other camera's are swapped when its rays then pass
    closer to the first camera's."""
    w = wand.select(camera_of[wand.camera] >= 0)
    w = w.select(np.lexsort((w.marker, w.camera, w.frame)))
    f = w.frame[0::2]
    cam = camera_of[w.camera[0::2]]
    o, d = RigArrays.from_rig(rig).rays(np.repeat(cam, 2), w.uv)
    o0, o1, d0, d1 = o[0::2], o[1::2], d[0::2], d[1::2]
    first = np.r_[True, f[1:] != f[:-1]]
    ref = np.maximum.accumulate(np.where(first, np.arange(len(f)), 0))

    def gap(oa, da, ob, db):
        n = np.cross(da, db)
        nn = np.linalg.norm(n, axis=1)
        return np.abs(np.sum((ob - oa) * n, axis=1)) / np.maximum(nn, 1e-12)

    keep_cost = gap(o0[ref], d0[ref], o0, d0) + gap(o1[ref], d1[ref], o1, d1)
    swap_cost = gap(o0[ref], d0[ref], o1, d1) + gap(o1[ref], d1[ref], o0, d0)
    swap = (swap_cost < keep_cost) & ~first
    # where both labellings fit about as well (the wand along an epipolar line) say nothing
    clear = first | (np.minimum(keep_cost, swap_cost) < 0.3 * np.maximum(keep_cost, swap_cost))
    marker = w.marker.copy()
    marker[0::2] = np.where(swap, 1, 0)  # rows come in (0, 1) pairs
    marker[1::2] = np.where(swap, 0, 1)
    w.marker = marker.astype(np.int32)
    w = w.select(np.repeat(clear, 2))
    return w.select(np.lexsort((w.marker, w.camera, w.frame)))
