"""Which dots to keep: the DotFilter thresholds scored against the true dot positions.

The monitor capture (one camera, calibkit.calibrate.dotcapture) and the projector capture
(a rig, calibkit.calibrate.extrinsic_capture) find and name dots with one function and one
DotFilter. This script captures once through rendered simulator frames, keeps each
camera's settled images, then re-finds and re-names the dots under every filter in a grid
(roundness, area share of the median, scatter, border check) and scores every named dot
against where the true dot projects: dots named, the RMS error over all of them, and the
gross ones (> 1 px: misnamed or damaged) counted beside it.

Scenes: the monitor of bench_intrinsic.py (640 x 480, 6 views, seeds --monitor-seeds) and
the projector of bench_extrinsic.py's rendered run (6 cameras, floor and table sessions,
seeds --projector-seeds), plus the 2-camera 320 x 240 scene of
tests/test_extrinsic.py (grazing views of the table).

    python benchmarks/bench_dotfilter.py [--monitor-seeds 0,1,2] [--projector-seeds 0]
"""

from __future__ import annotations

import argparse
import itertools

import numpy as np

from calibkit.calibrate import dotcapture, extrinsic_capture
from calibkit.calibrate import extrinsic_reference as exr
from calibkit.calibrate.dotcapture import DotCapture, DotFilter, identify_dots
from calibkit.clitools import print_table
from calibkit.core.camera import Rig
from calibkit.synthetic import projector as sp
from calibkit.synthetic.monitor import MonitorSimConfig, make_monitor_sim
from projector.patterns import coded_schedule

GRID = [DotFilter(r, a, s, b) for r, a, s, b in itertools.product(
    (0.4, 0.5), (0.4, 0.5), (0.25, 0.3), (False, True))]


class Recorder:
    """Stands in for identify_dots during the capture: keeps its inputs, then names."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def __call__(self, schedule, step_images, on_shots, dot_filter=dotcapture.DOT_FILTER):
        self.calls.append((schedule, step_images, on_shots))
        return identify_dots(schedule, step_images, on_shots, dot_filter)


def monitor_cases(seed: int, n_views: int = 6) -> list[tuple]:
    """(schedule, step images, on shots, true uv of every point) per view."""
    cfg = MonitorSimConfig(seed=seed)
    sim = make_monitor_sim(n_views, (640, 480), seed, cfg, fill=0.8)
    schedule = coded_schedule(cfg.screen_px, 80.0, 2, 6.0)
    rec = Recorder()
    cases = []
    saved, dotcapture.identify_dots = dotcapture.identify_dots, rec
    try:
        with sim:
            cap = DotCapture(sim, schedule)
            for v in range(n_views):
                sim.set_view(v)
                cap.run()
                uv, _ = sim.truth_uv(schedule.points_xy)
                cases.append((*rec.calls[-1], uv))
    finally:
        dotcapture.identify_dots = saved
    return cases


def projector_cases(scene: sp.ProjectorScene, step: float, radius: float, seed: int,
                    latency=None) -> list[tuple]:
    """(schedule, step images, on shots, true uv of every point) per camera and session."""
    m = sp.measured_references(scene, exr.reference_layout_px((1280, 800)),
                               sp.table_reference_px(scene), 0.005, seed=seed)
    refs = exr.References(m["floor_px"], m["floor_xy_m"], m["table_px"], m["table_xy_m"],
                          m["table_height_m"])
    _, table = exr.plane_maps(refs)
    sch = coded_schedule((1280, 800), step, 2, radius)
    tsch = exr.table_schedule(sch, table)
    cfg = sp.ProjectorSimConfig(seed=seed) if latency is None else \
        sp.ProjectorSimConfig(camera_latency_s=latency, seed=seed)
    rec = Recorder()
    saved, extrinsic_capture.identify_dots = extrinsic_capture.identify_dots, rec
    try:
        with sp.ProjectorRigSim(scene, cfg) as dev:
            fcap = extrinsic_capture.capture_session(dev, sch, len(scene.rig))
            dev.set_table(True)
            extrinsic_capture.capture_session(dev, tsch, len(scene.rig),
                                              latency_frames=fcap.latency_frames)
    finally:
        extrinsic_capture.identify_dots = saved
    cases = []
    for k, call in enumerate(rec.calls):
        table_present = k >= len(scene.rig)
        xyz, _ = scene.land(sch.points_xy, table_present)
        uv, _ = scene.rig[k % len(scene.rig)].project(xyz)
        cases.append((*call, uv))
    return cases


def score(cases: list[tuple], f: DotFilter) -> dict:
    n, gross, sq = 0, 0, []
    for schedule, step_images, on_shots, truth_uv in cases:
        named = identify_dots(schedule, step_images, on_shots, f)
        err = np.linalg.norm(named.uv - truth_uv[named.ids], axis=1)
        n += len(err)
        gross += int(np.sum(~(err <= 1.0)))
        sq.append(err[err <= 1.0] ** 2)
    good = np.concatenate(sq) if sq else np.zeros(0)
    return {"dots": n, "gross": gross,
            "rms_good_px": float(np.sqrt(np.mean(good))) if len(good) else float("nan"),
            "gross_per_1000": 1000.0 * gross / max(n, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--monitor-seeds", default="0,1,2")
    ap.add_argument("--projector-seeds", default="0")
    args = ap.parse_args()
    sets = {}
    sets["monitor"] = [c for s in args.monitor_seeds.split(",") if s
                       for c in monitor_cases(int(s))]
    four = sp.make_scene(4, size=(320, 240), seed=1)
    two = sp.ProjectorScene(Rig((four.rig[0], four.rig[2])), four.projector, four.table)
    sets["projector 2 cams"] = projector_cases(two, 96, 10, 1, latency=(0.02, 0.25))
    sets["projector 6 cams"] = [c for s in args.projector_seeds.split(",") if s
                                for c in projector_cases(sp.make_scene(6, 4.0, 0.75, seed=int(s)),
                                                         64, 8, int(s))]
    for name, cases in sets.items():
        rows = []
        for f in GRID:
            r = score(cases, f)
            rows.append([f.min_roundness, f.min_area_ratio, f.max_scatter_px,
                         "yes" if f.drop_border else "no", r["dots"], r["rms_good_px"],
                         r["gross"], r["gross_per_1000"]])
        print(f"\n{name}: {len(cases)} camera views")
        print_table(rows, ["roundness", "area_share", "scatter_px", "border", "dots",
                           "rms_px (<= 1 px)", "gross (> 1 px)", "gross per 1000"])


if __name__ == "__main__":
    main()
