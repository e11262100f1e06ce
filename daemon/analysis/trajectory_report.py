"""The trajectory evaluation as pictures: a PNG of the paths and errors, and one HTML page."""

from __future__ import annotations

import base64
import html
import io
from pathlib import Path

import numpy as np

from calibkit.core.fileio import write_bytes_atomic, write_text_atomic
from daemon.analysis.trajectory_eval import Evaluation


def plot_png(ev: Evaluation, title: str = "") -> bytes:
    """Top view of both paths, position error over time, and the relative errors."""
    # deferred on purpose: loads matplotlib only where used
    import matplotlib

    matplotlib.use("Agg")
    # deferred on purpose: loads matplotlib only where used
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    ax = axes[0]
    ax.plot(ev.ref_xyz[:, 0], ev.ref_xyz[:, 1], lw=1.0, label="reference")
    ax.plot(ev.est_xyz[:, 0], ev.est_xyz[:, 1], lw=1.0, ls="--", label="estimate, aligned")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("paths, top view")
    ax.legend(loc="best", fontsize=8)
    ax = axes[1]
    t = ev.t_s - ev.t_s[0]
    ax.plot(t, ev.position_error_m * 1000, lw=0.8)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("position error (mm)")
    ax.set_title("absolute error after alignment")
    ax = axes[2]
    if len(ev.rpe_translation_m):
        ax.hist(ev.rpe_translation_m * 1000, bins=50)
    ax.set_xlabel(f"translation error over {ev.rpe_delta_s:g} s (mm)")
    ax.set_ylabel("pose pairs")
    ax.set_title("relative error")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue()


def _rows(figs: dict) -> list[tuple[str, str]]:
    a, r = figs["ate_position_mm"], figs["ate_rotation_deg"]
    rpe = figs["rpe"]
    time = figs["time"]
    return [
        ("poses compared", f"{figs['poses_compared']}"),
        ("clock offset (estimate - reference)", f"{time['offset_s'] * 1000:.3f} ms"),
        ("clock drift", f"{time['drift_ppm']:.1f} ppm"),
        ("alignment rotation", f"{figs['alignment']['rotation_deg']:.4f} deg"),
        ("alignment scale", f"{figs['alignment']['scale']:.6f}"),
        ("position error RMS / median / max",
         f"{a['rms']:.2f} / {a['median']:.2f} / {a['max']:.2f} mm"),
        (f"gross position errors (> {a['gross_limit']:g} mm)", f"{a['gross']}"),
        ("orientation error RMS / max", f"{r['rms']:.3f} / {r['max']:.3f} deg"),
        (f"gross orientation errors (> {r['gross_limit']:g} deg)", f"{r['gross']}"),
        (f"relative translation error over {rpe['delta_s']:g} s, RMS",
         f"{rpe['translation_mm'].get('rms', float('nan')):.2f} mm"),
        (f"relative rotation error over {rpe['delta_s']:g} s, RMS",
         f"{rpe['rotation_deg'].get('rms', float('nan')):.3f} deg"),
    ]


def write_html(path: str | Path, figs: dict, png: bytes, reference: str, estimate: str) -> None:
    """One self-contained page: the figures table and the plots (embedded)."""
    rows = "\n".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(v)}</td></tr>"
                     for k, v in _rows(figs))
    image = base64.b64encode(png).decode("ascii")
    page = f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<title>Trajectory evaluation: {html.escape(estimate)} against {html.escape(reference)}</title>
<style>
body {{ font-family: system-ui, sans-serif; margin: 2em; color: #222; }}
table {{ border-collapse: collapse; margin-bottom: 1.5em; }}
td {{ border-bottom: 1px solid #ddd; padding: 4px 12px; }}
td:last-child {{ text-align: right; font-variant-numeric: tabular-nums; }}
img {{ max-width: 100%; }}
</style></head><body>
<h1>Trajectory evaluation</h1>
<p>Estimate <code>{html.escape(estimate)}</code> against reference
<code>{html.escape(reference)}</code>, after lining up the clocks and the world frames.</p>
<table id="figures">
{rows}
</table>
<img alt="paths and errors" src="data:image/png;base64,{image}">
</body></html>
"""
    write_text_atomic(path, page)


def write_png(path: str | Path, png: bytes) -> None:
    write_bytes_atomic(path, png)


def table_rows(figs: dict) -> list[list[str]]:
    """The same figures as rows for a terminal table."""
    return [[k, v] for k, v in _rows(figs)]


def errors_csv(ev: Evaluation) -> str:
    """Per-pose errors: reference time, position error (mm), orientation error (deg)."""
    data = np.column_stack([ev.t_s, ev.position_error_m * 1000, ev.rotation_error_deg])
    lines = ["t_s,position_error_mm,orientation_error_deg"]
    lines += [f"{t:.6f},{p:.4f},{r:.4f}" for t, p, r in data]
    return "\n".join(lines) + "\n"
