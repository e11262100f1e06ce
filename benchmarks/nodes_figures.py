"""bench_nodes.py's figures: frame sets, tracking and the hop, from the daemon's own figures.

The daemon reports what it can see (its counts, its estimate of each node's clock); the
benchmark knows what the nodes' clocks really are (CLOCKS: each node's offset and drift,
given on its command line), so the hop is also stated against that truth.
"""

from __future__ import annotations

import numpy as np

CLOCKS = [(1250.0, 50.0), (-830.0, -50.0), (40.0, 20.0), (3700.0, -10.0)]  # ms, ppm


def true_offset_ms(offset_ms, drift_ppm, t_ns):
    """A node's clock minus the machine's at `t_ns` (ms), as its --clock-offset-ms and
    --clock-drift-ppm make it (daemon.nodes.node.NodeTime)."""
    return (round(t_ns * (1 + drift_ppm * 1e-6)) + round(offset_ms * 1e6) - t_ns) * 1e-6


def never_taken(mux: dict) -> int:
    """Sets the frame loop never took because it was behind: those it skipped to stay
    live, and those that fell off the full queue of ready sets while it was busy with one
    (`overflow`: counted apart by the multiplexer, and they are sets made too)."""
    return (mux.get("skipped_behind") or 0) + (mux.get("overflow") or 0)


def complete(incomplete: int, made: int) -> float:
    """The share of sets made with every camera. The counts are read while sets are still
    queued for the frame loop (up to its backlog: sets made, counted incomplete, neither
    taken nor skipped yet), so a share within that of 0 is shown as 0."""
    return max(0.0, 1 - incomplete / max(made, 1))


def tracking(fig) -> dict:
    """A run's whole-run figures (`mocapd start --json`): rate, frame sets, the poses
    against the simulator's truth, latency to the poses."""
    t = fig.get("truth", {})
    bodies = t.get("bodies", {}).values()
    mux = fig.get("multiplexer") or {}
    n = fig["frames"] + never_taken(mux)  # sets made
    return {"frames": fig["frames"], "rate_hz": fig["rate_hz"],
            "sets_complete": complete(mux.get("incomplete_sets", 0), n),
            "skipped_behind": never_taken(mux),
            "valid_fraction_min": min((b["valid_fraction"] for b in bodies), default=None),
            "position_error_mm_rms": t.get("position_error_mm_rms"),
            "gross_error_frames": t.get("gross_error_frames"),
            "position_error_mm_rms_without_gross": t.get("position_error_mm_rms_without_gross"),
            "latency_to_poses_ms_median": fig["latency_to_poses"]["median_ms"],
            "latency_to_poses_ms_p99": fig["latency_to_poses"]["p99_ms"]}


def hop_figures(nodes: list[dict]) -> dict:
    """The hop (node -> daemon's multiplexer) from the daemon's per-node figures, as the
    daemon measures it (through its clock estimate) and against the nodes' true clocks
    (the estimate's error at `offset_at_ns` taken off: what a frame lived), with the
    estimate's worst error (us) and a frame's time in its node."""
    errs, true = [], []
    hops = [n for n in nodes if n["hop_median_ms"] is not None]
    for n in hops:
        if n["offset_ms"] is not None and n["alive"]:
            err = n["offset_ms"] - true_offset_ms(*CLOCKS[int(n["name"][1:])], n["offset_at_ns"])
            errs.append(abs(err) * 1e3)
            true.append((n["hop_median_ms"] - err, n["hop_p99_ms"] - err))
    if not hops:
        return {"clock_error_us_loopback_max": max(errs) if errs else None}
    return {"clock_error_us_loopback_max": max(errs) if errs else None,
            "hop_ms_median": float(np.median([n["hop_median_ms"] for n in hops])),
            "hop_ms_p99": float(np.max([n["hop_p99_ms"] for n in hops])),
            "hop_true_ms_median": float(np.median([t[0] for t in true])) if true else None,
            "hop_true_ms_p99": float(np.max([t[1] for t in true])) if true else None,
            "in_node_ms_median": float(np.median([n["in_node_median_ms"] for n in hops])),
            "in_node_ms_p99": float(np.max([n["in_node_p99_ms"] for n in hops]))}
