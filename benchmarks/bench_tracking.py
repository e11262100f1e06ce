"""Tracking as the daemon runs it on what real cameras give: frames/s, pose errors, identity
swaps and gross errors, latency.

Scene: 8 cameras on a ring around a 4 m volume, 10 rigid bodies of 5 markers (50 markers)
moving and crossing at 240 fps, 0.2 px centroid noise, blobs as real cameras make them
(markers whose images overlap merge into one blob: sim.observe's default), 5 % dropouts
and 2 stray blobs per camera per frame; two camera kinds: 640x480 webcams and 1280x1024
machine-vision cameras (the same 70 degree field of view).

What the daemon is given, never the truth: a rig calibrated by the wand step (a simulated
wand dance solved by calibkit's wand solve from monitor-grade intrinsics, intrinsics
refined, the world frame from an L-frame), and bodies each defined as
`mocapd rigid-body add --from-live` does (the object held still alone in the volume, its
tracked markers over 60 frames clustered). The truth is read by the scorer only
(daemon.synthetic.evaluator.Evaluator: track swaps, gross errors over 2 cm / 5 degrees, RMS).

Speed, one core: Pipeline.process per frame set (tracker, rigid bodies, no outputs) on
frame sets prepared beforehand (paired by the multiplexer from the simulated cameras' own
stamps, as `mocapd start --sim --fast` pairs them: daemon.synthetic.virtual; the cameras
open up to 0.3 s apart, so the first sets lack some), median of `--repeats` runs; in the
same process: the
tracker fed the blobs' areas directly (as the pipeline now does too: the two rows should
agree), and the baseline of matching every frame from scratch with the epipolar
correspondence (calibkit.vision.correspondence.match_frame), no bodies.

Long run: `--minutes` of motion in 30 s scenes (daemon.synthetic.scene.SimScene), each with
its own 10 bodies defined live first, through the multiplexer and the Pipeline as fast as
it goes (no pacing).

Latency: `mocapd start --sim` in a subprocess (8 capture threads at 240 fps, triggered
multiplexer) sending UDP to this process on 127.0.0.1; latency = receive time minus the
frame's capture time carried by the packet (both the same monotonic clock; the daemon's
estimate of it from each camera's own clock, which includes the camera's smallest
transfer delay, 0.1-0.5 ms in the simulator). The simulated cameras open up to 0.3 s
apart; the first second is left out.

    python benchmarks/bench_tracking.py [--frames 1200] [--repeats 3] [--minutes 2]
                                        [--latency-s 10] [--json out.json]
"""

from __future__ import annotations

import argparse
import itertools
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from calibkit.clitools import Progress, print_table, write_json
from calibkit.core.camera import Rig
from calibkit.synthetic import sim
from calibkit.vision.correspondence import match_frame
from daemon.capture.pipeline import FrameSet, Pipeline
from daemon.capture.sources import CameraSample
from daemon.config.mocapd import SimConfig
from daemon.synthetic import virtual
from daemon.synthetic.evaluator import Evaluator
from daemon.synthetic.scene import SimScene
from daemon.tracking.rigid import BodyDef, RigidConfig
from daemon.tracking.rigid_define import body_from_snapshots
from daemon.tracking.tracker import TrackerConfig

FPS = 240.0
N_CAMERAS, N_BODIES, PER_BODY = 8, 10, 5
NOISE_PX, DROPOUT, GHOSTS = 0.2, 0.05, 2.0
VOLUME_M = 4.0
WAND_FRAMES = 2000  # 20 s of wand dance at 100 fps
LEARN_FRAMES = 60
PIECE_S = 30.0
SIZES = {"640x480": (640, 480), "1280x1024": (1280, 1024)}
ROOT = Path(__file__).resolve().parents[1]


# ---- what the daemon is given: a calibrated rig and bodies defined live -------------------------

def monitor_intrinsics(true_rig, seed):
    """The true cameras' intrinsics as a monitor calibration leaves them (focal lengths
    0.1 % off, principal points 0.5 px, k1 0.005), without their poses: what the wand step
    starts from."""
    rng = np.random.default_rng(seed)
    cams = []
    for c in true_rig:
        dist = np.array(c.dist, dtype=np.float64)
        dist[0] += rng.normal(0, 0.005)
        scale = 1 + rng.normal(0, 0.001)
        cams.append(c.replace(fx=c.fx * scale, fy=c.fy * scale, cx=c.cx + rng.normal(0, 0.5),
                              cy=c.cy + rng.normal(0, 0.5), dist=dist, rvec=np.zeros(3),
                              t=np.zeros(3)))
    return Rig(tuple(cams), meta=dict(true_rig.meta))


def calibrated_rig(true_rig, seed, wand_frames=WAND_FRAMES):
    """The rig as `calibkit wand --sim` makes it: a wand dance seen by the true cameras
    (merged blobs and all), solved from monitor-grade intrinsics with the intrinsics
    refined, the world frame from an L-frame on the floor. -> (rig, solve seconds)."""
    from calibkit.calibrate import floor
    from calibkit.calibrate.wand_solve import calibrate
    from calibkit.core.observations import Truth

    spacing = (0.0, 0.2, 0.5)
    truth = sim.wand_motion(wand_frames, 100.0, VOLUME_M, spacing, seed=seed)
    obs = sim.observe(true_rig, truth, noise_px=NOISE_PX, seed=seed + 1)
    pts = floor.LFrame().points((0.0, 0.0), 0.0)
    lframe = sim.observe(true_rig, Truth(np.repeat(np.arange(30), 3), np.tile(np.arange(3), 30),
                                         np.tile(pts, (30, 1))), noise_px=NOISE_PX, seed=seed + 2)

    def world(r, _xyz):
        return floor.world_from_recording(r, lframe, "lframe")

    t0 = time.perf_counter()
    cal = calibrate(obs, monitor_intrinsics(true_rig, seed + 3), spacing, refine_intrinsics=True,
                    holdout=0.1, seed=seed, world=world)
    rig = Rig(cal.rig.cameras, dict(cal.rig.quality), {**cal.rig.meta, "volume_m": VOLUME_M})
    return rig, time.perf_counter() - t0


def frame_sets(obs, n_frames, fps=FPS):
    """FrameSets of blobs (what capture threads hand the pipeline) from observations."""
    key = obs.frame * len(obs.camera_names) + obs.camera
    order = np.argsort(key, kind="stable")
    starts = np.searchsorted(key[order], np.arange(n_frames * len(obs.camera_names) + 1))
    for f in range(n_frames):
        t = int(f * 1e9 / fps)
        samples = []
        for c in range(len(obs.camera_names)):
            rows = order[starts[f * len(obs.camera_names) + c]:
                         starts[f * len(obs.camera_names) + c + 1]]
            samples.append(CameraSample(camera=c, index=f, t_ns=t, arrival_ns=t,
                                        uv=obs.uv[rows], area=obs.area[rows],
                                        peak=obs.peak[rows]))
        yield FrameSet(f, t, t, samples)


def learn_body(true_rig, rig, layout, name, body_id, seed, n_frames=LEARN_FRAMES):
    """A body defined as `mocapd rigid-body add --from-live` does: the object held still,
    alone, at its reference orientation in the middle of the volume, its markers seen by
    the true cameras (merged blobs, dropouts, strays), tracked with the calibrated rig for
    n_frames and clustered (daemon.tracking.rigid_define). Only the blobs reach the daemon."""
    from calibkit.core.observations import Truth

    xyz = layout + [0.0, 0.0, 0.25 * VOLUME_M]
    k = len(layout)
    truth = Truth(np.repeat(np.arange(n_frames), k), np.tile(np.arange(k), n_frames),
                  np.tile(xyz, (n_frames, 1)))
    obs = sim.observe(true_rig, truth, noise_px=NOISE_PX, dropout=DROPOUT,
                      ghosts_per_camera=GHOSTS, fps=FPS, seed=seed)
    pipe = Pipeline(rig, TrackerConfig(), RigidConfig(), [])
    snaps = []
    for fs in frame_sets(obs, n_frames):
        tr = pipe.process(fs).tracks
        if fs.index >= 5:  # as the command would: after the daemon has found the markers
            snaps.append((tr.ids[tr.seen], tr.xyz[tr.seen]))
    return BodyDef(name, body_id, body_from_snapshots(snaps), np.zeros(3))


def scene_config(size, seed, dropout=DROPOUT, ghosts=GHOSTS):
    return SimConfig(cameras=N_CAMERAS, bodies=N_BODIES, markers_per_body=PER_BODY, fps=FPS,
                     noise_px=NOISE_PX, dropout=dropout, ghosts=ghosts, volume_m=VOLUME_M,
                     size=size, seed=seed, realtime=False)


def live_bodies(scene, true_rig, rig, seed):
    """Every body of the scene defined live, one after the other."""
    return [learn_body(true_rig, rig, b.markers_body, b.name, b.id, seed + 7 * i)
            for i, b in enumerate(scene.bodies_truth)]


def scene_sets(scene, n_frames):
    """The scene's frame sets as the multiplexer makes them from the simulated cameras
    (each opening, counting and stamping on its own clock; daemon.synthetic.virtual)."""
    return list(itertools.islice(virtual.frame_sets(scene), n_frames))


def time_pipeline(rig, bodies, sets, repeats):
    """Median ms per Pipeline.process over `repeats` runs (the first frames, while tracks
    are found, left out)."""
    runs = []
    for _ in range(repeats):
        pipe = Pipeline(rig, TrackerConfig(), RigidConfig(), bodies)
        times = []
        for fs in sets:
            t0 = time.perf_counter()
            pipe.process(fs)
            times.append(time.perf_counter() - t0)
        runs.append(np.median(times[5:]))
    return float(np.median(runs)) * 1000


def time_with_areas(rig, bodies, sets, repeats):
    """As Pipeline.process does, with the blobs' areas handed to the tracker."""
    from daemon.tracking.rigid import RigidTracker
    from daemon.tracking.tracker import Tracker

    runs = []
    for _ in range(repeats):
        tracker, rigid = Tracker(rig), RigidTracker(bodies)
        times = []
        for fs in sets:
            t0 = time.perf_counter()
            cam = np.concatenate([np.full(len(s.uv), s.camera) for s in fs.samples])
            uv = np.concatenate([s.uv for s in fs.samples])
            area = np.concatenate([s.area for s in fs.samples])
            tr = tracker.update(cam, uv, fs.t_ns, area)
            rigid.update(tr, uv, tracker.cams)
            tracker.place(*rigid.hidden_markers(tr))
            times.append(time.perf_counter() - t0)
        runs.append(np.median(times[5:]))
    return float(np.median(runs)) * 1000, tracker.merged_blobs


def time_baseline(rig, sets):
    times = []
    for fs in sets:
        cam = np.concatenate([np.full(len(s.uv), s.camera) for s in fs.samples])
        uv = np.concatenate([s.uv for s in fs.samples])
        t0 = time.perf_counter()
        match_frame(rig, cam, uv)
        times.append(time.perf_counter() - t0)
    return float(np.median(times)) * 1000


def long_run(true_rig, rig, size, minutes, seed=100):
    """`minutes` of motion in PIECE_S scenes, each with its bodies defined live first,
    through the Pipeline; sums of the Evaluator's figures."""
    n_pieces = max(1, int(round(minutes * 60 / PIECE_S)))
    n = int(PIECE_S * FPS)
    tot = {"frames": 0, "poses": 0, "body_frames": 0, "gross": 0, "track_swaps": 0,
           "pos_sq": 0.0, "pos_sq_good": 0.0, "ang_sq_good": 0.0, "merged_blobs": 0}
    progress = Progress("long run, scenes", n_pieces)
    for k in range(n_pieces):
        scene = SimScene(scene_config(size, seed + 10 * k), rig, true_rig, n)
        tot["merged_blobs"] += int(scene.obs.meta.get("merged_blobs", 0))
        bodies = live_bodies(scene, true_rig, rig, seed + 10 * k)
        ev = Evaluator(scene, slots=False)
        pipe = Pipeline(rig, TrackerConfig(), RigidConfig(), bodies, hooks=[ev])
        for fs in itertools.islice(virtual.frame_sets(scene), n):
            pipe.process(fs)
        tot["frames"] += n
        tot["poses"] += int(ev.valid.sum())
        tot["body_frames"] += (ev.frames - ev.skip) * len(bodies)
        tot["gross"] += int(ev.gross.sum())
        tot["track_swaps"] += ev.track_swaps
        tot["pos_sq"] += float(ev.pos_sq.sum())  # every valid pose
        tot["pos_sq_good"] += float(ev.pos_sq_good.sum())  # those within the gross limits
        tot["ang_sq_good"] += float(ev.ang_sq_good.sum())
        progress.update(k + 1, f"{ev.track_swaps} track swaps, {int(ev.gross.sum())} gross")
    progress.finish()
    m = max(tot["poses"] - tot["gross"], 1)
    return {"minutes": tot["frames"] / FPS / 60, "frames": tot["frames"],
            "poses": tot["poses"], "valid_fraction": tot["poses"] / max(tot["body_frames"], 1),
            "track_swaps": tot["track_swaps"], "gross_errors": tot["gross"],
            "gross_fraction": tot["gross"] / max(tot["poses"], 1),
            "position_error_mm_rms_all": float(np.sqrt(tot["pos_sq"] / max(tot["poses"], 1))
                                               * 1000),
            "position_error_mm_rms_within": float(np.sqrt(tot["pos_sq_good"] / m) * 1000),
            "orientation_error_deg_rms_within": float(np.sqrt(tot["ang_sq_good"] / m)),
            "merged_blobs": tot["merged_blobs"]}


def latency(seconds: float, size: str, nice: int = 0) -> dict:
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.5)
    prio = ["nice", "-n", str(nice)] if nice else []  # as the unit's Nice= would run it
    cmd = [*prio, sys.executable, "-m", "daemon.cli", "start", "--sim",
           "--sim-cameras", str(N_CAMERAS), "--sim-bodies", str(N_BODIES),
           "--sim-fps", str(FPS), "--noise-px", str(NOISE_PX),
           "--udp", f"127.0.0.1:{rx.getsockname()[1]}", "--duration", str(seconds),
           "--runtime-dir", f"/tmp/mocapd-bench-{rx.getsockname()[1]}", "--realtime"]
    cfg = ROOT / "benchmarks" / f".bench_tracking_{size}.toml"
    w, h = SIZES[size]
    cfg.write_text(f"[sim]\nmarkers_per_body = {PER_BODY}\nsize = [{w}, {h}]\n")
    proc = subprocess.Popen(cmd + ["--config", str(cfg)], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_latency import receive_latencies

    try:
        lat, daemon_lat = receive_latencies(proc, rx)
    finally:
        proc.wait()
        cfg.unlink(missing_ok=True)
    skip = int(FPS)  # the first second: tracks being found
    a = np.array(lat[skip:]) * 1e-6
    d = np.array(daemon_lat[skip:]) * 1e-6
    return {"packets": len(a), "median_ms": float(np.median(a)), "p99_ms": float(
        np.percentile(a, 99)), "daemon_median_ms": float(np.median(d)),
            "daemon_p99_ms": float(np.percentile(d, 99)),
            "rate_hz": len(lat) / seconds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=1200, help="frames per speed run")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--minutes", type=float, default=2.0,
                    help="minutes of motion for the swap count (640x480; 0: none)")
    ap.add_argument("--latency-s", type=float, default=10.0)
    ap.add_argument("--nice", type=int, default=0,
                    help="run the daemon at this priority (negative: as root, like the "
                         "system unit's Nice=-10)")
    ap.add_argument("--rig-dir", type=Path,
                    help="keep the calibrated rigs here (NAME.rig.toml) and load them when "
                         "present, instead of solving the wand each run")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    out = {"scene": {"cameras": N_CAMERAS, "bodies": N_BODIES, "markers": N_BODIES * PER_BODY,
                     "fps": FPS, "noise_px": NOISE_PX, "dropout": DROPOUT,
                     "ghosts_per_camera": GHOSTS, "blobs": "merged (sim.observe default)"}}
    rigs = {}
    need = [n for n in SIZES if args.frames > 0 or (n == "640x480" and args.minutes > 0)]
    for name in need:
        true_rig = sim.make_rig(N_CAMERAS, VOLUME_M, size=SIZES[name], seed=100)
        path = args.rig_dir / f"{name}.rig.toml" if args.rig_dir else None
        if path is not None and path.exists():
            rig, solve_s = Rig.load(path), float("nan")
        else:
            rig, solve_s = calibrated_rig(true_rig, seed=200)
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
                rig.save(path)
        rigs[name] = (true_rig, rig)
        out[f"rig_{name}"] = {"wand_solve_s": solve_s, **{k: v for k, v in rig.quality.items()
                                                         if isinstance(v, (int, float, str))}}
        print(f"{name}: calibrated rig, reprojection "
              f"{rig.quality.get('reprojection_rms_px', float('nan')):.3f} px, grade "
              f"{rig.quality.get('grade', '?')}", file=sys.stderr, flush=True)
    rows = []
    for name in SIZES if args.frames > 0 else ():
        true_rig, rig = rigs[name]
        scene = SimScene(scene_config(SIZES[name], 1), rig, true_rig, args.frames)
        bodies = live_bodies(scene, true_rig, rig, 1)
        sets = scene_sets(scene, args.frames)
        ms = time_pipeline(rig, bodies, sets, args.repeats)
        ms_area, merged = time_with_areas(rig, bodies, sets, args.repeats)
        base = time_baseline(rig, sets[:200])
        out[name] = {"ms_per_frame": ms, "frames_per_s": 1000 / ms,
                     "ms_per_frame_with_areas": ms_area, "area_ratio": ms_area / ms,
                     "merged_blobs_by_area": merged,
                     "baseline_ms_per_frame": base, "speedup": base / ms}
        rows.append([name, round(ms, 3), round(1000 / ms), round(ms_area, 3),
                     round(ms_area / ms, 2), round(base, 2), round(base / ms, 1)])
    if rows:
        print_table(rows, ["cameras", "ms/frame", "frames/s", "ms_with_areas", "ratio",
                           "baseline_ms", "speedup"])
    if args.minutes > 0:
        true_rig, rig = rigs["640x480"]
        lr = long_run(true_rig, rig, SIZES["640x480"], args.minutes)
        out["long_run_640x480"] = lr
        print("")
        print_table([[round(lr["minutes"], 1), lr["poses"], round(100 * lr["valid_fraction"], 2),
                      lr["track_swaps"], lr["gross_errors"], round(100 * lr["gross_fraction"], 4),
                      round(lr["position_error_mm_rms_all"], 3),
                      round(lr["position_error_mm_rms_within"], 3),
                      round(lr["orientation_error_deg_rms_within"], 3), lr["merged_blobs"]]],
                    ["minutes", "poses", "valid_%", "track_swaps", "gross", "gross_%",
                     "pos_mm_rms_all", "pos_mm_rms_ok", "rot_deg_rms_ok", "merged_blobs"])
    if args.latency_s > 0:
        lrows = []
        for name in SIZES:
            lat = latency(args.latency_s, name, args.nice)
            out[f"latency_{name}"] = lat
            lrows.append([name, lat["packets"], round(lat["rate_hz"], 1),
                          round(lat["median_ms"], 3), round(lat["p99_ms"], 3),
                          round(lat["daemon_median_ms"], 3), round(lat["daemon_p99_ms"], 3)])
        print("")
        print_table(lrows, ["cameras", "packets", "rate_hz", "udp_median_ms", "udp_p99_ms",
                            "daemon_median_ms", "daemon_p99_ms"])
    if args.json:
        write_json(args.json, out)


if __name__ == "__main__":
    main()
