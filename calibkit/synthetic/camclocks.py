"""Simulated cameras' own clocks: each camera's start, frame counter, stamps and lost frames.

A triggered rig takes every camera's frames at the same instants, but what reaches the
computer is per camera: the camera opens at its own moment and counts frames from there,
a frame lost on the way (a full bus, a busy computer) is simply not delivered, so the
counter (the driver's count of frames handed over) says nothing about which instant a
frame shows. Each frame comes with a capture time on the computer's clock, mapped from
the camera's own: a fixed offset (the transfer delay, the moment the mapping was made),
a drift (its crystal, tens of ppm from the computer's) and jitter. `per_camera` turns
observations numbered by instant (what `sim.observe` makes) into exactly that; which
instant each delivered frame really shows (`FrameTruth`) goes only to the scorers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibkit.core.errors import UserError
from calibkit.core.observations import Observations

EPOCH_NS = 10**12  # the computer's clock at trigger 0 (a monotonic clock is never at 0)


@dataclass(frozen=True, eq=False)
class CameraClocks:
    """Per camera: when it opens (ns after trigger 0), its stamps' offset (ns) and drift
    (ppm) against the computer's clock, the fraction of its frames lost; and the stamps'
    jitter (ns, Gaussian SD)."""

    open_ns: np.ndarray
    offset_ns: np.ndarray
    drift_ppm: np.ndarray
    drop: np.ndarray
    jitter_ns: float = 50_000.0


def make_clocks(n_cameras: int, seed: int = 0, open_spread_s: float = 0.5,
                offset_ms: float = 1.0, drift_ppm: float = 30.0, jitter_ns: float = 50_000.0,
                drop: dict[int, float] | None = None) -> CameraClocks:
    """Clocks for `n_cameras`: opening within `open_spread_s` of each other, offsets
    within +-`offset_ms`, drifts within +-`drift_ppm`; `drop`: camera index -> fraction
    of its frames lost (none otherwise)."""
    if open_spread_s < 0 or offset_ms < 0 or drift_ppm < 0 or jitter_ns < 0:
        raise UserError("camera clock spreads must not be negative")
    rng = np.random.default_rng([seed, 29])
    lost = np.zeros(n_cameras)
    for c, f in (drop or {}).items():
        if not 0 <= f < 1:
            raise UserError(f"a camera's lost-frame fraction must be in [0, 1), got {f}")
        lost[c] = f
    return CameraClocks(rng.uniform(0, open_spread_s * 1e9, n_cameras).round(),
                        rng.uniform(-offset_ms, offset_ms, n_cameras) * 1e6,
                        rng.uniform(-drift_ppm, drift_ppm, n_cameras), lost, float(jitter_ns))


@dataclass(eq=False)
class FrameTruth:
    """Every delivered frame: camera, its counter, its stamp (ns), the trigger it was taken
    at and when (ns, computer clock). Scorers find a frame by (camera, stamp)."""

    camera: np.ndarray
    frame: np.ndarray
    t_ns: np.ndarray
    trigger: np.ndarray
    taken_ns: np.ndarray

    def lookup(self, camera: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
        """Row of each (camera, stamp) in this table; -1 where none."""
        order = np.lexsort((self.t_ns, self.camera))
        kc, kt = self.camera[order], self.t_ns[order]
        pos = np.zeros(len(camera), dtype=np.int64)
        for c in np.unique(camera):  # cameras, not rows
            m = camera == c
            lo, hi = np.searchsorted(kc, c), np.searchsorted(kc, c, side="right")
            p = lo + np.searchsorted(kt[lo:hi], t_ns[m])
            p = np.minimum(p, max(hi - 1, 0))
            pos[m] = np.where((hi > lo) & (kt[p] == t_ns[m]) & (kc[p] == c), order[p], -1)
        return pos


def per_camera(obs: Observations, clocks: CameraClocks, n_frames: int, fps: float,
               seed: int = 0) -> tuple[Observations, FrameTruth]:
    """Observations numbered by trigger (frames 0..n_frames-1, every camera at the same
    instants) as each camera delivers them: only frames from its opening on and not lost,
    `frame` its own count of delivered frames, `t_ns` its stamp on the computer's clock."""
    n_cams = len(obs.camera_names)
    period = 1e9 / fps
    rng = np.random.default_rng([seed, 31])
    g = np.arange(n_frames)
    taken = EPOCH_NS + np.round(g * period).astype(np.int64)
    counter = np.full((n_cams, n_frames), -1, dtype=np.int64)
    stamp = np.zeros((n_cams, n_frames), dtype=np.int64)
    parts = []
    for c in range(n_cams):  # cameras, not frames
        delivered = (g * period >= clocks.open_ns[c]) & (rng.random(n_frames) >= clocks.drop[c])
        counter[c, delivered] = np.arange(int(delivered.sum()))
        stamp[c] = np.round(taken + (taken - EPOCH_NS) * clocks.drift_ppm[c] * 1e-6
                            + clocks.offset_ns[c]
                            + rng.normal(0.0, clocks.jitter_ns, n_frames)).astype(np.int64)
        g_ = np.flatnonzero(delivered)
        parts.append((np.full(len(g_), c), g_))
    fc = counter[obs.camera, obs.frame]
    keep = fc >= 0
    out = obs.select(keep)
    out.frame = fc[keep]
    out.t_ns = stamp[out.camera, obs.frame[keep]]
    out.meta = {**obs.meta, "frames": "per camera"}
    cam = np.concatenate([p[0] for p in parts])
    trig = np.concatenate([p[1] for p in parts])
    truth = FrameTruth(cam, counter[cam, trig], stamp[cam, trig], trig, taken[trig])
    return out.sorted(), truth


def sets_mixing_instants(paired: Observations, truth: FrameTruth, fps: float) -> dict:
    """Scored from the truth: the frame sets (rows sharing a frame number) whose cameras
    really took their frames more than half a period apart, of the sets of two or more."""
    look = truth.lookup(paired.camera, paired.t_ns)
    if np.any(look < 0):
        raise ValueError("a paired row is not a delivered frame of the simulation")
    taken = truth.taken_ns[look].astype(np.float64)
    frames, inv = np.unique(paired.frame, return_inverse=True)
    lo = np.full(len(frames), np.inf)
    hi = np.full(len(frames), -np.inf)
    np.minimum.at(lo, inv, taken)
    np.maximum.at(hi, inv, taken)
    cams = np.zeros((len(frames), len(paired.camera_names)), dtype=bool)
    cams[inv, paired.camera] = True
    multi = cams.sum(axis=1) >= 2
    spread = (hi - lo)[multi]
    return {"sets": int(multi.sum()), "mixing": int(np.sum(spread > 0.5e9 / fps)),
            "worst_spread_ms": float(spread.max() * 1e-6) if len(spread) else 0.0}
