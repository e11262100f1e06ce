"""Marker sets learned from the real CMU takes: segments, distances, handedness, TOML."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibkit.core.errors import UserError
from daemon.markers.c3dio import read_c3d
from daemon.markers.markerset import MarkerSet, learn, signed_volume

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
    ms = MarkerSet.load(ROOT / "daemon" / "markers" / "sets" / "cmu41.toml")
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
