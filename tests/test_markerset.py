"""Marker sets learned from the real CMU takes: segments, distances, handedness, TOML."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibkit.core.errors import UserError
from daemon.formats.c3dio import read_c3d
from daemon.labelling.markerset import MarkerSet, learn, signed_volume

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "fixtures" / "cmu_c3d"


@pytest.fixture(scope="module")
def takes():
    a = read_c3d(DATA / "85_02.c3d")
    b = read_c3d(DATA / "01_01.c3d").select(a.labels)
    return a, b


@pytest.fixture(scope="module")
def ms_85(takes):
    return learn([takes[0]], name="s85")


def _names(ms, seg):
    return {ms.labels[i] for i in seg.markers}


def test_segments_group_markers_that_keep_their_shape(ms_85, takes):
    segs = [_names(ms_85, s) for s in ms_85.segments]
    assert {"LFWT", "RFWT", "LBWT", "RBWT"} in segs          # the pelvis
    assert {"LFHD", "RFHD", "LBHD", "RBHD"} in segs          # the head
    # every segment really is steady in the take: internal distances vary < 12 mm (SD)
    x = takes[0].xyz_m
    for s in ms_85.segments:
        m = s.markers
        if len(m) < 2:
            continue
        d = np.linalg.norm(x[:, m, None] - x[:, None, m], axis=3)
        assert np.nanstd(d, axis=0).max() < 0.012
    # exactly one root, and every parent chain reaches it
    roots = [i for i, s in enumerate(ms_85.segments) if s.parent < 0]
    assert len(roots) == 1
    for s in ms_85.segments:
        hops, p = 0, s.parent
        while p >= 0 and hops < 50:
            p, hops = ms_85.segments[p].parent, hops + 1
        assert hops < 50


def test_distances_match_the_take(ms_85, takes):
    x = takes[0].xyz_m
    i, j = ms_85.labels.index("LFHD"), ms_85.labels.index("RBHD")
    d = np.linalg.norm(x[:, i] - x[:, j], axis=1)
    assert ms_85.mean_m[i, j] == pytest.approx(d.mean(), abs=1e-9)
    assert ms_85.sd_m[i, j] == pytest.approx(max(d.std(), 0.002), abs=1e-9)


def test_handedness_holds_on_another_subject_and_flips_in_a_mirror(ms_85, takes):
    """Learned on 85_02 only, the chiral quadruples keep their sign on 01_01 (another
    person, another session) and all flip when the body is mirrored."""
    x = takes[1].xyz_m[::10]
    v = signed_volume(x, ms_85.chiral)
    ok = np.isfinite(v)
    agree = (np.sign(v) == ms_85.chiral_sign)[ok].mean()
    assert len(ms_85.chiral) >= 10 and agree > 0.98
    mirrored = x * np.array([-1.0, 1.0, 1.0])
    vm = signed_volume(mirrored, ms_85.chiral)
    assert (np.sign(vm) == ms_85.chiral_sign)[ok].mean() < 0.02


def test_toml_round_trip(tmp_path, ms_85):
    ms_85.save(tmp_path / "set.toml")
    back = MarkerSet.load(tmp_path / "set.toml")
    assert back.labels == ms_85.labels
    assert np.abs(back.mean_m - ms_85.mean_m).max() < 1e-5      # stored to 0.01 mm
    assert [s.markers for s in back.segments] == [s.markers for s in ms_85.segments]
    assert np.array_equal(back.chiral, ms_85.chiral)


def test_shipped_cmu41_loads_and_covers_both_subjects():
    ms = MarkerSet.load(ROOT / "daemon" / "labelling" / "sets" / "cmu41.toml")
    assert ms.n == 41 and ms.name == "cmu41"
    # learned from two subjects: between-take spread is known and non-zero somewhere
    assert ms.subject_sd_m.max() > 0.005


def test_bad_marker_set_files(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        MarkerSet.load(tmp_path / "none.toml")
    (tmp_path / "bad.toml").write_text("markers = [1, 2\n")
    with pytest.raises(UserError, match="not a valid TOML"):
        MarkerSet.load(tmp_path / "bad.toml")
    (tmp_path / "short.toml").write_text('markers = ["A", "B"]\n')
    with pytest.raises(UserError, match="markerset learn"):
        MarkerSet.load(tmp_path / "short.toml")


def test_learn_needs_shared_labels(takes):
    a, b = takes
    with pytest.raises(UserError, match="lacks marker"):
        learn([a, b.select(b.labels[:10])])


def test_cli_learn(tmp_path, mocapd_cli):
    r = mocapd_cli("markerset", "learn", DATA / "85_02.c3d", "--out", tmp_path / "s.toml",
                   "--json", tmp_path / "s.json")
    assert r.code == 0, r.err
    assert "41 markers" in r.out
    assert MarkerSet.load(tmp_path / "s.toml").n == 41
    r = mocapd_cli("markerset", "learn", DATA / "85_02.c3d", "--out", tmp_path / "s.txt")
    assert r.code == 2 and "toml" in r.err and "Traceback" not in r.err


# ---------------------------------------------------------------------- fit check


@pytest.fixture(scope="module")
def cmu41():
    from daemon.labelling.markerset import open_set
    return open_set("cmu41")


def test_fit_check_judges_a_set_on_a_take(cmu41, takes):
    """The shipped set on a take it was learned from fits; the same take 20 % larger
    fits as well at scale 1.2; a thigh marker stuck 8 cm higher and a wrist marker 6 cm
    along the forearm are named and spoil the verdict; a marker the take
    never shows is listed."""
    from daemon.labelling.markerset_fit import check_fit
    x = takes[1].select(cmu41.labels).xyz_m[:600]
    fit = check_fit(cmu41, x)
    assert fit.verdict.startswith("good fit") and abs(fit.scale - 1) < 0.05
    assert fit.missing == [] and fit.misplaced == [] and fit.bent == []
    big = check_fit(cmu41, 1.2 * x)
    assert big.scale / fit.scale == pytest.approx(1.2, abs=1e-3)      # rounded to 4 digits
    assert big.verdict.startswith("good fit") and f"{big.scale:.2f}x" in big.verdict
    assert [s.relative for s in big.segments] == pytest.approx(
        [s.relative for s in fit.segments], abs=1e-3)
    moved = x.copy()
    moved[:, cmu41.labels.index("LTHI"), 2] += 0.08
    fore = [cmu41.labels.index(n) for n in ("RWRA", "RELB")]
    along = moved[:, fore[1]] - moved[:, fore[0]]
    moved[:, fore[0]] += 0.06 * along / np.linalg.norm(along, axis=1, keepdims=True)
    moved[:, cmu41.labels.index("RFHD")] = np.nan
    bad = check_fit(cmu41, moved)
    assert set(bad.misplaced) == {"LTHI", "RWRA"}
    assert bad.missing == ["RFHD"] and not bad.verdict.startswith("good fit")
    assert "RFHD" in bad.verdict and "LTHI" in bad.verdict


def test_cli_markerset_check(tmp_path, mocapd_cli, takes, cmu41):
    """`mocapd markerset check`: by the take's labels, and on its points alone (the start
    from the set, as labelling would do) the same scale and verdict; --json; a file that
    is not a take is one line and exit 2."""
    import json

    from daemon.formats.c3dio import Points, Take, write_points_csv, write_take
    t = takes[1].select(cmu41.labels)
    short = Take(t.labels, t.xyz_m[:240], t.rate_hz, 0)
    write_take(tmp_path / "t.c3d", short)
    write_points_csv(tmp_path / "p.csv", Points.from_take(short, seed=2))
    figs = []
    for args in ((tmp_path / "t.c3d",), (tmp_path / "p.csv",)):
        out = tmp_path / f"fit{len(figs)}.json"
        r = mocapd_cli("markerset", "check", *args, "--markerset", "cmu41", "--json", out)
        assert r.code == 0, r.err
        assert "good fit" in r.out
        figs.append(json.loads(out.read_text()))
    assert [f["labelled_by"] for f in figs] == ["labels", "start"]
    # (the start looks at a window of 120 frames: another posture, a little another scale)
    assert figs[1]["scale"] == pytest.approx(figs[0]["scale"], rel=0.02)
    assert figs[1]["missing"] == []
    (tmp_path / "x.txt").write_text("hello")
    r = mocapd_cli("markerset", "check", tmp_path / "x.txt", "--markerset", "cmu41")
    assert r.code == 2 and len(r.err.strip().splitlines()) == 1
