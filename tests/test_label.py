"""Labelling the real CMU takes with their labels stripped and points shuffled per frame."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from daemon.formats.c3dio import (
    Points,
    Take,
    read_c3d,
    read_labelled_csv,
    write_points_csv,
    write_take,
)
from daemon.labelling.labeller import Labeller
from daemon.labelling.markerset import MarkerSet, learn
from daemon.labelling.offline import label_take
from daemon.labelling.single import chirality_votes, initial_labels
from daemon.synthetic.labelling import hide_spans, points_with_ghosts, score

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "fixtures" / "cmu_c3d"
FRAMES = 360          # 3 s of each take keeps the tests fast


@pytest.fixture(scope="module")
def cmu41():
    return MarkerSet.load(ROOT / "daemon" / "labelling" / "sets" / "cmu41.toml")


def _excerpt(name, labels, start=0):
    t = read_c3d(DATA / name).select(labels)
    return Take(t.labels, t.xyz_m[start:start + FRAMES], t.rate_hz, t.first_frame + start)


@pytest.fixture(scope="module")
def walk(cmu41):
    return _excerpt("01_01.c3d", cmu41.labels)


@pytest.fixture(scope="module")
def acro(cmu41):
    return _excerpt("85_02.c3d", cmu41.labels, start=300)


def test_gap_free_with_labelled_start_frames_is_exact(acro, cmu41):
    pts, truth = points_with_ghosts(acro, 0, seed=1)
    _, _, labels = label_take(pts, cmu41, start_labels=acro, start_frames=10)
    s = score(pts, truth, labels, 10)
    assert s["correct"] == 1.0


def test_gap_free_from_the_template_alone(walk, cmu41):
    pts, truth = points_with_ghosts(walk, 0, seed=2)
    _, _, labels = label_take(pts, cmu41)
    assert score(pts, truth, labels)["correct"] >= 0.99


def test_other_subjects_marker_set_with_labelled_start_frames(walk, acro):
    """A marker set learned on 85_02 only labels 01_01 (another person) given a labelled
    start: the distances are re-learned from the seed frames."""
    ms = learn([read_c3d(DATA / "85_02.c3d")])
    pts, truth = points_with_ghosts(walk, 0, seed=3)
    _, _, labels = label_take(pts, ms, start_labels=walk, start_frames=10)
    assert score(pts, truth, labels, 10)["correct"] >= 0.999


def test_other_subjects_marker_set_from_the_template_alone(walk):
    """No labelled frame and a marker set learned on another person: the tolerance for
    another body's distances (15 %) still finds a start frame, and tracking learns the
    rest (one marker of 41 may stay wrong)."""
    ms = learn([read_c3d(DATA / "85_02.c3d")])
    pts, truth = points_with_ghosts(walk, 0, seed=2)
    _, _, labels = label_take(pts, ms)
    assert score(pts, truth, labels)["correct"] >= 0.95


@pytest.mark.parametrize("which", ["walk", "acro"])
def test_hidden_spans_and_ghosts(which, walk, acro, cmu41):
    """20 % of marker-frames hidden in spans of 0.1-1 s and 3 ghosts per frame: the issue's
    target is >= 97 % on whole takes; on these 3 s excerpts we hold >= 95 %, and at least
    95 % of the ghosts must stay unlabelled."""
    take = walk if which == "walk" else acro
    hidden = hide_spans(take, 0.2, seed=5)
    pts, truth = points_with_ghosts(hidden, 3, seed=5)
    out, conf, labels = label_take(pts, cmu41, start_labels=hidden, start_frames=10)
    s = score(pts, truth, labels, 10)
    assert s["correct"] >= 0.95, s
    assert s["ghosts_rejected"] >= 0.95, s
    # every labelled sample sits where the truth has that marker (or is a rare ghost hit)
    both = out.visible & hidden.visible
    err = np.linalg.norm(out.xyz_m[both] - hidden.xyz_m[both], axis=1)
    assert (err < 1e-9).mean() >= 0.95
    assert conf.shape == (take.n_frames,) and 0.0 <= conf.min() and conf.max() <= 1.0


def test_initial_labels_and_handedness_votes(walk, cmu41):
    """One frame labelled from the marker set alone; and the handedness votes that pick
    between a labelling and its left/right swapped twin (equal distances on a symmetric
    body) favour the true one."""
    x = walk.xyz_m[100]
    perm = np.random.default_rng(0).permutation(len(x))
    lab = initial_labels(x[perm], cmu41)
    assert (lab == perm).mean() >= 0.95
    names = cmu41.labels
    flip = {"L": "R", "R": "L"}
    swapped = np.array([names.index(flip[n[0]] + n[1:])
                        if n[0] in flip and flip[n[0]] + n[1:] in names else i
                        for i, n in enumerate(names)])
    truth_point = np.argsort(perm)                  # marker -> point index
    assert chirality_votes(x[perm], cmu41, truth_point) >= 0.9 * len(cmu41.chiral)
    assert chirality_votes(x[perm], cmu41, truth_point[swapped]) <= -0.5 * len(cmu41.chiral)


@pytest.mark.kernels  # a Labeller's compiled kernels
def test_per_frame_api(walk, cmu41):
    lab = Labeller(cmu41, rate_hz=walk.rate_hz)
    lab.start_from_labelled(walk.xyz_m[0])
    rng = np.random.default_rng(4)
    for f in range(1, 30):
        ghosts = rng.uniform(-1, 1, (2, 3)) + np.nanmean(walk.xyz_m[f], axis=0)
        pts = np.concatenate([walk.xyz_m[f], ghosts])
        perm = rng.permutation(len(pts))
        labels, conf = lab.update(pts[perm])
        want = np.r_[np.arange(cmu41.n), -1, -1][perm]
        assert labels.shape == (len(pts),) and conf.shape == (len(pts),)
        assert np.array_equal(labels, want)
        assert (conf[labels >= 0] > 0.5).all() and (conf[labels < 0] == 0).all()
    assert np.allclose(lab.positions, walk.xyz_m[29])


def test_cli_label_csv(tmp_path, mocapd_cli, walk, cmu41):
    short = Take(walk.labels, walk.xyz_m[:120], walk.rate_hz, 0)
    write_points_csv(tmp_path / "pts.csv", Points.from_take(short, seed=6))
    r = mocapd_cli("label", tmp_path / "pts.csv", "--markerset",
                   ROOT / "daemon" / "labelling" / "sets" / "cmu41.toml", "--out",
                   tmp_path / "lab.csv", "--json", tmp_path / "lab.json", "--rate", "120")
    assert r.code == 0, r.err
    back = read_labelled_csv(tmp_path / "lab.csv")
    back = back.select(cmu41.labels)
    assert np.allclose(back.xyz_m, short.xyz_m, atol=2e-6)   # CSV keeps micrometres
    r = mocapd_cli("label", tmp_path / "pts.csv", "--markerset", tmp_path / "none.toml",
                   "--out", tmp_path / "x.csv")
    assert r.code == 2 and "does not exist" in r.err
    r = mocapd_cli("label", tmp_path / "pts.csv", "--markerset",
                   ROOT / "daemon" / "labelling" / "sets" / "cmu41.toml", "--out",
                   tmp_path / "x.csv", "--start-frames", "5")
    assert r.code == 2 and "--start-labels" in r.err


def test_cli_label_from_labelled_start_frames(tmp_path, mocapd_cli, acro):
    """`--start-labels TAKE --start-frames N` takes the first N frames' labels from TAKE
    and labels the rest against the truth; the shipped set is named as `cmu41`; the
    former names of the two options (--seed, --seed-frames) still do the same."""
    hidden = hide_spans(Take(acro.labels, acro.xyz_m[:240], acro.rate_hz, 0), 0.1, seed=3)
    pts, truth = points_with_ghosts(hidden, 2, seed=3)
    write_points_csv(tmp_path / "pts.csv", pts)
    write_take(tmp_path / "start.c3d", hidden)
    outs = []
    for opts in (("--start-labels", "--start-frames"), ("--seed", "--seed-frames")):
        out = tmp_path / f"lab{len(outs)}.csv"
        r = mocapd_cli("label", tmp_path / "pts.csv", "--markerset", "cmu41", "--out", out,
                       opts[0], tmp_path / "start.c3d", opts[1], "10", "--rate", "120")
        assert r.code == 0, r.err
        back = read_labelled_csv(out).select(acro.labels)
        outs.append(back.xyz_m)
    assert np.array_equal(outs[0], outs[1], equal_nan=True)
    # nearly every point is at its true marker's place in the labelled take
    f0 = back.first_frame
    got = outs[0][10 - f0:]
    want = hidden.xyz_m[10:10 - f0 + len(outs[0])]
    seen = np.isfinite(want).all(2)
    right = np.isfinite(got).all(2) & seen & (np.linalg.norm(got - want, axis=2) < 1e-5)
    assert right.sum() >= 0.97 * seen.sum()


# ---------------------------------------------------------------------- rigid modules


def test_rigid_fit_tells_a_module_from_its_mirror_image(cmu41, acro):
    """The left foot's tetrahedron (ankle, heel, 5th metatarsal, toe): the labels of the
    two forefoot markers swapped keep the heel and ankle distances nearly (equal on this
    subject) but turn the tetrahedron inside out; the proper rigid fit sees it."""
    from daemon.labelling.modules import rigid_modules
    from daemon.labelling.modules import rigid_residuals as _rigid_residuals
    foot = next(m for m in rigid_modules(cmu41) if cmu41.labels.index("LTOE") in m)
    assert sorted(cmu41.labels[i] for i in foot) == ["LANK", "LHEE", "LMT5", "LTOE"]
    x = acro.xyz_m[:, foot]
    ok = np.isfinite(x).all(axis=(1, 2))
    ref, later = x[ok][0], x[ok][-1]
    swap = [cmu41.labels[i] for i in foot]
    perm = np.arange(len(foot))
    a, b = swap.index("LMT5"), swap.index("LTOE")
    perm[[a, b]] = perm[[b, a]]
    w = np.ones((2, len(foot)))
    r2 = _rigid_residuals(ref, np.stack([later, later[perm]]), w, True)
    assert np.sqrt(r2[0].max()) < 0.015                 # the same foot, seconds later
    assert np.sqrt(r2[1].max()) > 0.025                 # its labels swapped


@pytest.mark.parametrize("pattern", [0, 4])
def test_modules_found_again_after_long_occlusions(cmu41, pattern):
    """The first 5 s of 85_02 (acrobatics) with two of the benchmark's occlusion patterns
    (20 % hidden, 3 ghosts per frame): in pattern 0 the left foot's LMT5 and LTOE are
    hidden together for 0.15 s and LMT5 for 0.75 s more; marker by marker, the toe was
    taken for LMT5 and a ghost for the toe (97.9 %); re-identified by the foot's rigid
    fit they are right (99.1 %). Pattern 4: 98.0 % -> 99.6 %."""
    full = read_c3d(DATA / "85_02.c3d").select(cmu41.labels)
    hidden = hide_spans(full, 0.2, seed=pattern)
    part = Take(hidden.labels, hidden.xyz_m[:600], hidden.rate_hz, hidden.first_frame)
    pts, truth = points_with_ghosts(part, 3, seed=pattern)
    _, _, labels = label_take(pts, cmu41, start_labels=part, start_frames=10)
    assert score(pts, truth, labels, 10)["correct"] >= 0.988


@pytest.mark.parametrize(("name", "pattern", "before"), [
    ("85_02.c3d", 13, 93.4), ("85_02.c3d", 21, 91.6), ("85_02.c3d", 29, 95.4),
    ("01_01.c3d", 18, 88.9)])
def test_hard_occlusion_patterns(cmu41, name, pattern, before):
    """Whole takes with occlusion patterns that once went wrong for hundreds of frames
    (`before`, % labelled right), each for a reason now handled: a shoulder marker taken
    for the sternum by a 3-point fit of the trunk (01_01, 18); a toe never seen in the
    seed frames, then taken for the 5th metatarsal (85_02, 13: the marker set's shape of
    the foot, with its handedness); a ghost taken for the shank made two foot markers
    look swapped (85_02, 21: markers found in this frame witness no swap); a forearm
    hidden whole, with its elbow (85_02, 29: found again as a whole by its shape)."""
    full = read_c3d(DATA / name).select(cmu41.labels)
    hidden = hide_spans(full, 0.2, seed=pattern)
    pts, truth = points_with_ghosts(hidden, 3, seed=pattern)
    _, _, labels = label_take(pts, cmu41, full.rate_hz, start_labels=hidden, start_frames=10)
    assert score(pts, truth, labels, 10)["correct"] >= 0.98


def test_forearm_hidden_whole_is_found_again(cmu41):
    """The right forearm (elbow, forearm, both wrists, finger) hidden whole for 0.6 s of
    acrobatics, with 3 ghosts per frame: its predictions are far off when it shows again
    (the arm swung), so marker by marker 4 in 10 of the next frames had one wrong; found as a
    whole by the shape of its points, every frame from 5 frames after is right."""
    full = read_c3d(DATA / "85_02.c3d").select(cmu41.labels)
    arm = [cmu41.labels.index(x) for x in ("RELB", "RFRM", "RWRA", "RWRB", "RFIN")]
    xyz = full.xyz_m[:732].copy()
    xyz[600:672, arm] = np.nan
    take = Take(full.labels, xyz, full.rate_hz, full.first_frame)
    pts, truth = points_with_ghosts(take, 3, seed=5)
    _, _, labels = label_take(pts, cmu41, full.rate_hz, start_labels=take, start_frames=10)
    order = np.argsort(pts.frame, kind="stable")
    per_truth = np.split(truth[order], np.unique(pts.frame[order], return_index=True)[1][1:])
    for f in range(677, 732):
        for j in arm:
            got = labels[f][per_truth[f] == j]
            assert got.size == 1 and got[0] == j, (f, cmu41.labels[j])


def test_wrist_markers_taken_for_each_other_are_set_right(cmu41):
    """01_01, occlusion pattern 23: the left wrist's two markers show again one at a time
    beside the finger marker alone (forearm marker hidden) and are taken for each other;
    when the forearm marker shows, the module's fit with the two decided again puts them
    right (before, they stayed swapped for 400 frames)."""
    full = read_c3d(DATA / "01_01.c3d").select(cmu41.labels)
    hidden = hide_spans(full, 0.2, seed=23)
    part = Take(hidden.labels, hidden.xyz_m[:600], hidden.rate_hz, hidden.first_frame)
    pts, truth = points_with_ghosts(part, 3, seed=23)
    _, _, labels = label_take(pts, cmu41, full.rate_hz, start_labels=part, start_frames=10)
    order = np.argsort(pts.frame, kind="stable")
    per_truth = np.split(truth[order], np.unique(pts.frame[order], return_index=True)[1][1:])
    wrist = [cmu41.labels.index(x) for x in ("LWRA", "LWRB")]
    for f in range(520, 600):
        for j in wrist:
            got = labels[f][per_truth[f] == j]
            assert got.size == 0 or got[0] == j, (f, cmu41.labels[j], got)


def test_module_order_from_the_marker_sets_shape(cmu41, acro):
    """A foot's labels turned around its tetrahedron are put back by the marker set's
    shape of the foot (with its handedness); the flat pelvis with left and right swapped
    is left alone: turned over, its swapped labels fit as well (a mirror twin)."""
    from daemon.labelling.modules import better_order as _better_order
    from daemon.labelling.modules import module_template as _module_template
    from daemon.labelling.modules import rigid_modules
    frame = acro.xyz_m[0]
    for names, order, expect in ((["LANK", "LHEE", "LMT5", "LTOE"], [2, 3, 1, 0], True),
                                 (["LFWT", "RFWT", "LBWT", "RBWT"], [1, 0, 3, 2], False)):
        module = next(m for m in rigid_modules(cmu41) if cmu41.labels.index(names[0]) in m)
        assert sorted(cmu41.labels[i] for i in module) == sorted(names)
        X = frame[module]
        assert np.isfinite(X).all()
        perm = _better_order(_module_template(cmu41, module), 0.015, X[order])
        if expect:
            assert perm is not None and np.array_equal(np.asarray(order)[perm],
                                                       np.arange(len(module)))
        else:
            assert perm is None
        assert _better_order(_module_template(cmu41, module), 0.015, X) is None


def test_start_from_the_marker_set_alone_with_occlusions(cmu41):
    """85_02 from the marker set alone (no labelled frame), 10 % hidden in 0.1-1 s spans
    and 2 ghosts per frame, pattern 0 (the issue's target from the set alone: 95 %)."""
    full = read_c3d(DATA / "85_02.c3d").select(cmu41.labels)
    hidden = hide_spans(full, 0.1, seed=0)
    pts, truth = points_with_ghosts(hidden, 2, seed=0)
    _, _, labels = label_take(pts, cmu41, full.rate_hz)
    s = score(pts, truth, labels)
    assert s["correct"] >= 0.98, s
    assert 1 - s["correct"] - s["unlabelled"] <= 0.005, s


@pytest.mark.kernels  # a Labeller's compiled kernels
def test_skipped_frames_are_predicted_over(cmu41, acro):
    """A live stage that fell behind labels every 2nd frame of the acrobatics: told how
    many frames passed (`steps`), the tracker widens its gate for the longer motion and
    keeps every label; told nothing it loses some."""
    pts, truth = points_with_ghosts(acro, 0)
    _, per = pts.split()
    order = np.argsort(pts.frame, kind="stable")
    per_truth = np.split(truth[order], np.unique(pts.frame[order], return_index=True)[1][1:])
    right = {}
    for steps in (1, 2):
        lab = Labeller(cmu41, acro.rate_hz)
        lab.start_from_labelled_frames(acro.xyz_m[:10])
        good = total = 0
        for i in range(10, len(per), 2):
            got, _ = lab.update(per[i], steps)
            good += int((got == per_truth[i]).sum())
            total += len(got)
        right[steps] = good / total
    assert right[2] >= 0.995
    assert right[2] > right[1]


@pytest.mark.kernels  # a Labeller's compiled kernels
def test_kernels_match_their_numpy_twins(cmu41, acro):
    """Each compiled kernel (daemon/labelling/kernels.py) against the numpy code it replaces,
    on a labeller's state in the middle of an occluded take with ghosts."""
    from daemon.labelling import kernels as kern
    from daemon.labelling.modules import rigid_residuals as _rigid_residuals
    from daemon.labelling.reid import module_candidates_numpy
    from daemon.labelling.repair import swap_scores_numpy
    hidden = hide_spans(acro, 0.2, seed=11)
    pts, _ = points_with_ghosts(hidden, 3, seed=11)
    _, per = pts.split()
    fast = Labeller(cmu41, rate_hz=acro.rate_hz)
    ref = Labeller(cmu41, rate_hz=acro.rate_hz, compiled=False)
    for lab in (fast, ref):
        lab.start_from_labelled_frames(hidden.xyz_m[:10])
    for i, p in enumerate(per[10:150]):
        steps = 1 + (i % 7 == 3)          # now and then a frame skipped (a live stage)
        got_fast, conf_fast = fast.update(p, steps)
        got_ref, conf_ref = ref.update(p, steps)
        assert np.array_equal(got_fast, got_ref)
        assert np.allclose(conf_fast, conf_ref)
    # the state the commit kernel keeps
    for name in ("pos", "vel", "snap", "mod_shape"):
        assert np.allclose(getattr(fast, name), getattr(ref, name), equal_nan=True), name
    for name in ("age", "since_reacquired"):
        assert np.array_equal(getattr(fast, name), getattr(ref, name)), name
    cur = hidden.xyz_m[150]
    lost = np.nonzero(~np.isfinite(cur).all(1))[0]
    assert len(lost) >= 3
    assert np.allclose(fast._structure_error(cur), ref._structure_error(cur), equal_nan=True)
    m1, n1 = fast._candidate_error(lost, per[150], cur)
    m2, n2 = ref._candidate_error(lost, per[150], cur)
    assert np.allclose(m1, m2) and np.array_equal(n1, n2)
    assert np.allclose(fast._cand_chi2, ref._cand_chi2)
    assert np.allclose(fast._predict_from_neighbours(lost, cur),
                       ref._predict_from_neighbours(lost, cur), atol=1e-12)
    assert np.allclose(fast._support_spread, ref._support_spread)
    assert np.array_equal(fast._fresh_cost(lost, per[150], cur),
                          ref._fresh_cost(lost, per[150], cur))
    i, j = ref.swap_pairs[:, 0], ref.swap_pairs[:, 1]
    seen = np.isfinite(cur).all(1)
    both = seen[i] & seen[j]
    witness = np.ones(len(cur), bool)
    witness[::5] = False                  # markers found again this frame witness nothing
    keep1, swap1 = kern.swap_scores(cur, i[both], j[both], ref.swap_w, ref.mean_all, witness)
    keep2, swap2 = swap_scores_numpy(cur, i[both], j[both], ref.swap_w, ref.mean_all, witness)
    assert np.allclose(keep1, keep2) and np.allclose(swap1, swap2)
    every = kern.swap_scores(cur, i[both], j[both], ref.swap_w, ref.mean_all,
                             np.ones(len(cur), bool))
    assert not np.allclose(every[0], keep1)
    mods = lost[ref.mod_of[lost] >= 0]
    everything = acro.xyz_m[150][np.isfinite(acro.xyz_m[150]).all(1)]  # hidden ones too
    start = np.zeros((len(mods), len(everything)), bool)
    start[:, ::3] = True
    args = (mods, ref.mates, cur, everything, ref.mean_all, ref.adapt_tol, start)
    assert np.array_equal(kern.module_candidates(*args), module_candidates_numpy(*args))
    assert module_candidates_numpy(*args).sum() > start.sum()
    rng = np.random.default_rng(0)
    S, X = rng.normal(size=(2, 40, 5, 3))
    w = (rng.random((40, 5)) > 0.3).astype(float)
    for proper in (True, False):
        assert np.allclose(kern.rigid_residuals(S, X, w, proper),
                           _rigid_residuals(S, X, w, proper), atol=1e-12)


def _with_duplicates(take, names, seed=0):
    """The take's points with the markers `names` stored twice (a second trajectory
    1-3 mm off the first, as some labs' files hold), and each point's true marker."""
    rng = np.random.default_rng(seed)
    idx = [take.labels.index(n) for n in names]
    off = rng.normal(size=(take.n_frames, len(idx), 3))
    off *= rng.uniform(0.001, 0.003, (take.n_frames, len(idx), 1)) / \
        np.linalg.norm(off, axis=2, keepdims=True)
    copy = take.xyz_m[:, idx] + off
    doubled = Take(take.labels + [f"{n}-1" for n in names],
                   np.concatenate([take.xyz_m, copy], axis=1), take.rate_hz, take.first_frame)
    pts, truth = points_with_ghosts(doubled, 2, seed=seed)
    n = len(take.labels)
    twin = truth >= n
    truth[twin] = np.array(idx)[truth[twin] - n]
    return pts, truth


@pytest.mark.parametrize("merge", [True, False])
def test_markers_stored_twice_are_labelled_as_one(cmu41, walk, merge):
    """Three markers stored twice (1-3 mm apart) with 10 % hidden in spans and 2 ghosts:
    both copies of a marker are the one marker, labelled wherever the marker is seen.
    Without merging them (merge_m=0) a copy that returns after a gap competes with its
    twin and the marker is left out far more often."""
    names = ["LWRA", "RTOE", "STRN"]
    hidden = hide_spans(walk, 0.1, seed=7)
    pts, truth = _with_duplicates(hidden, names, seed=7)
    options = None if merge else {"merge_m": 0.0}
    _, _, labels = label_take(pts, cmu41, start_labels=hidden, start_frames=10, options=options)
    order = np.argsort(pts.frame, kind="stable")
    after = pts.frame[order] >= hidden.first_frame + 10          # after the seed frames
    got = np.concatenate(labels)[after]
    want, frame = truth[order][after], pts.frame[order][after]
    dup = np.isin(want, [cmu41.labels.index(n) for n in names])
    # per marker-frame: labelled through at least one of its copies
    key = frame[dup] * 100 + want[dup]
    right = got[dup] == want[dup]
    seen = np.unique(key)
    named = np.isin(seen, key[right])
    if merge:
        assert named.mean() >= 0.99
        assert (got[dup] == want[dup]).mean() >= 0.98      # both copies named
        assert score(pts, truth, labels, 10)["correct"] >= 0.98
    else:
        assert (got[dup] == want[dup]).mean() < 0.9


def test_cli_label_by_shipped_name_reports_a_marker_stored_twice(tmp_path, mocapd_cli, walk):
    """`--markerset cmu41` names the shipped set in `label` (and `fill`); a C3D that
    stores a marker twice (RBAC-1 on RBAC, 2 mm off) is told, and both are labelled as
    the one marker."""
    short = Take(walk.labels, walk.xyz_m[:120], walk.rate_hz, 0)
    twin = short.xyz_m[:, [short.labels.index("RBAC")]] + np.array([0.002, 0.0, 0.0])
    doubled = Take(short.labels + ["RBAC-1"], np.concatenate([short.xyz_m, twin], axis=1),
                   short.rate_hz, 0)
    write_take(tmp_path / "twice.c3d", doubled)
    r = mocapd_cli("label", tmp_path / "twice.c3d", "--markerset", "cmu41", "--out",
                   tmp_path / "lab.csv", "--json", tmp_path / "lab.json")
    assert r.code == 0, r.err
    assert "RBAC-1 lies within 6 mm of RBAC in 120 frames" in r.out
    figures = json.loads((tmp_path / "lab.json").read_text())
    assert figures["merged_points"] == 120 and figures["unlabelled_points"] == 0
    assert figures["duplicate_trajectories"] == [["RBAC", "RBAC-1"]]
    back = read_labelled_csv(tmp_path / "lab.csv").select(short.labels)
    err = np.linalg.norm(back.xyz_m - short.xyz_m, axis=2)
    rbac = short.labels.index("RBAC")
    assert np.delete(err, rbac, axis=1).max() < 2e-6     # CSV keeps micrometres
    assert err[:, rbac].max() < 0.0021                   # RBAC: one of its two copies
    r = mocapd_cli("fill", tmp_path / "lab.csv", "--markerset", "cmu41", "--out",
                   tmp_path / "filled.csv")
    assert r.code == 0, r.err
    r = mocapd_cli("label", tmp_path / "twice.c3d", "--markerset", "cmu40", "--out",
                   tmp_path / "x.csv")
    assert r.code == 2 and "cmu40 does not exist" in r.err and "cmu41" in r.err
    assert len(r.err.strip().splitlines()) == 1


# ---------------------------------------------------------------------- verification


def _relabelled(take, cycles):
    """The take with its labels moved round each cycle of names (a wrong labelling that
    keeps every marker: a chain shifted by one, left and right swapped)."""
    names = list(take.labels)
    wrong = names.copy()
    for cycle in cycles:
        for a, b in zip(cycle, cycle[1:] + cycle[:1], strict=True):
            wrong[names.index(a)] = b
    return Take(wrong, take.xyz_m, take.rate_hz, take.first_frame)


@pytest.mark.parametrize("name,cycles,hidden", [
    ("01_01.c3d", [["LTHI", "LKNE", "LSHN", "LANK", "LHEE"]], 0.0),       # a leg shifted
    ("85_02.c3d", [["LTHI", "LKNE", "LSHN", "LANK", "LHEE"]], 0.1),
    ("01_01.c3d", [["LFWT", "RFWT"], ["LBWT", "RBWT"]], 0.0),             # a mirrored pelvis
    ("85_02.c3d", [["LFWT", "RFWT"], ["LBWT", "RBWT"]], 0.1),
])
def test_verification_repairs_a_wrong_start(cmu41, name, cycles, hidden):
    """Labelled start frames with a leg's labels shifted by one marker, or left and right
    swapped at the pelvis: tracking carries them on (the take's own distances, learned
    from the start frames, agree with them), and the verification against the marker set
    relabels them and renames the tracker. After the first window (1 s) the points are
    named right against the truth as often as with a right start (within 0.3 %; 99 % on
    the clean takes), where without it the wrong labels stay."""
    take = _excerpt(name, cmu41.labels)
    start = _relabelled(take, cycles)
    t = hide_spans(take, hidden, seed=1) if hidden else take
    pts, truth = points_with_ghosts(t, 2 if hidden else 0, seed=1)
    first_window = 130                       # 10 start frames and the first window
    got = {}
    for case, first, verify in (("right", take, True), ("wrong", start, False),
                                ("repaired", start, True)):
        _, _, labels = label_take(pts, cmu41, take.rate_hz, first, 10, verify=verify)
        got[case] = score(pts, truth, labels, first_window)["correct"]
    assert got["wrong"] < got["right"] - 0.05            # the wrong start is carried on
    assert got["repaired"] >= got["right"] - 0.003
    assert got["repaired"] >= (0.95 if hidden else 0.99)
