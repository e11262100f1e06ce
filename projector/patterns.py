"""Dot schedules for a monitor or projector, and decoding which dot a camera sees.

Two schedules. The single-dot raster scan (one dot per frame, step in pixels) is the
original system's: trivially identified, and slow (one frame per point). The coded schedule
shows a whole grid of dots at once and names each dot by a temporal code: over a few frames
each dot is on or off following the bits of the Gray code of its index, plus one even-parity
bit; an all-on and an all-off frame give every dot its own reference levels, so the
decision threshold adapts to each dot's brightness in the image (vignetting, viewing angle,
a camera that sees only part of the screen). The grid is then shown again shifted by
fractions of its step ("layers"), so the points fill the screen densely while neighbouring
dots stay far apart in the image.

The parity bit makes decoding survive a dropped or unreadable frame: a bit whose level is
missing (NaN) or ambiguous is an erasure, and a single erasure per code is restored from the
parity; codes with more erasures, a failed parity check or an index outside the grid are
rejected, never guessed.

Nothing here assumes a monitor: a projector casting dots on a floor uses the same schedule
and the same decoding (calibkit.calibrate.extrinsic_capture). Positions are screen pixels
(x right, y down, pixel centres at integer coordinates).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

ROLE_ON, ROLE_OFF, ROLE_BIT, ROLE_DOT = "on", "off", "bit", "dot"


@dataclass(frozen=True, eq=False)
class PatternFrame:
    """One frame to show: dot centres (K, 2) screen px with their global point ids (K,).

    layer: which grid layer (or, for a raster scan, which dot) it belongs to; role: "on"
    (every dot of the layer), "off" (none), "bit" (the dots whose code has bit `bit` set;
    bit == n_bits is the parity bit) or "dot" (a raster-scan frame).
    """

    xy: np.ndarray
    ids: np.ndarray
    layer: int
    role: str
    bit: int = -1


@dataclass(frozen=True, eq=False)
class Schedule:
    """A dot schedule: every point's screen position (by global id), the layers, the frames."""

    screen_px: tuple[int, int]
    points_xy: np.ndarray  # (P, 2) screen pixels of every point, indexed by global id
    layers: list[np.ndarray]  # global ids shown by each layer, in code-index order
    frames: list[PatternFrame]
    n_bits: int  # data bits per code (0 for a raster scan)
    radius_px: float
    step_px: float
    kind: str = "coded"
    meta: dict = field(default_factory=dict)

    def layer_frames(self, layer: int) -> list[int]:
        """Indices into `frames` of one layer, in the order on, off, bit 0.., parity."""
        return [i for i, f in enumerate(self.frames) if f.layer == layer]


def gray_encode(n: np.ndarray) -> np.ndarray:
    n = np.asarray(n, dtype=np.int64)
    return n ^ (n >> 1)


def gray_decode(g: np.ndarray) -> np.ndarray:
    g = np.asarray(g, dtype=np.int64).copy()
    shift = g >> 1
    while np.any(shift):
        g ^= shift
        shift >>= 1
    return g


def code_bits(index: np.ndarray, n_bits: int) -> np.ndarray:
    """(N, n_bits + 1) bool: the Gray code bits of each index (LSB first) and a parity bit
    making the count of ones even."""
    g = gray_encode(index)
    bits = ((g[:, None] >> np.arange(n_bits)) & 1).astype(bool)
    parity = bits.sum(axis=1) % 2 == 1
    return np.column_stack([bits, parity])


def grid_positions(screen_px: tuple[int, int], step_px: float, offset_px=(0.0, 0.0),
                   margin_px: float = 8.0) -> np.ndarray:
    """A rectangular grid of dot centres inside the screen, `margin_px` from its edges."""
    w, h = screen_px
    ox, oy = offset_px
    xs = np.arange(margin_px + ox, w - 1 - margin_px + 1e-9, step_px)
    ys = np.arange(margin_px + oy, h - 1 - margin_px + 1e-9, step_px)
    gx, gy = np.meshgrid(xs, ys)
    return np.column_stack([gx.ravel(), gy.ravel()])


def coded_schedule(screen_px: tuple[int, int], step_px: float = 80.0, shifts: int = 2,
                   radius_px: float = 6.0, margin_px: float | None = None,
                   predict: bool = True) -> Schedule:
    """The fast schedule: a grid with `step_px` spacing, shown in shifts x shifts layers
    offset by fractions (i / shifts, j / shifts) of the step.

    The first layer takes 2 + n_bits + 1 frames (on, off, bits, parity). With `predict`,
    every further layer is a single all-on frame: its dots are named by where the
    already identified dots around them say they must be (identify_by_neighbours), which
    cuts a view's frames by two thirds; without it each layer is coded like the first.
    """
    if step_px < 4 * radius_px:
        raise ValueError(f"step {step_px} px is too small for dots of radius {radius_px} px")
    if shifts < 1:
        raise ValueError("shifts must be >= 1")
    margin = 2 * radius_px + 2 if margin_px is None else margin_px
    all_xy, layers, frames = [], [], []
    offsets = [(i * step_px / shifts, j * step_px / shifts)
               for j in range(shifts) for i in range(shifts)]
    grids = [grid_positions(screen_px, step_px, off, margin) for off in offsets]
    n_max = max(len(g) for g in grids)
    n_bits = max(1, int(np.ceil(np.log2(max(n_max, 2)))))
    start = 0
    for layer, xy in enumerate(grids):
        ids = np.arange(start, start + len(xy))
        start += len(xy)
        all_xy.append(xy)
        layers.append(ids)
        bits = code_bits(np.arange(len(xy)), n_bits)
        frames.append(PatternFrame(xy, ids, layer, ROLE_ON))
        if predict and layer > 0:
            continue
        frames.append(PatternFrame(xy[:0], ids[:0], layer, ROLE_OFF))
        for b in range(n_bits + 1):
            on = bits[:, b]
            frames.append(PatternFrame(xy[on], ids[on], layer, ROLE_BIT, b))
    return Schedule(tuple(screen_px), np.concatenate(all_xy), layers, frames, n_bits,
                    float(radius_px), float(step_px), "coded",
                    {"shifts": shifts, "predict": predict})


def raster_schedule(screen_px: tuple[int, int], step_px: float = 80.0, radius_px: float = 6.0,
                    margin_px: float | None = None) -> Schedule:
    """The original single-dot scan: one dot per frame, row by row."""
    margin = 2 * radius_px + 2 if margin_px is None else margin_px
    xy = grid_positions(screen_px, step_px, (0.0, 0.0), margin)
    ids = np.arange(len(xy))
    frames = [PatternFrame(xy[i:i + 1], ids[i:i + 1], i, ROLE_DOT) for i in range(len(xy))]
    return Schedule(tuple(screen_px), xy, [ids[i:i + 1] for i in ids], frames, 0,
                    float(radius_px), float(step_px), "raster")


# ---- decoding ----------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Decoded:
    """Per observed dot: its code index within the layer (-1 if rejected), whether it was
    accepted, how many bits were restored from parity, and the smallest bit margin (0..0.5:
    how far the weakest bit's level was from the decision threshold)."""

    index: np.ndarray
    ok: np.ndarray
    restored: np.ndarray
    margin: np.ndarray


def decode_levels(on: np.ndarray, off: np.ndarray, bits: np.ndarray, n_codes: int,
                  min_contrast: float = 10.0, min_margin: float = 0.15) -> Decoded:
    """Identify dots from the levels measured at their image positions.

    on, off: (N,) levels in the all-on and all-off frames; bits: (N, n_bits + 1) levels in
    the bit frames (last column parity), NaN where the frame was not captured. A level is
    normalised to (level - off) / (on - off): above 0.5 the dot was on. Bits closer to 0.5
    than `min_margin` count as erasures, as do NaNs. Dots whose on-off contrast is below
    `min_contrast` are rejected (not a dot, or the monitor edge).
    """
    on = np.asarray(on, dtype=np.float64)
    off = np.asarray(off, dtype=np.float64)
    bits = np.asarray(bits, dtype=np.float64)
    n, nb1 = bits.shape
    contrast = on - off
    good = np.isfinite(contrast) & (contrast >= min_contrast)
    with np.errstate(invalid="ignore", divide="ignore"):
        level = (bits - off[:, None]) / np.where(good, contrast, 1.0)[:, None]
    value = level > 0.5
    margin = np.abs(level - 0.5)
    erased = ~np.isfinite(level) | (margin < min_margin)
    n_erased = erased.sum(axis=1)
    ones = (value & ~erased).sum(axis=1)
    # one erasure: the parity (even count of ones) says what the missing bit was
    fix = n_erased == 1
    missing = np.argmax(erased, axis=1)
    restored_bit = (ones % 2) == 1
    value = value.copy()
    rows = np.nonzero(fix)[0]
    value[rows, missing[rows]] = restored_bit[rows]
    parity_ok = value.sum(axis=1) % 2 == 0
    data = value[:, : nb1 - 1].astype(np.int64)
    gray = (data << np.arange(nb1 - 1)).sum(axis=1)
    index = gray_decode(gray)
    ok = good & (n_erased <= 1) & parity_ok & (index < n_codes)
    finite_margin = np.where(erased, np.inf, margin)
    weakest = np.min(finite_margin, axis=1, initial=np.inf)
    return Decoded(np.where(ok, index, -1), ok, fix & ok,
                   np.where(np.isfinite(weakest), weakest, 0.0))


def sample_levels(image: np.ndarray, uv: np.ndarray, radius_px: float) -> np.ndarray:
    """Mean level of a (2r+1)^2 box around each image position (N, 2): the cheap, robust
    per-dot brightness the decoder compares against its on/off references. NaN outside."""
    # deferred on purpose: loads OpenCV only where used
    import cv2

    img = np.asarray(image, dtype=np.float32)
    k = max(1, int(np.ceil(radius_px)))
    box = cv2.boxFilter(img, -1, (2 * k + 1, 2 * k + 1), borderType=cv2.BORDER_REPLICATE)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    col = np.rint(uv[:, 0]).astype(np.int64)
    row = np.rint(uv[:, 1]).astype(np.int64)
    inside = (col >= 0) & (row >= 0) & (col < img.shape[1]) & (row < img.shape[0])
    out = np.full(len(uv), np.nan)
    out[inside] = box[row[inside], col[inside]]
    return out


def decode_layer(schedule: Schedule, layer: int, step_images: dict[int, np.ndarray | None],
                 uv: np.ndarray, window_px: float = 2.0, min_contrast: float = 10.0
                 ) -> tuple[np.ndarray, Decoded]:
    """Global point ids (-1 when rejected) of dots seen at image positions `uv` (N, 2).

    step_images maps each frame index of the layer to the (averaged) camera image taken
    while it was shown, or None when that frame was dropped.
    """
    idx = schedule.layer_frames(layer)
    on_i, off_i, bit_i = idx[0], idx[1], idx[2:]

    def levels(i: int) -> np.ndarray:
        img = step_images.get(i)
        if img is None:
            return np.full(len(uv), np.nan)
        return sample_levels(img, uv, window_px)

    on, off = levels(on_i), levels(off_i)
    bits = np.column_stack([levels(i) for i in bit_i]) if bit_i else np.zeros((len(uv), 0))
    ids = schedule.layers[layer]
    dec = decode_levels(on, off, bits, len(ids), min_contrast)
    return np.where(dec.ok, ids[np.maximum(dec.index, 0)], -1), dec


def predict_from_neighbours(ref_screen: np.ndarray, ref_uv: np.ndarray, screen: np.ndarray,
                            k: int = 8, skip_self: bool = False
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image positions of screen points (P, 2) predicted by a local homography fitted to the
    k nearest identified dots around each. A flat screen seen by a camera is a homography
    up to the lens distortion, which is smooth, so over a few dot spacings the local fit
    is good to a fraction of a pixel even for steep tilts (an affine fit is not: it misses
    the perspective by pixels). Returns predictions (P, 2), the fit's RMS (P,) px, and
    whether the neighbours surround the point closely enough to trust it (P,). With
    skip_self the points are the reference dots themselves, each predicted without itself.
    """
    # deferred on purpose: loads SciPy's sparse graphs, SciPy's spatial only where used
    from scipy.spatial import cKDTree

    k = max(4, min(k, len(ref_uv) - (1 if skip_self else 0)))
    dist, nb = cKDTree(ref_screen).query(screen, k=k + (1 if skip_self else 0))
    if skip_self:
        dist, nb = dist[:, 1:], nb[:, 1:]
    P = len(screen)
    # normalise each neighbourhood (centred, unit spread) for a well-conditioned DLT
    S = ref_screen[nb] - screen[:, None, :]
    s_scale = np.maximum(np.sqrt(np.mean(np.sum(S ** 2, axis=2), axis=1)), 1e-9)
    S = S / s_scale[:, None, None]
    U0 = ref_uv[nb]
    u_mean = U0.mean(axis=1)
    U = U0 - u_mean[:, None, :]
    u_scale = np.maximum(np.sqrt(np.mean(np.sum(U ** 2, axis=2), axis=1)), 1e-9)
    U = U / u_scale[:, None, None]
    one = np.ones((P, k))
    zero = np.zeros((P, k, 3))
    xs = np.stack([S[:, :, 0], S[:, :, 1], one], axis=2)  # (P, k, 3)
    rows_u = np.concatenate([xs, zero, -U[:, :, :1] * xs], axis=2)
    rows_v = np.concatenate([zero, xs, -U[:, :, 1:] * xs], axis=2)
    A = np.concatenate([rows_u, rows_v], axis=1)  # (P, 2k, 9)
    _, sv, vt = np.linalg.svd(A)
    H = vt[:, -1, :].reshape(P, 3, 3)
    proj = np.einsum("pij,pkj->pki", H, xs)
    with np.errstate(divide="ignore", invalid="ignore"):
        fit = proj[:, :, :2] / proj[:, :, 2:]
        fit_rms = np.sqrt(np.mean(np.sum((fit - U) ** 2, axis=2), axis=1)) * u_scale
        centre = H[:, :2, 2] / H[:, 2, 2:3]  # the query point is the origin
    pred = centre * u_scale[:, None] + u_mean
    ok_fit = np.isfinite(pred).all(axis=1) & np.isfinite(fit_rms) & (sv[:, -2] > 1e-9)
    pred = np.where(ok_fit[:, None], pred, 0.0)
    fit_rms = np.where(ok_fit, fit_rms, np.inf)
    # neighbours must surround the point: no extrapolation far outside them
    near = dist[:, -1] <= 3.0 * np.median(dist[:, -1])
    return pred, fit_rms, ok_fit & near


def check_by_neighbours(screen: np.ndarray, uv: np.ndarray, k: int = 8,
                        max_px: float | None = None) -> np.ndarray:
    """Which identified dots agree with their neighbours: each dot's image position must be
    where its k nearest dots (on the screen) place it, within `max_px` (default a fifth of
    the image spacing). A misdecoded id points to a screen position far away, so its dot
    sits where its supposed neighbours say it cannot be (a local homography fitted to
    them, predict_from_neighbours). Mask (N,)."""
    # deferred on purpose: loads SciPy's sparse graphs, SciPy's spatial only where used
    from scipy.spatial import cKDTree

    n = len(uv)
    if n < k + 2:
        return np.ones(n, bool)  # too few to judge: keep
    if max_px is None:
        spacing, _ = cKDTree(uv).query(uv, k=2)
        max_px = 0.2 * float(np.median(spacing[:, 1]))
    # a wrong dot spoils its neighbours' fits too: peel off the worst offenders first,
    # then judge every dot (the peeled ones too) against the clean set
    keep = np.ones(n, bool)
    for limit in (8.0 * max_px, 3.0 * max_px, max_px):
        idx = np.nonzero(keep)[0]
        if len(idx) < k + 2:
            break
        pred, _, _ = predict_from_neighbours(screen[idx], uv[idx], screen[idx], k, True)
        keep[idx[np.linalg.norm(pred - uv[idx], axis=1) > limit]] = False
    idx = np.nonzero(keep)[0]
    out = keep.copy()
    rest = np.nonzero(~keep)[0]
    if len(idx) >= k + 1 and len(rest):
        pred, _, trusted = predict_from_neighbours(screen[idx], uv[idx], screen[rest], k)
        out[rest] = trusted & (np.linalg.norm(pred - uv[rest], axis=1) <= max_px)
    return out


def identify_by_neighbours(ref_screen: np.ndarray, ref_uv: np.ndarray, screen: np.ndarray,
                           uv: np.ndarray, k: int = 8, max_px: float | None = None,
                           max_fit_px: float = 0.5) -> np.ndarray:
    """Name detected dots from their identified neighbours, without a code.

    ref_screen/ref_uv: (M, 2) already identified dots (screen and image positions);
    screen: (P, 2) the screen positions shown now; uv: (N, 2) the dots detected now.
    Around each shown position the k nearest identified dots (on the screen) give a local
    homography screen -> image (predict_from_neighbours); the detection nearest to the
    prediction is taken if it is within `max_px` (default a quarter of the image spacing
    of the reference dots), the match is mutual, and the local fit itself is good to
    `max_fit_px`. Returns, per detection, the index
    into `screen` (-1 when not identified).
    """
    # deferred on purpose: loads SciPy's sparse graphs, SciPy's spatial only where used
    from scipy.spatial import cKDTree

    out = np.full(len(uv), -1, dtype=np.int64)
    if len(ref_uv) < max(k, 4) or len(uv) == 0 or len(screen) == 0:
        return out
    pred, fit_rms, trusted = predict_from_neighbours(ref_screen, ref_uv, screen, k)
    good = trusted & (fit_rms <= max_fit_px)
    if max_px is None:
        spacing, _ = cKDTree(ref_uv).query(ref_uv, k=2)
        max_px = 0.25 * float(np.median(spacing[:, 1]))
    tree_uv = cKDTree(uv)
    d_pu, j = tree_uv.query(pred)
    d_up, i_back = cKDTree(pred).query(uv)
    for_good = good & (d_pu <= max_px)
    cand = np.nonzero(for_good)[0]
    mutual = i_back[j[cand]] == cand
    out[j[cand[mutual]]] = cand[mutual]
    return out


def sampling_window_px(uv: np.ndarray) -> float:
    """A window for sampling a dot's code, well inside the dots' spacing in the image."""
    if len(uv) < 2:
        return 2.0
    # deferred on purpose: loads SciPy's sparse graphs, SciPy's spatial only where used
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(uv).query(uv, k=2)
    return float(np.clip(np.median(dist[:, 1]) / 6.0, 1.0, 4.0))


def name_layer(schedule: Schedule, layer: int, step_images: dict[int, np.ndarray | None],
               found: np.ndarray, known_ids: np.ndarray, known_uv: np.ndarray) -> np.ndarray:
    """The dot id of each dot `found` (image pixels) in one layer of a schedule, -1 where
    none can be given: a coded layer by its code, each id then checked against its
    neighbours; a predicted (uncoded) layer from where the dots already named (known_ids at
    known_uv) put it. What the intrinsic and extrinsic captures share."""
    if len(schedule.layer_frames(layer)) == 1:
        layer_ids = schedule.layers[layer]
        pick = identify_by_neighbours(schedule.points_xy[known_ids], known_uv,
                                      schedule.points_xy[layer_ids], found)
        return np.where(pick >= 0, layer_ids[np.maximum(pick, 0)], -1)
    got, _ = decode_layer(schedule, layer, step_images, found,
                          window_px=max(1.0, sampling_window_px(found)))
    named = np.flatnonzero(got >= 0)
    agree = check_by_neighbours(schedule.points_xy[got[named]], found[named])
    got[named[~agree]] = -1
    return got


def name_layers(schedule: Schedule, step_images: dict[int, np.ndarray | None], find_dots
                ) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray], int]:
    """Name the dots of every layer in order, each layer helped by those named before it:
    per layer the named ids, their image positions and scatter, and the count of dots that
    could not be named. `find_dots(on_index, on_image, off_image) -> (uv (N, 2), scatter
    (N,))` finds one layer's dots; a layer whose images are missing is skipped."""
    off0 = schedule.layer_frames(0)[1]
    assert schedule.frames[off0].role == ROLE_OFF
    ids, uv, scatter, rejected = [], [], [], 0
    for layer in range(len(schedule.layers)):
        idx = schedule.layer_frames(layer)
        on_i, off_i = idx[0], (off0 if len(idx) == 1 else idx[1])
        on_img, off_img = step_images.get(on_i), step_images.get(off_i)
        if on_img is None or off_img is None:
            continue
        found, spread = find_dots(on_i, on_img, off_img)
        known = np.concatenate(ids) if ids else np.zeros(0, np.int64)
        known_uv = np.concatenate(uv) if uv else np.zeros((0, 2))
        got = name_layer(schedule, layer, step_images, found, known, known_uv)
        keep = got >= 0
        rejected += int((~keep).sum())
        ids.append(got[keep])
        uv.append(found[keep])
        scatter.append(spread[keep])
    return ids, uv, scatter, rejected
