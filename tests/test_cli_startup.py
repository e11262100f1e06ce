"""`calibkit --help`, `mocapd --help` and every subcommand's --help import nothing heavy (issue 31),
and the static command table behind the top-level help says what the commands say."""

from __future__ import annotations

import contextlib
import importlib
import io
import json
import subprocess
import sys
import textwrap

import pytest
import typer
from typer.testing import CliRunner

# rich too: help is drawn by click's plain formatter (calibkit.clitools.HELP_MARKUP), and rich's
# help renderer alone costs more than half of the 0.3 s a --help may take
HEAVY = ("numpy", "cv2", "scipy", "gtsam", "numba", "matplotlib", "viser", "zenoh", "rich")
APPS = {"calibkit": "calibkit.cli", "mocapd": "daemon.cli"}

# Runs in a fresh interpreter: lists every command path of the app from the app itself, then
# runs `PROG [PATH...] --help` for each, one after another, and reports the exit codes and the
# heavy modules present after each (modules only accumulate, so the last report covers all).
_PROBE = textwrap.dedent("""
    import contextlib, io, json, sys
    prog, app_module, heavy = sys.argv[1], sys.argv[2], sys.argv[3].split(",")
    mod = __import__(app_module, fromlist=["main"])

    def run(argv):
        sys.argv = [prog, *argv]
        code = 0
        with contextlib.redirect_stdout(io.StringIO()) as out:
            try:
                mod.main()
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        loaded = sorted(m for m in heavy if m in sys.modules)
        commands = sorted(m for m in sys.modules if m.startswith(("calibkit.commands.",
                                                                  "daemon.commands.")))
        return {"argv": argv, "code": code, "heavy": loaded, "command_modules": commands,
                "out": out.getvalue()}

    reports = [run(["--help"])]
    import typer
    group = typer.main.get_command(mod.app)
    paths = []
    for name in group.list_commands(None):
        paths.append([name])
        reports.append(run([name, "--help"]))
        cmd = group.load(name)
        for sub in getattr(cmd, "commands", {}):
            paths.append([name, sub])
            reports.append(run([name, sub, "--help"]))
    print(json.dumps(reports))
""")


def _probe(prog: str) -> list[dict]:
    res = subprocess.run([sys.executable, "-c", _PROBE, prog, APPS[prog], ",".join(HEAVY)],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout)


@pytest.mark.parametrize("prog", sorted(APPS))
def test_help_everywhere_imports_nothing_heavy(prog):
    reports = _probe(prog)
    top = reports[0]
    assert top["code"] == 0 and "Usage:" in top["out"] and "Commands" in top["out"]
    assert top["heavy"] == [], f"`{prog} --help` imported {top['heavy']}"
    assert top["command_modules"] == [], f"`{prog} --help` imported {top['command_modules']}"
    names = set(importlib.import_module(APPS[prog]).COMMANDS)
    assert {r["argv"][0] for r in reports[1:]} == names
    assert len(reports) > len(names)  # the command groups' own commands were visited too
    for r in reports[1:]:
        shown = " ".join([prog, *r["argv"]])
        assert r["code"] == 0, f"`{shown}` exited {r['code']}"
        assert "Usage:" in r["out"], f"`{shown}` printed no help"
        assert r["heavy"] == [], f"`{shown}` imported {r['heavy']} (or an earlier help did)"


def _help(group, prog: str) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
        group.main(args=["--help"], prog_name=prog, standalone_mode=False)
    return out.getvalue()


@pytest.mark.parametrize("prog", sorted(APPS))
def test_command_table_says_what_the_commands_say(prog, monkeypatch):
    """cli.py's COMMANDS lists exactly the commands its modules register, and the top-level
    help drawn from it is the one drawn from the commands themselves."""
    monkeypatch.setenv("COLUMNS", "100")
    cli = importlib.import_module(APPS[prog])
    package = APPS[prog].replace(".cli", ".commands")
    for module in {module for module, _ in cli.COMMANDS.values()}:
        holder = typer.Typer()
        holder.callback()(lambda: None)
        importlib.import_module(f"{package}.{module}").register(holder)
        registered = set(typer.main.get_group(holder).commands)
        assert registered == {n for n, (m, _) in cli.COMMANDS.items() if m == module}, module
    from_table = _help(typer.main.get_command(cli.app), prog)
    loaded = typer.main.get_command(cli.app)
    for name in cli.COMMANDS:
        loaded.load(name)
    from_commands = _help(loaded, prog)
    assert "Commands" in from_table and from_table == from_commands


def test_a_mistyped_command_is_one_line_with_a_suggestion():
    from calibkit.cli import app

    res = CliRunner().invoke(app, ["wnad"])
    assert res.exit_code == 2
    assert "No such command 'wnad'" in res.output and "'wand'" in res.output


def test_version_needs_no_command():
    from calibkit import __version__
    from daemon.cli import app

    res = CliRunner().invoke(app, ["--version"])
    assert res.exit_code == 0 and res.output.strip() == f"mocapd {__version__}"


def test_rig_command_spells_anipose_default_unit():
    """rig_cmd spells the default itself so that its --help loads no rig readers."""
    from calibkit.commands import rig_cmd
    from calibkit.core.rigformats.anipose import DEFAULT_UNIT

    assert rig_cmd.DEFAULT_UNIT == DEFAULT_UNIT
