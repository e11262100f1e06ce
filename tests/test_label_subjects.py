"""Labelling subjects that are not the marker set's (issue 29): a real CMU take performed by
a body re-proportioned per segment (daemon/synthetic/subjects.py), and the rule that a
correct labelled start never ends worse than the set alone or than no verification."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from daemon.formats.c3dio import read_c3d
from daemon.labelling.markerset import MarkerSet
from daemon.labelling.offline import label_take
from daemon.synthetic.labelling import hide_spans, points_with_ghosts
from daemon.synthetic.subjects import (
    SEGMENTS,
    Subject,
    markers_of,
    random_subject,
    reproportion,
)

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "fixtures" / "cmu_c3d"


@pytest.fixture(scope="module")
def cmu41():
    return MarkerSet.load(ROOT / "daemon" / "labelling" / "sets" / "cmu41.toml")


@pytest.fixture(scope="module")
def take(cmu41):
    return read_c3d(DATA / "85_02.c3d").select(cmu41.labels)


def _dist(x, a, b, labels):
    return np.linalg.norm(x[:, labels.index(a)] - x[:, labels.index(b)], axis=1)


def test_a_reproportioned_subject_is_the_same_motion_by_another_body(take):
    """Each segment's own distances scale by its factor in every frame (the shank's SHN
    to ANK, the forearm's WRA to WRB); the identity subject gives the take back; extra
    markers keep their distance to their segment, and the truth of the extra markers
    maps to no marker of the set."""
    same = reproportion(take, Subject())
    assert np.allclose(same.xyz_m, take.xyz_m, equal_nan=True)
    subject = Subject((("Lshank", 1.15), ("Rforearm", 0.85), ("Lthigh", 0.9)), 0.0, 2, 1)
    other = reproportion(take, subject)
    L = take.labels
    for a, b, k in (("LSHN", "LANK", 1.15), ("RWRA", "RWRB", 0.85), ("LTHI", "LKNE", 0.9),
                    ("LHEE", "LTOE", 1.0)):
        ratio = _dist(other.xyz_m, a, b, other.labels) / _dist(take.xyz_m, a, b, L)
        assert np.allclose(ratio, k, atol=1e-9), (a, b)
    # the motion is kept: the knee angle's cosine (thigh and shank) is the same per frame
    def cos_knee(x, labels):
        u = x[:, labels.index("LTHI")] - x[:, labels.index("LKNE")]
        v = x[:, labels.index("LANK")] - x[:, labels.index("LKNE")]
        return (u * v).sum(1) / np.linalg.norm(u, axis=1) / np.linalg.norm(v, axis=1)
    assert np.allclose(cos_knee(other.xyz_m, other.labels), cos_knee(take.xyz_m, L),
                       atol=1e-9)
    assert other.labels[-2:] == ["X1", "X2"]
    for e in ("X1", "X2"):
        d = np.linalg.norm(other.xyz_m[:, other.labels.index(e)][:, None]
                           - other.xyz_m[:, :len(L)], axis=2).min(1)
        assert np.ptp(d) < 0.02 and 0.03 < d.min()
    assert list(markers_of(other, L)[-2:]) == [-1, -1]
    assert {s for s, _ in random_subject(0).scale} <= set(SEGMENTS)


def _right_wrong(take, cmu41, seed, start_frames, verify=True):
    t = hide_spans(take, 0.1, seed=seed)
    pts, mk = points_with_ghosts(t, 2, seed=seed)
    to_set = markers_of(t, cmu41.labels)
    truth = np.where(mk >= 0, to_set[np.maximum(mk, 0)], -1)
    _, _, labels = label_take(pts, cmu41, take.rate_hz, t if start_frames else None,
                              start_frames, verify=verify)
    order = np.argsort(pts.frame, kind="stable")
    _, starts = np.unique(pts.frame[order], return_index=True)
    want = np.concatenate(np.split(truth[order], starts[1:])[10:])
    got = np.concatenate(labels[10:])          # the same frames for every start
    real = want >= 0
    return (float((got[real] == want[real]).mean()),
            float(((got[real] >= 0) & (got[real] != want[real])).mean()))


def test_a_correct_start_never_ends_worse_on_another_body(take, cmu41):
    """85_02 by another body (subject 3: shanks 0.91, upper arms 1.12 ..., markers 10 mm
    off, 3 extra markers the set lacks), 10 % hidden and 2 ghosts: with 10 correctly
    labelled start frames the take ends at least as right as from the set alone and as
    without verification. Before the start's own distances outranked the set,
    verification took a thigh marker for the pelvis's (the subject "repaired" toward the
    set): 96.0 % right and 2.1 % wrong, against 97.8 % and none without it."""
    other = reproportion(take, random_subject(3, extra_markers=3))
    alone, _ = _right_wrong(other, cmu41, 3, 0)
    start, start_wrong = _right_wrong(other, cmu41, 3, 10)
    unverified, _ = _right_wrong(other, cmu41, 3, 10, verify=False)
    assert start >= alone
    assert start >= unverified
    assert start_wrong < 0.002


def test_a_marker_followed_alone_keeps_its_point_when_a_lost_neighbour_lands_on_a_ghost(
        cmu41):
    """01_01 by body 6 (10 % hidden, 2 ghosts): for 50 frames only LMT5 of the left foot
    is seen, and a ghost falls 7 cm from the hidden ankle. With a correct labelled start
    the lost LANK was found again on the ghost, and the swap check, which found the two
    fitting better the other way round, gave LMT5's point to LANK: the foot's labels then
    turned for about 70 frames (LMT5 named LANK, LTOE; LHEE named LMT5), 99.79 % right
    against 100 % from the set alone. A marker found again in a frame is no longer
    swapped with one that followed its own motion to a point beyond the tracking gate
    from it: the new one lets its point go."""
    take = read_c3d(DATA / "01_01.c3d").select(cmu41.labels)
    other = reproportion(take, random_subject(6))
    alone, _ = _right_wrong(other, cmu41, 6, 0)
    start, start_wrong = _right_wrong(other, cmu41, 6, 10)
    assert start >= alone
    assert start_wrong < 0.0005


@pytest.mark.parametrize("seed, before", [(3, 0.9431), (19, 0.9277)])
def test_another_body_from_the_set_alone(take, cmu41, seed, before):
    """85_02 by two other bodies, from the set alone (10 % hidden, 2 ghosts), labelled as
    well as the set's own subjects are: >= 97 % right, under 2 % wrong (before: 94.3 and
    92.8 % right, 4.1 and 6.2 % wrong; body 19 keeps its head turned in the start's
    window, 1.1 % of its points). Before, body 3's
    start window (its knee marker hidden there) named the shank marker RKNE, which this
    body's proportions make the set prefer; verification found the right leg in a later
    window that saw every marker, and the window after it, with a hip marker hidden,
    the leg shifted by one marker (94.3 %). Now the window with more evidence decides
    between them, and the take is labelled again from a window that holds more markers
    than the start did. Body 19's head was turned by one place from the start (the set
    prefers that in the start window, and the truth by 17 units in the first); no swap
    reaches a turn of four labels, a reordering of a near group does (92.8 %)."""
    other = reproportion(take, random_subject(seed))
    right, wrong = _right_wrong(other, cmu41, seed, 0)
    assert right >= 0.97 > before
    assert wrong < 0.02


@pytest.mark.parametrize("seed, got, before", [(42, 0.9886, 0.6880), (22, 0.9996, 0.7079)])
def test_a_scrambled_start_is_put_right_from_the_frames_before_it(take, cmu41, seed, got,
                                                                  before):
    """85_02 by two bodies held out while the rules were made (42) or not traced (22),
    from the set alone (10 % hidden, 2 ghosts). Both starts take frames 600-719 (the
    crouch) and the search scrambles them over the whole body (49 and 35 % of the
    window's points right, by the truth); verification put right the frames before the
    start (labelled backward), but the take was labelled again only from a window after
    it, and none there was better evidence: 68.8 and 70.8 % right. Now every window of
    the take counts, and the take is labelled again from frames 240-359 or 120-239
    (98.9 and 99.96 % in the run that set these thresholds)."""
    other = reproportion(take, random_subject(seed))
    right, wrong = _right_wrong(other, cmu41, seed, 0)
    assert right >= got - 0.01 > before
    assert wrong < 0.01


def test_a_leg_turned_along_its_chain_is_put_right(take, cmu41):
    """85_02 by body 43 (held out while the rules were made), from the set alone: the
    start named the right leg's thigh, knee and shank markers each by the next one
    along the leg, and tracking kept it through the take (91.1 % right, 6.6 % wrong),
    though the set prefers the truth in every window by 13-66 units: a cycle of three
    labels 20-40 cm apart, which no swap and no near group reaches. Verification's
    local search now also reorders each marker with its two steadiest neighbours by the
    set (97.4 % right and 0.3 % wrong in the run that set this threshold)."""
    other = reproportion(take, random_subject(43))
    right, wrong = _right_wrong(other, cmu41, 43, 0)
    assert right >= 0.964 > 0.9110
    assert wrong < 0.01


def test_chain_groups_are_a_limbs_joint_markers(cmu41):
    """Each chain group is three markers the set keeps steady together (each pair's
    spread under 8 mm from the middle marker), and the knee's thigh-knee-shank is one."""
    from daemon.labelling.assign import chain_groups
    groups = [tuple(cmu41.labels[i] for i in g) for g in chain_groups(cmu41)]
    assert ("RKNE", "RSHN", "RTHI") in [tuple(sorted(g)) for g in groups]
    for g in chain_groups(cmu41):
        sd = cmu41.sd_m[np.ix_(g, g)]
        assert (np.sort(sd, axis=1)[:, 2] < 0.008).any()      # a marker steady with both


def test_group_moves_change_the_score_as_they_say(take, cmu41):
    """The reorderings inside a near group (a head's four markers) are scored by the
    compatibility's exact change, batched: each equals the change of the whole score."""
    from daemon.labelling.assign import (
        Compat,
        body_scale,
        group_moves,
        near_groups,
        pair_stats,
        to_marker_track,
    )
    groups = near_groups(cmu41)
    head = {cmu41.labels.index(n) for n in ("LFHD", "RFHD", "LBHD", "RBHD")}
    assert any(set(g.tolist()) == head for g in groups)
    other = reproportion(take, random_subject(5))
    X = np.ascontiguousarray(other.xyz_m[200:320].transpose(1, 0, 2))
    seen = np.isfinite(X).all(2).all(1)
    X = X[seen]
    D, S = pair_stats(X)
    cp = Compat(cmu41, D, S, body_scale(D, cmu41))
    rng = np.random.default_rng(0)
    lab = np.nonzero(seen)[0]
    h = np.array(sorted(head))
    lab = lab.copy()
    rows = np.nonzero(np.isin(lab, h))[0]
    lab[rows] = lab[rows][rng.permutation(len(rows))]        # the head's labels shuffled
    P = np.zeros((len(X), cmu41.n))
    P[np.arange(len(X)), lab] = 1.0
    mt = to_marker_track(P)
    moves = group_moves(cp, cp.gain(P), mt, groups)
    assert moves
    for dv, m2 in moves:
        Q = np.zeros_like(P)
        ok = m2 >= 0
        Q[m2[ok], np.nonzero(ok)[0]] = 1.0
        assert dv > 0
        assert dv == pytest.approx(cp.score(Q) - cp.score(P), rel=1e-5)   # (single precision)
