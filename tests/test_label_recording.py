"""`mocapd label REC.mcrec --rig`: a recording of 2D blobs triangulated, then labelled,
checked against the simulated person's true marker positions."""

from __future__ import annotations

import numpy as np
import pytest

from calibkit.core.recording import save_observations
from calibkit.synthetic import person as sim_person
from calibkit.synthetic import sim
from daemon.formats.c3dio import Take, read_take, write_take

RATE = 120.0


@pytest.fixture(scope="module")
def person_recording(tmp_path_factory):
    d = tmp_path_factory.mktemp("labelrec")
    take = sim_person.walk(240, RATE, seed=0)
    xyz = take.markers_m + np.array([0.9, 0.0, 0.0])  # walk through the middle
    rig = sim.make_rig(8, 4.0, seed=0)
    rig.save(d / "rig.toml")
    obs = sim.observe(rig, sim._frames_truth(xyz), noise_px=0.2, fps=RATE, seed=1)
    save_observations(d / "walk.mcrec", obs)
    # the marker set, learned from another walk of the same person
    other = sim_person.walk(600, RATE, seed=5)
    write_take(d / "other.csv", Take(other.labels, other.markers_m, RATE))
    return d, take.labels, xyz


@pytest.fixture(scope="module")
def person_set(person_recording):
    from daemon.labelling.markerset import learn

    d, _, _ = person_recording
    learn([read_take(d / "other.csv")], name="walker").save(d / "set.toml")
    return d / "set.toml"


def test_label_a_recording_against_the_truth(person_recording, person_set, mocapd_cli):
    d, labels, xyz = person_recording
    r = mocapd_cli("label", d / "walk.mcrec", "--rig", d / "rig.toml", "--markerset",
                   person_set, "--out", d / "walk.csv")
    assert r.code == 0, r.err
    out = read_take(d / "walk.csv")
    assert out.rate_hz == RATE  # from the recording
    got = out.xyz_m[:, [out.labels.index(n) for n in labels]]
    err = np.linalg.norm(got - xyz[:len(got)], axis=2)  # NaN where not labelled
    right = np.nan_to_num(err, nan=np.inf) < 0.005
    assert right.mean() >= 0.99, right.mean()  # named right and triangulated within 5 mm
    assert np.nanmedian(err) < 0.0015


def test_a_recording_needs_the_rig(person_recording, person_set, mocapd_cli, tmp_path):
    d, _, _ = person_recording
    r = mocapd_cli("label", d / "walk.mcrec", "--markerset", person_set,
                   "--out", tmp_path / "x.csv")
    assert r.code == 2 and "--rig" in r.err and len(r.err.strip().splitlines()) == 1
    r = mocapd_cli("label", d / "other.csv", "--rig", d / "rig.toml", "--markerset",
                   person_set, "--out", tmp_path / "x.csv")
    assert r.code == 2 and "--rig is for a .mcrec" in r.err
    assert not (tmp_path / "x.csv").exists()
