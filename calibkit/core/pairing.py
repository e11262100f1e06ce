"""Camera frames grouped into wand frames by capture time, not by each camera's counter.

Real cameras open at different moments, count frames from their own start, and lose a
frame now and then (a full USB bus, a busy computer). Pairing frame n of one camera with
frame n of another is then wrong from the first drop on, and nothing in the numbers
shows it: the solve just gets worse. What a capture does give is each frame's capture
time. A wand is captured by a triggered (or at least evenly clocked) rig, so each
camera's stamps lie on a grid of its frame period: stamp = start + period * n + jitter,
with its own start (the transfer delay, the moment the driver's clock was mapped) and
its own period (its crystal, tens of ppm from the nominal rate). Those two numbers are
learned per camera from its stamps alone: the trigger count n of each stamp is read off
a straight line through (n, stamp) fitted on ever longer spans from the first stamps on
(counting from the rounded gaps instead, one gap that jitter rounded wrong would shift
every later count), each fit refitted without the stamps that sit far from it (a frame
handed over late). The fitted grid replaces
each stamp, which takes the jitter out; a frame whose stamp is more than a quarter of a
period off its camera's grid is not trusted and left unpaired.

Every camera's grid is then read on the reference camera's (the one with most frames):
a frame belongs to the reference instant nearest to it, and one that is more than half a
period from every instant, or that shares its instant with a nearer frame of its camera,
is left unpaired, never paired with the wrong instant. The one thing times cannot tell
is a whole number of periods between two cameras' clocks: stamps are assumed to agree to
within half a period at the start (one computer's clock, or device clocks mapped to it),
and the drift that builds up after that is what the fit follows. Stamps may jitter by up
to about a fifth of a period (6 ms SD at 30 fps: webcams stamped when the computer reads
them; tests/test_wand_pairing.py); beyond that a camera's grid is not found reliably.

Recordings that already number frames by instant (older calibkit recordings, other
tools' files, cameras that share a hardware frame id) are kept as they are:
`frames_are_instants` tells them apart by what the file says, else by whether the
cameras' times of one frame number agree.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibkit.core.observations import Observations

PER_CAMERA = "per camera"  # meta["frames"]: each camera's own counter (pair by time)
INSTANTS = "instants"  # meta["frames"]: one number per instant, shared by the cameras
TRUST_FRAC = 0.25  # a stamp this many periods off its camera's grid is not trusted
MIN_FRAMES = 3  # a camera with fewer timed frames cannot have its grid fitted
MAX_RATE_ERROR = 0.002  # a camera's fitted period this far from the nominal one is no
# crystal's drift (tens of ppm) but a fit misled by jitter: none of its frames is trusted


@dataclass(eq=False)
class Pairing:
    """Observations with `frame` numbering instants, and how they were paired."""

    obs: Observations
    method: str  # "time" or "as recorded"
    stats: dict = field(default_factory=dict)


def _records(obs: Observations) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The distinct (camera, frame) records: camera, frame, time, and each row's record."""
    key = obs.camera.astype(np.int64) * (int(obs.frame.max()) - int(obs.frame.min()) + 1) \
        + (obs.frame - obs.frame.min())
    uniq, first, inv = np.unique(key, return_index=True, return_inverse=True)
    return obs.camera[first], obs.frame[first], obs.t_ns[first], inv.reshape(-1)


def nominal_period_ns(obs: Observations) -> float | None:
    """The frame period: the median time between a camera's successive frames (its counter
    one apart), or the recording's frame rate when that agrees with it to 10 % (a file
    may say a rate the cameras did not run at); None when neither says anything."""
    said = 1e9 / float(obs.fps) if obs.fps else None
    if len(obs) == 0:
        return said
    cam, frame, t, _ = _records(obs)
    order = np.lexsort((frame, cam))
    cam, frame, t = cam[order], frame[order], t[order]
    step = (cam[1:] == cam[:-1]) & (np.diff(frame) == 1)
    dt = np.diff(t)[step].astype(np.float64)
    dt = dt[dt > 0]
    if len(dt) < 3:
        return said
    seen = float(np.median(dt))
    return said if said is not None and abs(seen - said) <= 0.1 * said else seen


def frames_are_instants(obs: Observations, period_ns: float | None = None) -> bool:
    """Whether the frame numbers already name instants shared by the cameras: the file says
    so (meta "frames"), or the cameras' capture times of each frame number agree to within
    half a period (all but 1 % of them; times all equal, as in files without times, agree)."""
    said = obs.meta.get("frames") if obs.meta else None
    if said in (PER_CAMERA, INSTANTS):
        return said == INSTANTS
    if len(obs) == 0 or len(obs.camera_names) < 2:
        return True
    period = period_ns or nominal_period_ns(obs)
    if period is None:
        return True
    cam, frame, t, _ = _records(obs)
    order = np.argsort(frame, kind="stable")
    frame, t = frame[order], t[order].astype(np.float64)
    starts = np.flatnonzero(np.r_[True, frame[1:] != frame[:-1]])
    counts = np.diff(np.r_[starts, len(frame)])
    shared = np.repeat(counts >= 2, counts)
    if not shared.any():
        return False  # no frame number seen by two cameras: counters of their own
    mid = np.repeat(np.minimum.reduceat(t, starts) / 2 + np.maximum.reduceat(t, starts) / 2,
                    counts)
    off = np.abs(t - mid)[shared] > 0.5 * period
    return bool(np.mean(off) <= 0.01)


def _fit(x: np.ndarray, y: np.ndarray, period_ns: float) -> tuple[float, float]:
    """(start, step) of the line y = start + step * x, by least squares, refitted twice
    without the points more than 6 robust SDs (at most TRUST_FRAC periods) off it."""
    keep = np.ones(len(x), dtype=bool)
    start, step = float(y[0] - period_ns * x[0]), period_ns
    for _ in range(3):
        if keep.sum() < 2 or np.ptp(x[keep]) == 0:
            break
        step, start = np.polyfit(x[keep], y[keep], 1)
        resid = y - (start + step * x)
        scale = 1.4826 * np.median(np.abs(resid[keep] - np.median(resid[keep])))
        keep = np.abs(resid) <= min(TRUST_FRAC * period_ns, max(6 * scale, 1e-3 * period_ns))
    return float(start), float(step)


def _grid(t: np.ndarray, period_ns: float) -> tuple[np.ndarray, float, float, np.ndarray]:
    """One camera's stamps (sorted) on its own grid: (trigger count of each, start, period,
    whether the stamp is trusted). The first 16 stamps are counted in nominal periods
    from their mean phase (not from the first stamp, whose jitter would shift them all;
    nor from the gaps, where one rounded wrong would shift every later count); the line is
    fitted on them, the counts of twice as many are then read off it and the line
    refitted, and so on to the last stamp (the error a fit leaves in the period is never
    half a period over the span it is extended to)."""
    y = (t - t[0]).astype(np.float64)
    m = min(len(t), 16)
    turn = np.exp(2j * np.pi * y[:m] / period_ns)
    phase = np.angle(turn.mean()) / (2 * np.pi) * period_ns  # the first stamps' own jitter
    n = np.rint((y - phase) / period_ns)  # averaged out
    while True:
        start, step = _fit(n[:m], y[:m], period_ns)
        if m == len(t):
            break
        m = min(len(t), 2 * m)
        n[:m] = np.rint((y[:m] - start) / step)
    n = np.rint((y - start) / step)
    start, step = _fit(n, y, period_ns)
    resid = y - (start + step * n)
    trusted = np.abs(resid) <= TRUST_FRAC * period_ns
    if abs(step / period_ns - 1) > MAX_RATE_ERROR:  # no crystal: the fit lost its way
        trusted[:] = False
    return n.astype(np.int64), float(t[0] + start), float(step), trusted


def pair_by_time(obs: Observations, period_ns: float | None = None) -> Pairing:
    """Rows regrouped so that `frame` numbers the reference camera's instants (see the
    module docstring); rows of frames left unpaired are dropped and counted. Stats: the
    reference camera; per camera: its clock's offset from the reference's (ms, whole
    periods aside), its drift against it (ppm), its frames paired and left unpaired."""
    names = obs.camera_names
    stats = {"cameras": list(names), "offset_ms": [None] * len(names),
             "drift_ppm": [None] * len(names), "paired_frames": [0] * len(names),
             "unpaired_frames": [0] * len(names)}
    period = period_ns or nominal_period_ns(obs)
    if len(obs) == 0 or period is None:
        return Pairing(obs, "as recorded", stats)
    cam, frame, t, row_rec = _records(obs)
    n_cams = len(names)
    counts = np.bincount(cam, minlength=n_cams)
    grids: dict[int, tuple] = {}
    for c in np.flatnonzero(counts >= MIN_FRAMES):  # a loop over cameras, not frames
        idx = np.flatnonzero(cam == c)
        idx = idx[np.argsort(t[idx], kind="stable")]
        grids[int(c)] = (idx, *_grid(t[idx], period))
    slot = np.full(len(cam), np.iinfo(np.int64).min)
    off = np.full(len(cam), np.inf)
    if grids:
        # the reference: the camera with most frames among those whose grid is a clock's
        # (a camera whose fit lost its way trusts none of its frames)
        ref = max(grids, key=lambda c: (bool(grids[c][-1].any()), counts[c]))
        stats["reference"] = names[ref]
        _, _, ref_start, ref_step, _ = grids[ref]
        for c, (idx, n, start, step, trusted) in grids.items():
            fitted = start + step * n  # the camera's grid, jitter taken out
            at = (fitted - ref_start) / ref_step
            s = np.rint(at).astype(np.int64)
            slot[idx] = np.where(trusted, s, slot[idx])
            off[idx] = np.where(trusted, np.abs(at - s), np.inf)
            phase = (start - ref_start) / ref_step  # whole periods: its later opening
            stats["offset_ms"][c] = round((phase - np.rint(phase)) * ref_step * 1e-6, 4)
            stats["drift_ppm"][c] = round((step / ref_step - 1.0) * 1e6, 2)
    ok = off <= 0.5
    # two frames of one camera on one instant: the nearer one is kept
    order = np.lexsort((off, slot, cam))
    dup = np.zeros(len(cam), dtype=bool)
    same = (cam[order][1:] == cam[order][:-1]) & (slot[order][1:] == slot[order][:-1])
    dup[order[1:][same]] = True
    ok &= ~dup
    stats["paired_frames"] = np.bincount(cam[ok], minlength=n_cams).tolist()
    stats["unpaired_frames"] = np.bincount(cam[~ok], minlength=n_cams).tolist()
    if ok.any():
        slot = slot - slot[ok].min()
    keep_rows = ok[row_rec]
    out = obs.select(keep_rows)
    out.frame = slot[row_rec][keep_rows]
    out.meta = {**out.meta, "frames": INSTANTS, "paired_by": "time"}
    return Pairing(out.sorted(), "time", stats)


def pair_frames(obs: Observations, period_ns: float | None = None) -> Pairing:
    """Observations whose frames name instants: as recorded when they already do
    (frames_are_instants), else paired by capture time."""
    if frames_are_instants(obs, period_ns):
        return Pairing(obs, "as recorded", {})
    return pair_by_time(obs, period_ns)
