"""Every command keeps the top-level help's word (issue 31): each either takes --sim or says
in its help what it reads; and the --sim options added for it run and are scored against
the simulator's truth."""

from __future__ import annotations

import contextlib
import csv
import importlib
import io
import json
import re

import pytest

from calibkit.clitools import eager_group

APPS = {"calibkit": "calibkit.cli", "mocapd": "daemon.cli"}


def _leaves(cmd, path):
    """(path, click command) of every command that runs (groups walked into)."""
    subs = getattr(cmd, "commands", None)
    if subs:
        for name in cmd.list_commands(None):
            yield from _leaves(cmd.get_command(None, name), [*path, name])
    else:
        yield path, cmd


def _help_text(cmd, path) -> str:
    """The command's --help as a user sees it, whitespace folded."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
        cmd.main(args=["--help"], prog_name=" ".join(path), standalone_mode=False)
    return re.sub(r"[\s│]+", " ", out.getvalue())


def _commands():
    for prog, module in APPS.items():
        group = eager_group(importlib.import_module(module).app)
        for name in group.list_commands(None):
            yield from _leaves(group.load(name), [prog, name])


COMMANDS = list(_commands())


@pytest.mark.parametrize("path, cmd", COMMANDS, ids=[" ".join(p) for p, _ in COMMANDS])
def test_each_command_takes_sim_or_names_its_input(path, cmd, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")
    text = _help_text(cmd, path)
    options = {o for p in cmd.params for o in getattr(p, "opts", ())}
    if "--sim" in options:
        assert "--sim" in text
        return
    reads = re.search(r"\bReads ([^.]{8,})\.", text)
    assert reads, f"`{' '.join(path)}` has no --sim and its help does not say what it reads"


def test_every_command_was_walked():
    names = {" ".join(p[:2]) for p, _ in COMMANDS}
    assert {"calibkit mask", "calibkit triangulate", "calibkit compare", "calibkit convert",
            "calibkit sim", "calibkit rig", "calibkit displays", "calibkit intrinsic"} <= names
    assert sum(p[1] == "sim" for p, _ in COMMANDS) >= 4  # sim's own commands too
    assert {"mocapd track", "mocapd label", "mocapd view", "mocapd evaluate", "mocapd fill",
            "mocapd markerset", "mocapd status", "mocapd rigid-body"} <= names


@pytest.mark.parametrize("path", [["mocapd", "track"], ["mocapd", "label"],
                                  ["calibkit", "triangulate"], ["calibkit", "mask"],
                                  ["calibkit", "displays"], ["mocapd", "start"]])
def test_the_commands_a_person_tries_first_take_sim(path):
    cmd = dict((tuple(p), c) for p, c in COMMANDS)[tuple(path)]
    assert "--sim" in {o for p in cmd.params for o in getattr(p, "opts", ())}


def test_top_level_help_says_what_is_true(calibkit_cli):
    r = calibkit_cli("--help")
    text = re.sub(r"[\s│]+", " ", r.out)
    assert "Add --sim to any command that reads cameras, a monitor or a capture" in text
    assert "add --sim to any command to" not in text


@pytest.mark.slow  # a whole run of the command
def test_triangulate_sim_is_scored_against_the_truth(calibkit_cli, tmp_path):
    out, js = tmp_path / "points.csv", tmp_path / "t.json"
    r = calibkit_cli("triangulate", "--sim", "--frames", 60, "--out", out, "--json", js)
    assert r.code == 0, r.err
    assert "true poses and lenses" in r.err  # no --rig: said which cameras were used
    truth = json.loads(js.read_text())["truth"]
    # 0.2 px of noise at 2-5 m with ~460 px focal lengths: a few mm per ray, less averaged
    assert truth["error_mm_rms"] < 3.0 and truth["gross_errors"] == 0
    assert truth["recall_3"] > 0.95
    rows = list(csv.DictReader(out.open()))
    assert rows and all(float(row["error_mm"]) < 10.0 for row in rows)


def test_triangulate_sim_with_a_rig_of_other_cameras_is_one_line(calibkit_cli, tmp_path):
    other = tmp_path / "other.toml"
    assert calibkit_cli("sim", "rig", "--out", other, "--cameras", 4).code == 0
    r = calibkit_cli("triangulate", "--sim", "--rig", other, "--out", tmp_path / "p.csv")
    assert r.code == 2 and len(r.err.strip().splitlines()) == 1 and "cam4" in r.err, r.err
    r = calibkit_cli("triangulate", "--out", tmp_path / "p.csv")
    assert r.code == 2 and "--sim" in r.err and len(r.err.strip().splitlines()) == 1


@pytest.mark.slow  # a whole run of the command
def test_triangulate_sim_with_an_estimated_rig(calibkit_cli, tmp_path):
    """A rig file of the same cameras, a little off (as an estimate is): triangulated with
    it, the error grows above the perfect calibration's."""
    from calibkit.core.camera import Rig
    from calibkit.synthetic import sim

    true_rig = sim.make_rig(6, 4.0, seed=0)
    est = Rig(tuple(c.replace(fx=c.fx * 1.01, fy=c.fy * 1.01) for c in true_rig),
              meta=true_rig.meta)
    path = tmp_path / "est.toml"
    est.save(path)
    errors = []
    for extra in ((), ("--rig", path)):
        js = tmp_path / "t.json"
        r = calibkit_cli("triangulate", "--sim", "--frames", 40, "--out", tmp_path / "p.csv",
                         "--json", js, *extra)
        assert r.code == 0, r.err
        errors.append(json.loads(js.read_text())["truth"]["error_mm_rms"])
    assert errors[1] > 1.5 * errors[0]


def test_displays_sim_lists_the_monitor_intrinsic_display_sim_draws(calibkit_cli, tmp_path):
    from calibkit.synthetic.monitor import MonitorSimConfig

    js = tmp_path / "d.json"
    r = calibkit_cli("displays", "--sim", "--json", js)
    assert r.code == 0, r.err
    (screen,) = json.loads(js.read_text())["displays"]
    cfg = MonitorSimConfig()
    assert (screen["width_px"], screen["height_px"]) == cfg.screen_px
    assert screen["pixel_pitch_mm"] == pytest.approx(cfg.pixel_pitch_mm, rel=2e-3)
