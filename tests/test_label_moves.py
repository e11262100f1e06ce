"""The local search's batched move scores (daemon/labelling/moves.py) against the search's
own one-move-at-a-time scores, and check_fit's batched neighbour medians against
np.median: the batches only decide which moves are scored one by one, so they must never
drop a move the exact score would take."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from daemon.formats.c3dio import read_c3d
from daemon.labelling.assign import (
    Compat,
    _sparse_delta,
    body_scale,
    mirror_map,
    pair_stats,
    to_marker_track,
)
from daemon.labelling.body import HAND_WEIGHT, MODULE_WEIGHT, BodyTerms
from daemon.labelling.markerset import MarkerSet
from daemon.labelling.markerset_fit import _neighbour_median
from daemon.labelling.moves import SLACK, MoveTable, changed_bounds, mirror_moves, module_moves
from daemon.synthetic.subjects import random_subject, reproportion

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cmu41():
    return MarkerSet.load(ROOT / "daemon" / "labelling" / "sets" / "cmu41.toml")


@pytest.fixture(scope="module")
def window(cmu41):
    """Tracks of a window of 85_02 performed by another body, the compatibility and the
    whole-body terms at that body's size."""
    take = read_c3d(ROOT / "fixtures" / "cmu_c3d" / "85_02.c3d").select(cmu41.labels)
    other = reproportion(take, random_subject(3))
    X = np.ascontiguousarray(other.xyz_m[300:420].transpose(1, 0, 2))
    X = X[np.isfinite(X).all(2).all(1)]
    D, S = pair_stats(X)
    return X, Compat(cmu41, D, S, body_scale(D, cmu41)), BodyTerms(X, cmu41)


def _labellings(n_tracks: int, n: int, seed: int) -> list[np.ndarray]:
    """Labellings (track -> marker) near the truth: a few labels shuffled, a few tracks
    left unlabelled (so moves meet free markers and tracks)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(6):
        lab = np.arange(n_tracks) % n
        k = rng.choice(n_tracks, 6, replace=False)
        lab[k] = lab[rng.permutation(k)]
        lab[rng.choice(n_tracks, rng.integers(0, 4), replace=False)] = -1
        out.append(lab)
    return out


def _assignment(lab: np.ndarray, n: int) -> np.ndarray:
    P = np.zeros((len(lab), n))
    got = np.nonzero(lab >= 0)[0]
    P[got, lab[got]] = 1.0
    return P


def test_each_moves_batched_score_is_its_exact_change(window, cmu41):
    """For every fixed move (mirror moves, module reorderings) and labellings with
    shuffled and missing labels: the batched bound minus the terms' bound is the
    compatibility's change `_sparse_delta` gives, which is the change of the whole
    compatibility score; moves that change nothing are -inf."""
    X, cp, terms = window
    moves = [(p, -1) for p in mirror_moves(cmu41, mirror_map(cmu41.labels))]
    moves += module_moves(terms)
    table = MoveTable(moves, cmu41.n)
    checked = 0
    for lab in _labellings(len(X), cmu41.n, seed=1):
        P = _assignment(lab, cmu41.n)
        mt = to_marker_track(P)
        terms(mt)
        G = cp.gain(P)
        est = table.bounds(cp.C, G, mt, terms, every_order=True)
        for j, (perm, _) in enumerate(moves):
            m2 = mt[perm]
            ch = np.nonzero(m2 != mt)[0]
            if not len(ch):
                assert est[j] == -np.inf
                continue
            o, nw = ch[mt[ch] >= 0], ch[m2[ch] >= 0]
            exact = _sparse_delta(cp, G, (mt[o], o), (m2[nw], nw))
            assert est[j] - terms.gain_bound(m2) == pytest.approx(exact, abs=1e-8)
            Q = np.zeros_like(P)
            got = m2 >= 0
            Q[m2[got], np.nonzero(got)[0]] = 1.0
            assert cp.score(Q) - cp.score(P) == pytest.approx(exact, abs=1e-6)
            checked += 1
    assert checked > 500


def test_candidates_keep_every_move_the_exact_score_would_take(window, cmu41):
    """Against a bar set between the moves' exact scores, the moves handed on are those
    whose exact score plus bound clears it (none lost), and without `every_order` the
    reorderings of a module whose shape fits are left out, as the search leaves them."""
    X, cp, terms = window
    moves = [(p, -1) for p in mirror_moves(cmu41, mirror_map(cmu41.labels))]
    moves += module_moves(terms)
    table = MoveTable(moves, cmu41.n)
    for lab in _labellings(len(X), cmu41.n, seed=2):
        P = _assignment(lab, cmu41.n)
        mt = to_marker_track(P)
        cur = cp.score(P) + terms(mt)
        G = cp.gain(P)
        exact = np.full(len(moves), -np.inf)
        for j, (perm, _) in enumerate(moves):
            m2 = mt[perm]
            ch = np.nonzero(m2 != mt)[0]
            if len(ch):
                o, nw = ch[mt[ch] >= 0], ch[m2[ch] >= 0]
                exact[j] = cur + _sparse_delta(cp, G, (mt[o], o), (m2[nw], nw)) \
                    + terms.gain_bound(m2)
        finite = np.sort(exact[np.isfinite(exact)])
        for best in (finite[0] - 1.0, np.median(finite), finite[-1] - 1e-3, finite[-1] + 1):
            got = set(table.candidates(cp.C, G, mt, terms, cur, best, True).tolist())
            need = set(np.nonzero(exact > best + 1e-6)[0].tolist())
            assert need <= got
            assert all(exact[j] > best + 1e-6 - 2 * SLACK for j in got)
        got = table.candidates(cp.C, G, mt, terms, cur, -np.inf, False)
        fits = [j for j, (_, k) in enumerate(moves)
                if k >= 0 and terms.cost[k] < len(terms.modules[k])]
        assert not set(fits) & set(got.tolist())
        assert set(got.tolist()) == set(np.nonzero(np.isfinite(exact))[0].tolist()) - set(fits)


def test_gain_bounds_are_gain_bound_batched(window, cmu41):
    """`BodyTerms.gain_bounds` (and `changed_bounds` for pairs of markers) equal
    `gain_bound` of each labelling they stand for."""
    X, _, terms = window
    rng = np.random.default_rng(3)
    for lab in _labellings(len(X), cmu41.n, seed=3):
        mt = to_marker_track(_assignment(lab, cmu41.n))
        terms(mt)
        a = rng.integers(0, cmu41.n, 40)
        b = rng.integers(0, cmu41.n, 40)
        b[::5] = -1
        b[b == a] = -1
        want = []
        for x, y in zip(a, b, strict=True):
            m2 = mt.copy()
            m2[x] = len(X) + 1 if m2[x] < 0 else -1           # changed, whatever it was
            if y >= 0:
                m2[y] = len(X) + 2 if m2[y] < 0 else -1
            want.append(terms.gain_bound(m2))
        assert np.allclose(changed_bounds(terms, a, b), want, atol=1e-9)


def test_batched_hand_changes_and_module_change_are_the_terms_whole_change(window, cmu41):
    """For labellings one to three markers off a scored one (tracks swapped, taken away,
    given to a free marker): the batched handedness change plus the module change is the
    terms' value recomputed from scratch minus the scored one's, and the modules' bound
    is at least what the modules gain (the local search skips on these)."""
    X, _, terms = window
    rng = np.random.default_rng(7)
    checked = 0
    for lab in _labellings(len(X), cmu41.n, seed=5):
        mt = to_marker_track(_assignment(lab, cmu41.n))
        cands = []
        for _ in range(30):
            m2 = mt.copy()
            x, y = rng.choice(cmu41.n, 2, replace=False)
            m2[x], m2[y] = mt[y], mt[x]
            if rng.random() < 0.5:
                m2[rng.integers(cmu41.n)] = -1
            if m2.tolist() != mt.tolist():
                cands.append(m2)
        base = terms(mt)
        dv, mod_bound = terms.hand_changes(np.stack(cands))
        got = [HAND_WEIGHT * d - MODULE_WEIGHT * terms.module_change(m2)
               for d, m2 in zip(dv, cands, strict=True)]
        mod_gain = [-MODULE_WEIGHT * terms.module_change(m2) for m2 in cands]
        want = [terms(m2) - base for m2 in cands]  # each call rescores from scratch
        assert np.allclose(got, want, atol=1e-9)
        assert (np.asarray(mod_bound) >= np.asarray(mod_gain) - 1e-9).all()
        checked += len(cands)
    assert checked > 100


def test_neighbour_median_is_np_median_of_the_first_finite_values():
    """Per row, the median of its first k finite values (NaN between and after them),
    as np.median of those values gives, with their count; a row with none is NaN."""
    rng = np.random.default_rng(4)
    Z = rng.random((200, 12)) * 5
    Z[rng.random(Z.shape) < 0.4] = np.nan
    Z[0] = np.nan
    Z[1, 1:] = np.nan
    med, count = _neighbour_median(Z, 6)
    for r in range(len(Z)):
        vals = Z[r][np.isfinite(Z[r])][:6]
        assert count[r] == len(vals)
        if len(vals):
            assert med[r] == np.median(vals)          # exactly: the same arithmetic
        else:
            assert np.isnan(med[r])
