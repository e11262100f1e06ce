"""Marker sets: names, near-rigid segments, expected distances; learned from a labelled take.

A marker set is what the labeller, the gap filler and the skeleton know about a body
without any data of the current take: which markers keep their shape together (segments,
"modules"), how far apart every two markers are and how much that varies,
and which handed (chiral) marker quadruples tell left from right. It is learned from one or
more labelled takes so any marker set works, and stored as TOML so a user can read and
edit it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path

import numpy as np
import tomli_w
import tomllib

from calibkit.core.errors import UserError
from calibkit.core.fileio import write_text_atomic

SHIPPED = Path(__file__).resolve().parent / "sets"  # cmu41.toml, sim_person.toml, ...
SEGMENT_SPREAD_M = 0.012   # complete-linkage cut: markers whose distances vary less stay together
MIN_SD_M = 0.002           # floor on learned spreads: measurement noise of a live rig


@dataclass
class Segment:
    name: str
    markers: list[int]            # indices into MarkerSet.labels
    shape_m: np.ndarray           # (len(markers), 3) reference shape, centred, segment frame
    parent: int = -1              # index of the parent segment, -1 for the root
    spread_m: float = 0.0         # mean spread (SD) of the segment's internal distances


@dataclass
class MarkerSet:
    labels: list[str]
    mean_m: np.ndarray            # (n, n) mean distance between markers i and j
    sd_m: np.ndarray              # (n, n) its spread (SD), floored at MIN_SD_M
    segments: list[Segment]
    chiral: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), int))  # (k, 4)
    chiral_sign: np.ndarray = field(default_factory=lambda: np.zeros(0))        # (k,) +-1
    name: str = "markerset"
    subject_sd_m: np.ndarray | None = None   # (n, n) spread of the mean between takes
    # swap witnesses: quads (i, j, a, b) whose signed volume flips when the close markers
    # i and j swap labels (which their distances may not show), sign and typical size
    pair_quads: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), int))
    pair_sign: np.ndarray = field(default_factory=lambda: np.zeros(0))
    pair_volume: np.ndarray = field(default_factory=lambda: np.zeros(0))   # 6V, m^3

    def __post_init__(self) -> None:
        if self.subject_sd_m is None:
            self.subject_sd_m = np.zeros_like(self.mean_m)

    @property
    def n(self) -> int:
        return len(self.labels)

    def segment_of(self) -> np.ndarray:
        """segment index of each marker."""
        out = np.full(self.n, -1, int)
        for s, seg in enumerate(self.segments):
            out[seg.markers] = s
        return out

    def index(self, names: list[str]) -> list[int]:
        missing = [n for n in names if n not in self.labels]
        if missing:
            raise UserError(f"marker(s) {', '.join(missing)} are not in marker set {self.name}")
        return [self.labels.index(n) for n in names]

    # ------------------------------------------------------------------ TOML
    def to_toml(self) -> str:
        doc = {
            "name": self.name,
            "markers": list(self.labels),
            "segment": [{"name": s.name, "markers": [self.labels[i] for i in s.markers],
                         "parent": self.segments[s.parent].name if s.parent >= 0 else "",
                         "spread_mm": round(1000 * s.spread_m, 3),
                         "shape_mm": [[round(1000 * float(v), 2) for v in row]
                                      for row in s.shape_m]}
                        for s in self.segments],
            "distances": {"mean_mm": [[round(1000 * float(v), 2) for v in row]
                                      for row in self.mean_m],
                          "sd_mm": [[round(1000 * float(v), 2) for v in row]
                                    for row in self.sd_m],
                          "between_takes_sd_mm": [[round(1000 * float(v), 2) for v in row]
                                                  for row in self.subject_sd_m]},
            "chiral": [{"markers": [self.labels[i] for i in q], "sign": int(s)}
                       for q, s in zip(self.chiral, self.chiral_sign, strict=True)],
            "swap_witness": [{"markers": [self.labels[i] for i in q], "sign": int(s),
                              "volume_cm3": round(1e6 * float(v), 4)}
                             for q, s, v in zip(self.pair_quads, self.pair_sign,
                                                self.pair_volume, strict=True)],
        }
        return tomli_w.dumps(doc)

    def save(self, path: str | Path) -> None:
        write_text_atomic(path, self.to_toml())

    @staticmethod
    def load(path: str | Path) -> MarkerSet:
        path = Path(path)
        try:
            doc = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise UserError(f"marker set {path} does not exist") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise UserError(f"{path} is not a valid TOML marker set: {exc}") from None
        try:
            labels = [str(v) for v in doc["markers"]]
            idx = {n: i for i, n in enumerate(labels)}
            mean = np.asarray(doc["distances"]["mean_mm"], float) / 1000
            sd = np.asarray(doc["distances"]["sd_mm"], float) / 1000
            between = np.asarray(doc["distances"].get("between_takes_sd_mm", 0.0 * sd),
                                 float) / 1000
            names = [s["name"] for s in doc["segment"]]
            segs = [Segment(s["name"], [idx[m] for m in s["markers"]],
                            np.asarray(s["shape_mm"], float).reshape(-1, 3) / 1000,
                            names.index(s["parent"]) if s.get("parent") else -1,
                            float(s.get("spread_mm", 0.0)) / 1000)
                    for s in doc["segment"]]
            chiral = np.array([[idx[m] for m in c["markers"]] for c in doc.get("chiral", [])],
                              int).reshape(-1, 4)
            sign = np.array([c["sign"] for c in doc.get("chiral", [])], float)
            wit = doc.get("swap_witness", [])
            pq = np.array([[idx[m] for m in c["markers"]] for c in wit], int).reshape(-1, 4)
            ps = np.array([c["sign"] for c in wit], float)
            pv = np.array([c["volume_cm3"] for c in wit], float) / 1e6
        except (KeyError, ValueError, TypeError) as exc:
            raise UserError(f"{path}: marker set is missing or has a bad entry ({exc}); "
                            f"write one with `mocapd markerset learn`") from None
        n = len(labels)
        if mean.shape != (n, n) or sd.shape != (n, n):
            raise UserError(f"{path}: distance tables must be {n}x{n} for {n} markers")
        for s in segs:
            if len(s.markers) != len(s.shape_m):
                raise UserError(f"{path}: segment {s.name} has {len(s.markers)} markers but "
                                f"{len(s.shape_m)} shape rows")
        if between.shape != (n, n):
            between = np.zeros((n, n))
        return MarkerSet(labels, mean, np.maximum(sd, MIN_SD_M), segs, chiral, sign,
                         str(doc.get("name", path.stem)), between, pq, ps, pv)


# ---------------------------------------------------------------------- by name


def shipped_sets() -> list[str]:
    """Names of the marker sets that ship with mocapd (`--markerset cmu41`)."""
    return sorted(p.stem for p in SHIPPED.glob("*.toml"))


def resolve(value: str | Path, base: Path | None = None) -> Path:
    """A marker set given by a user to a file: a shipped set's name (no folder, no
    .toml), else a path, relative to `base` (the configuration's folder) if given."""
    text = str(value)
    if "/" not in text and not text.endswith(".toml") and (SHIPPED / f"{text}.toml").exists():
        return SHIPPED / f"{text}.toml"
    return Path(text) if base is None else base / text


def open_set(value: str | Path, base: Path | None = None) -> MarkerSet:
    """The marker set a user named (a shipped set's name or a file); UserError in one
    line if it is missing, a folder, malformed or too small to label with."""
    path = resolve(value, base)
    if path.is_dir():
        raise UserError(f"marker set {path} is a folder, not a TOML file")
    if not path.exists():
        raise UserError(f"marker set {value} does not exist (a .toml file, or a shipped "
                        f"set: {', '.join(shipped_sets())})")
    ms = MarkerSet.load(path)
    if ms.n < 3:
        raise UserError(f"marker set {path} has {ms.n} markers; labelling needs at least 3")
    return ms


# ---------------------------------------------------------------------- learning


def _pair_stats(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sum, sum of squares and count of every pairwise distance over frames (NaN-aware)."""
    d = np.linalg.norm(xyz[:, :, None] - xyz[:, None, :], axis=3)
    ok = np.isfinite(d)
    d0 = np.where(ok, d, 0.0)
    return d0.sum(0), (d0 * d0).sum(0), ok.sum(0)


def rigid_align(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising |R A + t - B| (Kabsch, no scaling); A and B are (k, 3)."""
    ca, cb = A.mean(0), B.mean(0)
    H = (A - ca).T @ (B - cb)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    D = np.diag([1.0, 1.0, d])
    R = Vt.T @ D @ U.T
    return R, cb - R @ ca


def _mean_shape(pts: np.ndarray) -> np.ndarray:
    """Procrustes mean of a segment's shapes over frames (frames, k, 3) -> (k, 3), centred."""
    ok = np.isfinite(pts).all(axis=(1, 2))
    pts = pts[ok]
    if len(pts) == 0:
        raise UserError("a segment is never fully visible in the learning take")
    ref = pts[len(pts) // 2] - pts[len(pts) // 2].mean(0)
    step = max(1, len(pts) // 400)
    sample = pts[::step]
    for _ in range(2):
        acc = np.zeros_like(ref)
        for P in sample:
            if len(ref) >= 3:
                R, t = rigid_align(P, ref)
                acc += P @ R.T + t
            else:
                acc += P - P.mean(0)
        ref = acc / len(sample)
        ref -= ref.mean(0)
    return ref


def _segment_names(labels: list[str], members: list[int]) -> str:
    return "+".join(labels[i] for i in members[:3]) + ("+..." if len(members) > 3 else "")


def learn(takes: list, cut_m: float = SEGMENT_SPREAD_M, name: str = "markerset",
          n_chiral: int = 24) -> MarkerSet:
    """Learn a marker set from labelled takes (c3dio.Take) that share their labels."""
    # deferred on purpose: loads SciPy's clustering, SciPy's sparse graphs... only where used
    from scipy.cluster.hierarchy import fcluster, linkage
    from scipy.sparse.csgraph import minimum_spanning_tree
    from scipy.spatial.distance import squareform

    if not takes:
        raise UserError("no labelled take to learn from")
    labels = list(takes[0].labels)
    xyzs = []
    for t in takes:
        missing = [n for n in labels if n not in t.labels]
        if missing:
            raise UserError(f"take {t.meta.get('source', '')} lacks marker(s) "
                            f"{', '.join(missing)}")
        xyzs.append(t.select(labels).xyz_m)
    n = len(labels)
    # Spreads are pooled within takes (the body's own motion); between-take differences
    # (another subject, markers placed elsewhere) are kept apart in subject_sd_m.
    means, vars_, counts = [], [], []
    for x in xyzs:
        a, b, c = _pair_stats(x)
        m = a / np.maximum(c, 1)
        means.append(np.where(c > 0, m, np.nan))
        vars_.append(np.maximum(b / np.maximum(c, 1) - m ** 2, 0.0))
        counts.append(c)
    cnt = np.sum(counts, axis=0)
    if (cnt + np.eye(n) == 0).any():
        i, j = np.argwhere(cnt + np.eye(n) == 0)[0]
        raise UserError(f"markers {labels[i]} and {labels[j]} are never seen together in the "
                        "learning take(s)")
    w = np.array(counts, float)
    mean = np.nansum(np.nan_to_num(np.array(means)) * w, axis=0) / np.maximum(cnt, 1)
    sd = np.sqrt(np.sum(np.array(vars_) * w, axis=0) / np.maximum(cnt, 1))
    between = np.sqrt(np.sum(w * (np.nan_to_num(np.array(means)) - mean) ** 2, axis=0)
                      / np.maximum(cnt, 1))
    np.fill_diagonal(mean, 0.0)
    np.fill_diagonal(sd, 0.0)
    np.fill_diagonal(between, 0.0)

    # Segments: complete-linkage clusters of the distance spread.
    Z = linkage(squareform(sd, checks=False), "complete")
    cluster = fcluster(Z, cut_m, "distance")
    allx = np.concatenate(xyzs, axis=0)
    groups = [list(np.nonzero(cluster == c)[0]) for c in np.unique(cluster)]
    groups.sort(key=lambda g: (-len(g), g[0]))
    segs: list[Segment] = []
    for g in groups:
        spread = float(sd[np.ix_(g, g)][np.triu_indices(len(g), 1)].mean()) if len(g) > 1 \
            else 0.0
        segs.append(Segment(_segment_names(labels, g), [int(i) for i in g],
                            _mean_shape(allx[:, g]), -1, spread))

    # Parent links: a spanning tree over the segments by the steadiest distance between them,
    # rooted at the largest, steadiest segment (the pelvis on a body).
    k = len(segs)
    link = np.zeros((k, k))
    for a in range(k):
        for b in range(a + 1, k):
            v = sd[np.ix_(segs[a].markers, segs[b].markers)].min() + 1e-6
            link[a, b] = link[b, a] = v
    tree = minimum_spanning_tree(link).toarray()
    tree = (tree + tree.T) > 0
    centrality = mean.mean(1)
    root = min(range(k), key=lambda s: (len(segs[s].markers) < 3,
                                         float(centrality[segs[s].markers].mean())))
    seen = {root}
    frontier = [root]
    while frontier:
        a = frontier.pop()
        for b in np.nonzero(tree[a])[0]:
            if b not in seen:
                segs[b].parent = a
                seen.add(int(b))
                frontier.append(int(b))

    chiral, sign = _learn_chiral(allx, sd, n_chiral)
    pq, ps, pv = _learn_swap_witnesses(allx, mean, sd)
    return MarkerSet(labels, mean, np.maximum(sd, MIN_SD_M), segs, chiral, sign, name,
                     between, pq, ps, pv)


def signed_volume(x: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Signed volume (times 6) of tetrahedra quads (k, 4) of points x (..., n, 3)."""
    a = x[..., quads[:, 0], :]
    b = x[..., quads[:, 1], :] - a
    c = x[..., quads[:, 2], :] - a
    d = x[..., quads[:, 3], :] - a
    return np.einsum("...i,...i->...", np.cross(b, c), d)


def _learn_chiral(allx: np.ndarray, sd: np.ndarray, n_keep: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadruples of steady markers whose signed volume never changes sign: they tell a body
    from its mirror image, which distances alone cannot."""
    rng = np.random.default_rng(0)
    n = allx.shape[1]
    steady = np.argsort(sd.mean(1))[: max(8, n // 2)]
    cand = np.array([rng.choice(steady, 4, replace=False) for _ in range(3000)])
    step = max(1, len(allx) // 300)
    vol = signed_volume(allx[::step], cand)            # (frames, k)
    ok = np.isfinite(vol)
    med = np.nanmedian(vol, axis=0)
    consistent = np.where(ok, np.sign(vol) == np.sign(med), True).all(0)
    # score: smallest |volume| over the take (robust margin)
    margin = np.nanmin(np.abs(vol), axis=0)
    score = np.where(consistent, margin, -1.0)
    order = np.argsort(-score)
    keep = [i for i in order[:n_keep] if score[i] > 0]
    return cand[keep].astype(int), np.sign(med[keep])


def _learn_swap_witnesses(allx: np.ndarray, mean: np.ndarray, sd: np.ndarray,
                          close_m: float = 0.25) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each pair of markers close enough to be confused, two steady neighbours a, b
    such that the tetrahedron (i, j, a, b) keeps its handedness over the takes: swapping
    i and j negates its volume, even where the distances are symmetric (a foot's toe and
    fifth metatarsal seen from heel and ankle)."""
    n = len(mean)
    step = max(1, len(allx) // 300)
    x = allx[::step]
    quads, signs, vols = [], [], []
    s2 = sd.copy()
    np.fill_diagonal(s2, np.inf)
    for i in range(n):
        for j in range(i + 1, n):
            if mean[i, j] >= close_m:
                continue
            cand = [int(a) for a in np.argsort(s2[i] + s2[j])[:6] if a not in (i, j)]
            best = None
            for a, b in combinations(cand, 2):
                q = np.array([[i, j, a, b]])
                v = signed_volume(x, q)[:, 0]
                v = v[np.isfinite(v)]
                if len(v) < 10:
                    continue
                med = float(np.median(v))
                if not (np.sign(v) == np.sign(med)).all():
                    continue
                # a large volume with steady witnesses: far or loose ones flip by motion
                spread = sd[i, a] + sd[i, b] + sd[j, a] + sd[j, b] + 0.01
                margin = float(np.abs(v).min()) / spread
                if best is None or margin > best[0]:
                    best = (margin, [i, j, a, b], np.sign(med), abs(med))
            if best is not None:
                quads.append(best[1])
                signs.append(best[2])
                vols.append(best[3])
    return (np.array(quads, int).reshape(-1, 4), np.array(signs, float),
            np.array(vols, float))
