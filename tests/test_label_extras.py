"""Markers the set lacks (issue 29): a real CMU take performed by another body wearing three
extra markers (daemon/synthetic/subjects.py), labelled with a correct labelled start and
from the set alone; scored against the simulator's truth, the extras' points must stay
unlabelled."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from daemon.formats.c3dio import read_c3d
from daemon.labelling.extras import unlabelled_tracks, with_extras
from daemon.labelling.markerset import MarkerSet
from daemon.labelling.modules import rigid_modules
from daemon.labelling.offline import label_take
from daemon.labelling.start import window_start
from daemon.synthetic.labelling import hide_spans, points_with_ghosts
from daemon.synthetic.subjects import markers_of, random_subject, reproportion

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "fixtures" / "cmu_c3d"


@pytest.fixture(scope="module")
def cmu41():
    return MarkerSet.load(ROOT / "daemon" / "labelling" / "sets" / "cmu41.toml")


def _pattern(cmu41, seed):
    """85_02 by body `seed` with 3 extra markers, 10 % hidden, 2 ghosts a frame: the
    take (its truth), the points, each point's marker of the set (-1 none) and whether
    it is an extra marker's."""
    take = read_c3d(DATA / "85_02.c3d").select(cmu41.labels)
    t = hide_spans(reproportion(take, random_subject(seed, extra_markers=3)), 0.1, seed=seed)
    pts, mk = points_with_ghosts(t, 2, seed=seed)
    to_set = markers_of(t, cmu41.labels)
    truth = np.where(mk >= 0, to_set[np.maximum(mk, 0)], -1)
    return t, pts, truth, mk >= cmu41.n


def _per_frame(pts, values):
    order = np.argsort(pts.frame, kind="stable")
    _, starts = np.unique(pts.frame[order], return_index=True)
    return np.split(values[order], starts[1:])


def _figures(pts, truth, extra, labels, first=10):
    want = np.concatenate(_per_frame(pts, truth)[first:])
    ex = np.concatenate(_per_frame(pts, extra)[first:])
    got = np.concatenate(labels[first:])
    real = want >= 0
    return ((got[real] == want[real]).mean(), ((got[real] >= 0) & (got[real] != want[real])
                                               ).mean(), int(ex.sum()), int((got[ex] >= 0).sum()))


def test_a_starts_unlabelled_steady_points_become_markers_of_their_own(cmu41):
    """In 10 labelled start frames the three extra markers are the points no label
    holds that last (the ghosts do not): each found as one track, and added to the set
    under the name of the set's marker nearest it, with that marker's spreads, held to
    it as steadily as it is held to its steadiest neighbour."""
    t, pts, truth, extra = _pattern(cmu41, 0)
    _, per = pts.split()
    sx = t.select(cmu41.labels).xyz_m[:10]
    X = unlabelled_tracks(per[:10], sx, 0.006, cmu41)
    want = t.xyz_m[:10, cmu41.n:].transpose(1, 0, 2)                   # (3, 10, 3)
    assert len(X) == np.isfinite(want).all(2).any(1).sum() == 3
    for x in X:
        d = np.nanmin(np.linalg.norm(want - x[None], axis=2), axis=1)   # to each extra
        assert (d < 1e-9).sum() == 1
    ms2 = with_extras(cmu41, sx, X)
    assert ms2.n == cmu41.n + 3 and ms2.labels[:cmu41.n] == cmu41.labels
    for e in range(3):
        near = cmu41.labels.index(ms2.labels[cmu41.n + e].split("+")[0])
        d = np.linalg.norm(X[e][:, None] - sx, axis=2)
        assert near == int(np.nanargmin(np.nanmean(d, axis=0)))
        others = np.setdiff1d(np.arange(cmu41.n), [near])
        assert np.allclose(ms2.sd_m[cmu41.n + e, others], cmu41.sd_m[near, others])
    assert sum(len(m) for m in rigid_modules(ms2)) > sum(len(m) for m in rigid_modules(cmu41))


def test_a_correct_start_leaves_markers_the_set_lacks_unlabelled(cmu41):
    """85_02 by body 0 wearing three extra markers, with 10 correctly labelled start
    frames: before, the tracker gave the extra marker beside CLAV CLAV's name and the
    one beside LFHD LFHD's whenever those were hidden (390 of 2350 extra points named,
    98.40 % right). The start's unlabelled steady points are tracked as markers of their
    own now: none is named (99.81 % right in the run that set these bounds)."""
    t, pts, truth, extra = _pattern(cmu41, 0)
    _, _, labels = label_take(pts, cmu41, t.rate_hz, t, 10)
    right, wrong, n_extra, named = _figures(pts, truth, extra, labels)
    assert n_extra > 2000
    assert named <= 0.005 * n_extra
    assert right >= 0.995 > 0.9840
    assert wrong < 0.002


def test_the_set_alone_leaves_markers_it_lacks_unlabelled(cmu41):
    """85_02 by body 3 wearing three extra markers, from the set alone: before, the
    start's assignment named two of them (every labelled pair adds to its score) and
    pushed names along (88.6 % of the window's points right), and the take ended
    85.1 % right and 8.9 % wrong with 1148 of 2227 extra points named. A track whose
    name its rigid neighbours do not vouch for is left out and the rest assigned again:
    the extras stay unlabelled in the window and through the take."""
    t, pts, truth, extra = _pattern(cmu41, 3)
    _, per = pts.split()
    unfit = []
    w0, labels, _ = window_start(per, cmu41, unfit=unfit)
    want = np.concatenate(_per_frame(pts, truth)[w0:w0 + len(labels)])
    ex = np.concatenate(_per_frame(pts, extra)[w0:w0 + len(labels)])
    got = np.concatenate(labels)
    real = want >= 0
    assert (got[ex] < 0).all()
    assert (got[real] == want[real]).mean() >= 0.95 > 0.886
    assert len(unfit) >= 1
    _, _, labels = label_take(pts, cmu41, t.rate_hz)
    right, wrong, n_extra, named = _figures(pts, truth, extra, labels)
    assert named <= 0.01 * n_extra
    assert right >= 0.94 > 0.8515
    assert wrong < 0.04


def test_a_marker_the_start_leaves_unlabelled_is_no_extra(cmu41):
    """A start that leaves a marker of the set unlabelled although its point is there (a
    person labelled all but one) says nothing about that point: for each marker of body
    0 in turn, its track in the start frames sits where the set puts that marker and is
    not taken for a marker the set lacks (with one SD allowed instead of two, LSHN and
    RSHN were; an extra beside the marker left out may now be left to the tracker too);
    the take then names it (RKNE here)."""
    t, pts, truth, _ = _pattern(cmu41, 0)
    _, per = pts.split()
    full = t.select(cmu41.labels)
    tried = 0
    for j in range(cmu41.n):
        sx = full.xyz_m[:10].copy()
        if not np.isfinite(sx[:, j]).all():
            continue
        sx[:, j] = np.nan
        tried += 1
        X = unlabelled_tracks(per[:10], sx, 0.006, cmu41)
        d = np.linalg.norm(X - full.xyz_m[:10, j][None], axis=2)
        assert not (np.nanmin(d, axis=1) < 1e-9).any(), cmu41.labels[j]
    assert tried >= 30
    j = cmu41.labels.index("RKNE")
    xyz = full.xyz_m.copy()
    xyz[:10, j] = np.nan
    start = type(full)(full.labels, xyz, full.rate_hz, full.first_frame)
    _, _, labels = label_take(pts, cmu41, t.rate_hz, start, 10)
    want = np.concatenate(_per_frame(pts, truth)[10:])
    got = np.concatenate(labels[10:])
    mine = want == j
    assert (got[mine] == j).mean() >= 0.95
