"""A calibration report as one self-contained HTML page: figures, grade, plots and the rig.

One file a user can open offline, mail or attach to an issue: the plots the command draws
go in as data URIs, the rig is drawn as inline SVG (camera frusta, the floor and the
wand's points from above and from the side), the figures are tables of the same numbers
the command prints and writes with --json, and the grade comes with what to do about it.
Nothing on the page is fetched from anywhere.
"""

from __future__ import annotations

import base64
import html
import math
from pathlib import Path

import numpy as np

from calibkit.core.camera import Rig
from calibkit.core.fileio import write_text_atomic

FRUSTUM_DEPTH_M = 0.35
SVG_WIDTH_PX = 520
MAX_POINTS = 1500  # wand points drawn in each SVG view

# what a user does about each grade (the reason the grade gives comes first)
ADVICE = {
    "excellent": "The rig is ready for tracking.",
    "good": "The rig is ready for tracking. For 'excellent', wave the wand through more of "
            "every camera's image, the edges and corners most, and calibrate again.",
    "usable": "Tracking works, less precisely than this rig can. Recapture the wand with "
              "more coverage (each camera's image filled, the whole volume visited) and check "
              "the intrinsics before relying on millimetres.",
    "poor": "Do not track with this rig. Recapture the wand dance covering every camera's "
            "image, check that each camera's intrinsics belong to it, and look at the "
            "residual plot for a camera that stands out.",
    "failed": "The solution is impossible: do not use it. Check the floor frame (the L-frame "
              "or floor recording), then recapture.",
}

CSS = """
body{font:14px/1.45 system-ui,sans-serif;margin:24px auto;max-width:1150px;color:#222;
padding:0 16px}
h1{font-size:22px;margin-bottom:4px}h2{font-size:17px;margin-top:28px;border-bottom:1px solid
#ccc}
table{border-collapse:collapse;margin:8px 0}td,th{border:1px solid #ccc;padding:3px 8px;
text-align:right}th{background:#f2f2f2}td:first-child,th:first-child{text-align:left}
.grade{display:inline-block;padding:4px 12px;border-radius:4px;font-weight:600;color:#fff}
.excellent{background:#2a8a3e}.good{background:#4a9a2a}.usable{background:#c08a00}
.poor{background:#c0502a}.failed{background:#a01818}
.views{display:flex;flex-wrap:wrap;gap:12px;align-items:flex-start}figure{margin:0}figcaption{color:#555}
img{max-width:100%;border:1px solid #ddd}svg{border:1px solid #ddd;background:#fcfcfc}
.muted{color:#666}.warn{color:#a04000}
"""


def esc(value) -> str:
    return html.escape(str(value), quote=True)


def number(value, digits: int = 3) -> str:
    """A figure as the page shows it: fixed digits, '-' for NaN or nothing."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int | np.integer):
        return str(int(value))
    v = float(value)
    if not math.isfinite(v):
        return "-"
    if v != 0 and abs(v) < 0.5 * 10.0**-digits * 100:  # would show as 0.00x or 0.000
        return f"{v:.4g}"
    return f"{v:.{digits}f}"


def table(headers: list[str], rows: list[list], table_id: str | None = None,
          digits: int = 3) -> str:
    """A table of figures (`digits` after the point; small numbers in 4 significant
    digits); each cell carries its exact value (data-value) for scripts."""
    head = "".join(f"<th>{esc(h)}</th>" for h in headers)
    body = []
    for row in rows:
        cells = []
        for v in row:
            if isinstance(v, str):
                cells.append(f"<td>{esc(v)}</td>")
            else:
                exact = "" if v is None else f' data-value="{esc(repr(_plain(v)))}"'
                cells.append(f"<td{exact}>{number(v, digits)}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    ident = f' id="{esc(table_id)}"' if table_id else ""
    return f"<table{ident}><tr>{head}</tr>{''.join(body)}</table>"


def _plain(v):
    if isinstance(v, bool | np.bool_):
        return bool(v)
    if isinstance(v, int | np.integer):
        return int(v)
    return float(v)


def image(png: bytes, caption: str, image_id: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return (f'<figure><img id="{esc(image_id)}" alt="{esc(caption)}" '
            f'src="data:image/png;base64,{data}"><figcaption>{esc(caption)}</figcaption>'
            "</figure>")


def page(title: str, body: str) -> str:
    return ("<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">"
            "<meta http-equiv=\"Content-Security-Policy\" content=\"default-src 'none'; "
            "img-src data:; style-src 'unsafe-inline'\">"
            f"<title>{esc(title)}</title><style>{CSS}</style></head><body>{body}</body></html>")


# ---- the rig, drawn -------------------------------------------------------------------------

def frustum_corners(rig: Rig, depth_m: float = FRUSTUM_DEPTH_M) -> np.ndarray:
    """(cameras, 5, 3): each camera's centre and the four image corners' rays at depth_m,
    in the world (the pinhole model: distortion does not change where a frustum points)."""
    out = []
    for cam in rig:
        w, h = cam.width - 1.0, cam.height - 1.0
        px = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)
        rays = np.column_stack([(px[:, 0] - cam.cx) / cam.fx, (px[:, 1] - cam.cy) / cam.fy,
                                np.ones(4)]) * depth_m
        world = (rays - cam.t) @ cam.R  # R^T (x - t) for each row
        out.append(np.vstack([cam.centre, world]))
    return np.asarray(out)


def rig_svg(rig: Rig, points: np.ndarray | None, axes: tuple[int, int], title: str,
            svg_id: str) -> str:
    """The rig seen along one world axis: frusta (red), the floor (a 0.5 m grid from above,
    the line z = 0 from the side), the wand's points (grey); metres marked on the axes."""
    fr = frustum_corners(rig)
    i, j = axes
    pts = np.zeros((0, 3)) if points is None else np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    pts = pts[:: max(1, len(pts) // MAX_POINTS)]
    allp = np.vstack([fr.reshape(-1, 3), pts, np.zeros((1, 3))])
    lo, hi = allp[:, [i, j]].min(axis=0) - 0.3, allp[:, [i, j]].max(axis=0) + 0.3
    span = hi - lo
    s = min(SVG_WIDTH_PX / span[0], 420 / span[1])  # pixels a metre
    width, height = int(round(span[0] * s)) + 100, int(round(span[1] * s)) + 40

    def xy(p):
        p = np.asarray(p, np.float64).reshape(-1, 3)
        return np.column_stack([40 + (p[:, i] - lo[0]) * s, height - 20 - (p[:, j] - lo[1]) * s])

    parts = [f'<svg id="{esc(svg_id)}" xmlns="http://www.w3.org/2000/svg" width="{width}" '
             f'height="{height}" viewBox="0 0 {width} {height}">',
             f'<text x="6" y="14" font-size="12" fill="#333">{esc(title)}</text>']
    if j == 2:  # from the side: the floor is a line
        ends = np.zeros((2, 3))
        ends[:, i] = lo[0], hi[0]
        (x0, y0), (x1, _) = xy(ends)
        parts.append(f'<line class="floor" x1="{x0:.1f}" y1="{y0:.1f}" x2="{x1:.1f}" '
                     f'y2="{y0:.1f}" stroke="#7a7" stroke-width="2"/>')
    else:
        c = rig.centres()[:, :2]
        flo = np.maximum(np.floor((c.min(axis=0) - 0.5) * 2) / 2, np.ceil(lo * 2) / 2)
        fhi = np.minimum(np.ceil((c.max(axis=0) + 0.5) * 2) / 2, np.floor(hi * 2) / 2)
        for x in np.arange(flo[0], fhi[0] + 1e-9, 0.5):
            (a, b), (cc, d) = xy([[x, flo[1], 0], [x, fhi[1], 0]])
            parts.append(f'<line class="floor" x1="{a:.1f}" y1="{b:.1f}" x2="{cc:.1f}" '
                         f'y2="{d:.1f}" stroke="#cdc" stroke-width="1"/>')
        for y in np.arange(flo[1], fhi[1] + 1e-9, 0.5):
            (a, b), (cc, d) = xy([[flo[0], y, 0], [fhi[0], y, 0]])
            parts.append(f'<line class="floor" x1="{a:.1f}" y1="{b:.1f}" x2="{cc:.1f}" '
                         f'y2="{d:.1f}" stroke="#cdc" stroke-width="1"/>')
    if len(pts):
        q = xy(pts)
        parts.append('<g class="points" fill="#999">' + "".join(
            f'<circle cx="{a:.1f}" cy="{b:.1f}" r="1.2"/>' for a, b in q) + "</g>")
    (ox, oy), (ax, ay) = xy([[0, 0, 0], [0.5 if i == 0 else 0, 0.5 if i == 1 else 0, 0]])
    parts.append(f'<line x1="{ox:.1f}" y1="{oy:.1f}" x2="{ax:.1f}" y2="{ay:.1f}" '
                 f'stroke="#c22" stroke-width="2"/><text x="{ax + 3:.1f}" y="{ay + 4:.1f}" '
                 f'font-size="10" fill="#c22">{"xyz"[i]} 0.5 m</text>')
    for cam, f in zip(rig, fr, strict=True):
        q = xy(f)
        c0 = q[0]
        edges = "".join(f"M{c0[0]:.1f},{c0[1]:.1f}L{p[0]:.1f},{p[1]:.1f}" for p in q[1:])
        ring = "M" + "L".join(f"{p[0]:.1f},{p[1]:.1f}" for p in q[1:]) + "Z"
        parts.append(f'<g class="frustum" data-camera="{esc(cam.name)}"><path d="{edges}{ring}" '
                     'fill="rgba(200,40,40,0.12)" stroke="#c22" stroke-width="1.3"/>'
                     f'<text x="{c0[0] + 4:.1f}" y="{c0[1] - 4:.1f}" font-size="11" '
                     f'fill="#811">{esc(cam.name)}</text></g>')
    parts.append("</svg>")
    return "".join(parts)


# ---- the wand report ------------------------------------------------------------------------

def wand_page(report: dict, rig: Rig, points: np.ndarray | None,
              images: list[tuple[str, str, bytes]], rig_name: str) -> str:
    """The page of a `calibkit wand` run: `report` is the figures it writes with --json,
    `images` (id, caption, PNG bytes) the plots it drew."""
    g = report["grade"]
    out = [f"<h1>Wand calibration: {esc(rig_name)}</h1>",
           f'<p>grade <span id="grade" class="grade {esc(g)}">{esc(g)}</span> '
           f'<span id="grade-reason">{esc(report["grade_reason"])}</span></p>',
           f'<p id="advice"><b>What to do:</b> {esc(ADVICE.get(g, ""))}</p>']
    for w in report.get("warnings", []):
        out.append(f'<p class="warn">warning: {esc(w)}</p>')
    if report.get("left_out_cameras"):
        out.append(f'<p class="warn">left out, not calibrated (see the warnings): '
                   f'{esc(", ".join(report["left_out_cameras"]))}</p>')
    out.append("<h2>Cameras</h2>")
    out.append(table(
        ["camera", "observations", "coverage %", "reprojection RMS (px)", "held out (px)",
         "position SD (mm)", "orientation SD (deg)"],
        [[c["name"], c["observations"], 100.0 * c["coverage"], c["reprojection_rms_px"],
          c["held_out_rms_px"], c.get("position_std_mm"), c.get("orientation_std_deg")]
         for c in report["cameras"]], "cameras"))
    s, h = report["solve"], report["held_out"]
    keys = [("reprojection RMS (px)", "reprojection_rms_px"),
            ("wand length error, mean (mm)", "wand_length_error_mean_mm"),
            ("wand length error, SD (mm)", "wand_length_error_sd_mm"),
            ("mean ray distance (mm)", "mean_ray_distance_mm"), ("frames", "frames"),
            ("observations", "observations"),
            ("wand length variation, SD/mean (%)", "wand_length_variation_pct")]
    out.append("<h2>Figures</h2>")
    out.append(table(["figure", "solved", "held out"],
                     [[label, s.get(k), h.get(k)] for label, k in keys], "figures"))
    out += _not_computable([("solved", s), ("held out", h)])
    sy = report.get("systematic") or {}
    if sy:
        out.append("<p class=\"muted\">Systematic wand length errors (a warped space shows "
                   "here even when the pixels fit):</p>")
        out.append(table(["where", "mm", "% of the wand's length", "not computable because"],
                         [[what, sy.get(f"{key}_mm"), sy.get(f"{key}_pct"),
                           sy.get(f"{key}_reason", "")]
                          for key, what in (("volume", "across the volume"),
                                            ("radius", "image centre to edges"),
                                            ("region", "held-out regions"),
                                            ("trend", "trend with position"))],
                         "systematic"))
    det = report.get("position_ppm") or {}
    if det.get("camera") is not None:
        out.append(f'<p id="determination" class="muted">least determined camera: '
                   f'{esc(det["camera"])}, position SD {number(det["ppm"], 0)} ppm of its '
                   "distance from the reference camera (the solve's own uncertainty)</p>")
    out += _wand_intrinsics(report)
    scale = report.get("scale") or {}
    if scale and not scale.get("known", True):
        out.append(f'<p id="scale" class="warn">scale unknown: {esc(scale.get("unit", ""))}'
                   "</p>")
    out.append(f'<p class="muted">solve: {s["iterations"]} iterations, '
               f'{number(s["time_s"], 1)} s, noise {number(s["noise_px"])} px, '
               f'{s["outliers"]} outliers dropped; world frame: {esc(report["world_frame"])}; '
               f'intrinsics {"refined" if s.get("refine_intrinsics") else "kept fixed"}</p>')
    thr = report.get("grade_thresholds") or []
    if thr:
        out.append("<details><summary>Grade thresholds (held out)</summary>" + table(
            ["grade", "reprojection RMS at most (px)", "wand length SD at most (%)"],
            [[t["grade"], t["held_out_rms_px"], t["wand_length_sd_pct"]] for t in thr])
            + "</details>")
    out.append("<h2>The rig</h2><div class=\"views\">")
    out.append(rig_svg(rig, points, (0, 1), "from above (x right, y up)", "rig-top"))
    out.append(rig_svg(rig, points, (0, 2), "from the side (x right, z up)", "rig-side"))
    out.append("</div>")
    if images:
        out.append("<h2>Plots</h2><div class=\"views\">")
        out += [image(png, caption, ident) for ident, caption, png in images]
        out.append("</div>")
    return page(f"Wand calibration {rig_name}: {g}", "".join(out))


def _not_computable(parts: list[tuple[str, dict]]) -> list[str]:
    """Why a figure of the table is '-': the report's reasons, one line each."""
    return [f'<p class="muted">{esc(name)}: not computable: {esc(figs[key])}</p>'
            for name, figs in parts
            for key in ("reason", "wand_length_variation_reason") if key in figs]


def _wand_intrinsics(report: dict) -> list[str]:
    """Per camera: its intrinsics refined or kept, why, and what refining moved (or would
    have moved, for intrinsics kept)."""
    rows = []
    for c in (report.get("intrinsics") or {}).get("cameras", []):
        moved = c.get("if_refined") or c
        rows.append([c["name"], c.get("chosen", ""), moved.get("focal_change_pct"),
                     moved.get("centre_change_px"), moved.get("image_shift_px"),
                     moved.get("largest_change_sigmas"), c.get("why", "")])
    if not rows:
        return []
    return ["<h2>Intrinsics</h2>", table(
        ["camera", "intrinsics", "focal change (%)", "centre change (px)",
         "largest image shift (px)", "largest change (prior sigmas)", "why"],
        rows, "intrinsics"),
        '<p class="muted">For intrinsics kept, the changes are what refining them would have '
        "made.</p>"]


def write_page(path: Path, text: str) -> None:
    """Written whole or not at all (a temporary file renamed)."""
    write_text_atomic(path, text)


def write_wand_report(path: Path, cal, out: Path, plots: bool) -> None:
    """The page of a finished `calibkit wand` run beside its rig file `out`: with plots,
    the layout and residual PNGs it wrote next to the rig (read back, not drawn twice) and
    each camera's wand coverage over its image (solved and held-out frames)."""
    images = []
    if plots:
        # deferred on purpose: loads OpenCV only where used
        from calibkit.calibrate.wand_report import coverage_png

        for ident, suffix, caption in (("layout", ".layout.png", "cameras and wand points"),
                                       ("residuals", ".residuals.png",
                                        "residuals over each camera's image")):
            png = out.with_name(out.stem + suffix)
            if png.exists():
                images.append((ident, caption, png.read_bytes()))
        cam = np.concatenate([cal.solved["residual_camera"], cal.held["residual_camera"]])
        uv = np.concatenate([cal.solved["residual_uv"], cal.held["residual_uv"]])
        images.append(("coverage", "where each camera saw the wand",
                       coverage_png(cal.rig, cam, uv)))
    write_page(path, wand_page(cal.report, cal.rig, cal.solved["xyz"], images, out.name))


# ---- the intrinsic report -------------------------------------------------------------------

VIEW_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2",
                "#7f7f7f", "#bcbd22", "#17becf")
MAX_DOTS = 3000  # dots drawn per camera


def dots_svg(size: tuple[int, int], views: list, svg_id: str, width_px: int = 420) -> str:
    """The decoded dots of every view over the camera's image, a colour per view, with the
    8 x 6 grid the coverage figure counts: where in the image the lens was measured."""
    w, h = size
    s = width_px / w
    hp = int(round(h * s))
    parts = [f'<svg id="{esc(svg_id)}" xmlns="http://www.w3.org/2000/svg" width="{width_px}" '
             f'height="{hp}" viewBox="0 0 {width_px} {hp}"><rect width="{width_px}" '
             f'height="{hp}" fill="#202020"/>']
    for k in range(1, 8):
        parts.append(f'<line x1="{k * width_px / 8:.1f}" y1="0" x2="{k * width_px / 8:.1f}" '
                     f'y2="{hp}" stroke="#444"/>')
    for k in range(1, 6):
        parts.append(f'<line x1="0" y1="{k * hp / 6:.1f}" x2="{width_px}" '
                     f'y2="{k * hp / 6:.1f}" stroke="#444"/>')
    total = sum(len(v.uv) for v in views)
    step = max(1, total // MAX_DOTS)
    for k, v in enumerate(views):
        uv = np.asarray(v.uv, np.float64)[::step] * s
        colour = VIEW_COLOURS[k % len(VIEW_COLOURS)]
        parts.append(f'<g class="view" data-view="{k}" data-dots="{len(v.uv)}" '
                     f'fill="{colour}">' + "".join(f'<circle cx="{x:.1f}" cy="{y:.1f}" r="1.4"/>'
                                                   for x, y in uv) + "</g>")
    parts.append("</svg>")
    return "".join(parts)


def intrinsic_section(name: str, result, views: list, plot_png: bytes | None, k: int) -> str:
    """One camera's part of the intrinsic page: its figures, the views' residuals, its
    dots over the image and the distortion plot."""
    c, std = result.camera, result.std
    f = result.figures()
    rows = [["fx (px)", c.fx, std.get("fx")], ["fy (px)", c.fy, std.get("fy")],
            ["cx (px)", c.cx, std.get("cx")], ["cy (px)", c.cy, std.get("cy")],
            ["skew (px)", c.skew, std.get("skew")]]
    rows += [[n, float(v), std.get(n)] for n, v in zip(("k1", "k2", "p1", "p2", "k3"),
                                                        c.dist.tolist(), strict=False)]
    out = [f'<h2 id="camera-{k}">{esc(name)}</h2>',
           table(["figure", "value", "standard deviation"], rows, f"intrinsics-{k}"),
           table(["reprojection RMS (px)", "views", "dots", "image coverage %",
                  "inliers %"],
                 [[f["rms_px"], f["views"], f["points"], 100.0 * f["coverage"],
                   100.0 * f["inlier_fraction"]]], f"summary-{k}")]
    if f["coverage"] < 0.75:
        out.append(f'<p class="warn">The dots reached {100 * f["coverage"]:.0f} % of the '
                   "image's 8 x 6 cells: the lens is least known where none fell (its "
                   "corners and edges, most often). Show the monitor there too and "
                   "calibrate again.</p>")
    out.append('<div class="views">' + dots_svg(c.size, views, f"dots-{k}"))
    out.append(table(["view", "dots", "RMS (px)"],
                     [[v.name or f"view {i + 1}", len(v.uv), float(r)] for i, (v, r) in
                      enumerate(zip(views, result.view_rms_px, strict=False))],
                     f"views-{k}"))
    out.append("</div>")
    if plot_png is not None:
        out.append(image(plot_png, f"{name}: the lens distortion over the image",
                         f"distortion-{k}"))
    return "".join(out)


def intrinsic_page(cameras: list[tuple[str, object, list]], plots: bool = True) -> str:
    """The page of a `calibkit intrinsic` run: (name, IntrinsicResult, its views) per
    camera calibrated."""
    # deferred on purpose: loads OpenCV only where used
    from calibkit.calibrate.intrinsic import distortion_plot_png

    body = ["<h1>Intrinsic calibration: " + esc(", ".join(n for n, _, _ in cameras))
            + "</h1>", '<p class="muted">Each camera\'s lens from the dots a monitor showed: '
            "focal lengths, principal point and distortion with their standard deviations, "
            "the dots each view decoded over the image, and the distortion they give.</p>"]
    for k, (name, result, views) in enumerate(cameras):
        uv = np.concatenate([v.uv for v in views]) if views else None
        png = distortion_plot_png(result, uv) if plots else None
        body.append(intrinsic_section(name, result, views, png, k))
    names = ", ".join(n for n, _, _ in cameras)
    return page(f"Intrinsic calibration {names}", "".join(body))


# ---- the extrinsic report -------------------------------------------------------------------

def extrinsic_page(result, rig_name: str) -> str:
    """The page of a `calibkit extrinsic` run (ExtrinsicResult): which cameras were placed,
    their figures, the plane maps', and the rig with the dots from above and the side."""
    r = result.report
    n_cal, n_all = len(r["calibrated"]), len(r["cameras"])
    out = [f"<h1>Extrinsic calibration: {esc(rig_name)}</h1>",
           f'<p id="placed"><b>{n_cal} of {n_all} cameras placed</b> from the projector\'s '
           "dots on the floor" + (" and the table" if r.get("table_map") else "") + ".</p>"]
    if r["not_calibrated"]:
        out.append('<p id="advice" class="warn"><b>What to do:</b> '
                   f'{esc(", ".join(r["not_calibrated"]))} could not be placed (see the '
                   "warnings): check that each sees enough of the floor's dots, then run "
                   "again; the wand step can only refine cameras placed here.</p>")
    else:
        out.append('<p id="advice"><b>What to do:</b> refine every camera with the wand: '
                   f"<code>calibkit wand --rig {esc(rig_name)} --dots "
                   f"{esc(Path(rig_name).stem)}.dots.npz ...</code></p>")
    out += [f'<p class="warn">warning: {esc(w)}</p>' for w in result.warnings]
    out.append("<h2>Cameras</h2>")
    out.append(table(["camera", "placed", "floor dots", "table dots", "reprojection RMS (px)",
                      "mean ray distance (mm)", "on the table (mm)"],
                     [[c["name"], bool(c["calibrated"]), c["floor_dots"], c["table_dots"],
                       c["reprojection_rms_px"], c["mean_ray_distance_mm"],
                       c["mean_ray_distance_table_mm"]] for c in r["cameras"]], "cameras"))
    out.append("<h2>Figures</h2>")
    fm, tm = r["floor_map"], r.get("table_map")
    rows = [["reprojection RMS (px)", r["reprojection_rms_px"]],
            ["mean ray distance (mm)", r["mean_ray_distance_mm"]],
            ["  on the floor (mm)", r["mean_ray_distance_floor_mm"]],
            ["  on the table (mm)", r["mean_ray_distance_table_mm"]],
            ["dots seen by two or more cameras", r["dots"]],
            ["floor map residual RMS (mm)", fm["residual_rms_mm"]],
            ["floor map residual max (mm)", fm["residual_max_mm"]]]
    if tm:
        rows += [["table map residual RMS (mm)", tm["residual_rms_mm"]],
                 ["table height (m)", tm["height_m"]]]
    out.append(table(["figure", "value"], rows, "figures"))
    pts = np.asarray(result.refined_xyz, np.float64).reshape(-1, 3)
    out.append("<h2>The rig</h2><div class=\"views\">")
    out.append(rig_svg(result.rig, pts, (0, 1), "from above (x right, y up), the dots",
                       "rig-top"))
    out.append(rig_svg(result.rig, pts, (0, 2), "from the side (x right, z up)", "rig-side"))
    out.append("</div>")
    return page(f"Extrinsic calibration {rig_name}: {n_cal} of {n_all} cameras placed",
                "".join(out))
