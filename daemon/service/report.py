"""What a running daemon reports: its status (the control socket's `status`) and a run's figures.

Apart from daemon.service.daemon, which sets the daemon up and runs it: these only read
what it holds (the pipeline's statistics, the captures, the multiplexer, the publishers,
the scorers), so they take the Daemon and change nothing.
"""

from __future__ import annotations

import time

import numpy as np

from daemon.capture.pipeline import latency_figures, latency_stage_figures
from daemon.process.supervise import threads_status
from daemon.publish.udp import UdpPublisher


def status(daemon) -> dict:
    """The control socket's `status` answer: uptime, rates, latency, each camera, body,
    output and supervised thread."""
    st = daemon.pipeline.stats
    cams = []
    by_camera = {c.source.camera: c for c in daemon.captures}
    tables = {c.name: c for c in daemon.config.cameras}
    for i, name in enumerate(daemon.rig.names):
        cap = by_camera.get(i)
        if cap is None and daemon.captures:  # a camera that was skipped
            cams.append({"name": name, "connected": False, "rate_hz": 0.0, "frames": 0,
                         "dropped": 0, "failures": 0})
            continue
        mux = getattr(daemon, "mux", None)
        cam = {"name": name,
               "connected": bool(cap.connected) if cap else True,
               "rate_hz": cap.rate_hz() if cap else st.rate_hz(),
               "frames": cap.frames if cap else st.frames,
               "dropped": int(mux.missing[i]) if mux else 0,
               "failures": cap.failures if cap else 0,
               "restarts": cap.sup.restarts if hasattr(cap, "sup") else 0}
        if mux is not None:  # its clock against the daemon's, frames its counter skipped
            cam.update(mux.camera_status(i))
        table = tables.get(name)
        if table is not None:  # a [[camera]] of the configuration: how it detects
            cam.update(threshold=table.threshold, min_area=table.min_area,
                       max_area=table.max_area,
                       mask=None if table.mask is None else str(table.mask))
        cams.append(cam)
    poses = getattr(daemon.pipeline, "last_result", None)
    bodies = daemon.pipeline.rigid.bodies
    valid = poses.poses.valid if poses is not None else ()
    if len(valid) != len(bodies):  # a reload changed the bodies; no frame has them yet
        valid = np.zeros(len(bodies), dtype=bool)
    return {
        "uptime_s": (time.monotonic_ns() - daemon.started_ns) * 1e-9,
        "scheduling": daemon.scheduling,
        "frames": st.frames, "rate_hz": st.rate_hz(),
        "latency": latency_figures(st.latency),
        # CPU the simulator's scorers took on the frame loop's thread (0 without --sim)
        "scorers_cpu_s": daemon.pipeline.idle_cpu_ns * 1e-9,
        "cameras": cams,
        "bodies": [{"id": int(b.id), "name": b.name, "valid": bool(v)}
                   for b, v in zip(bodies, valid, strict=True)],
        "bodies_tracked": st.valid_bodies,
        "outputs": [p.status() for p in daemon.pipeline.publishers],
        "recording": str(daemon.recorder.path) if daemon.recorder else None,
        "recording_status": daemon.recorder.status() if daemon.recorder else None,
        "labelling": None if daemon.labelling is None else daemon.labelling.status(),
        "multiplexer": daemon.mux_stats(),
        "nodes": daemon.hub.status() if daemon.hub is not None else None,
        # every supervised thread (daemon.process.supervise): state and restarts
        "threads": threads_status(*daemon.captures, daemon.control,
                                  *daemon.pipeline.publishers, daemon.recorder, daemon.view,
                                  daemon.hub),
        "view": daemon.view.status() if daemon.view is not None else None,
    }


def figures(daemon, learn_frames: int) -> dict:
    """A finished run's figures (`mocapd start --json`): rate, latency, cameras, outputs,
    and with --sim the scorers' figures; `learn_frames` is what each body was held for."""
    st = daemon.pipeline.stats
    fps = daemon.config.sim.fps if daemon.config.sim is not None else daemon.config.fps
    elapsed = (st.done[-1] - st.done[0]) * 1e-9 if len(st.done) > 1 else 0.0
    out = {
        "frames": st.frames,
        "rate_hz": (len(st.done) - 1) / elapsed if elapsed > 0 else None,
        "latency_to_poses": latency_figures(st.all_latency),
        "markers_tracked_median": float(np.median(st.markers_seen)) if len(st.markers_seen)
        else 0.0,
        "bodies_valid_fraction": {str(i): st.body_valid[i] / st.body_frames[i]
                                  for i in st.body_frames},
        "cameras": daemon.status()["cameras"],
        "outputs": [p.status() for p in daemon.pipeline.publishers],
        "scheduling": daemon.scheduling,
    }
    sent = [p for p in daemon.pipeline.publishers if isinstance(p, UdpPublisher)]
    if sent:
        out["latency_to_udp_sent"] = latency_figures(
            [s - a for a, s in sent[0].send_ns])
    if daemon.captures:  # live: where the latency goes (the first second left out)
        out["latency_stages"] = latency_stage_figures(st.stage_ns, skip=int(fps))
    if daemon.mux_stats():
        out["multiplexer"] = daemon.mux_stats()
    if daemon.hub is not None:
        out["nodes"] = daemon.hub.status()
    if daemon.evaluator is not None:
        out["truth"] = daemon.evaluator.figures()
        out["truth"]["tracking_rig"] = daemon.tracking_rig_note()
    if daemon._learned is not None:
        out["bodies_defined_live"] = {
            "file": None if daemon.learned_path is None else str(daemon.learned_path),
            "frames_each": learn_frames,
            "bodies": [{"name": b.name, "id": b.id, "markers": len(b.markers)}
                       for b in daemon._learned[1]]}
    if daemon.label_score is not None and daemon.label_score.frames:
        out.setdefault("truth", {})["labelling"] = daemon.label_score.figures()
    if daemon.labelling is not None:
        st = daemon.labelling.status()
        out["labelling"] = {k: st[k] for k in ("markerset", "frames", "starts", "failures",
                                               "time_ms_median", "time_ms_p99")}
    return out


def tracking_rig_note(daemon) -> str:
    """Which cameras a simulated run tracked with, said beside its figures: a
    calibrated rig file, or (no rig given) the simulator's own cameras, whose figures
    are those of a perfect calibration."""
    cfg = daemon.config
    if daemon._truth_rig is not None:
        return f"calibrated: {cfg.rig or 'the rig given'} (blobs from the --truth-rig)"
    if cfg.rig is not None:
        return (f"{cfg.rig}, which also made the blobs (a perfect calibration; give "
                "--truth-rig for the true cameras, or run `calibkit demo`)")
    return ("the simulator's own cameras (a perfect calibration; give a calibrated --rig "
            "and the --truth-rig, or run `calibkit demo`)")


def mux_stats(daemon) -> dict | None:
    """The multiplexer's counts (None: no multiplexer, a fast simulated run)."""
    mux = getattr(daemon, "mux", None)
    if mux is None:
        return None
    return {"incomplete_sets": mux.incomplete, "late_samples": mux.late,
            "settling_samples": mux.settling, "overflow": mux.overflow,
            "skipped_behind": mux.skipped, "behind": getattr(mux, "behind", "")}
