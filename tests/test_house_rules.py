"""The house rules of issue 32 that a reader meets first: no module of ours is long, and no
command handler is more than a page of options, checks and one call.

Why a test: both rules were met once by moving code and drift back one feature at a time;
the scan names the offenders so the fix is obvious. The limits carry a little slack over
the guideline (~500 lines, ~60 lines) so that a docstring line does not fail a build.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("calibkit", "daemon", "projector")
MAX_MODULE_LINES = 520
MAX_HANDLER_BODY_LINES = 60


def _modules(packages=PACKAGES) -> list[Path]:
    return sorted(p for pkg in packages for p in (ROOT / pkg).rglob("*.py")
                  if "__pycache__" not in p.parts)


def long_modules(paths: list[Path], limit: int = MAX_MODULE_LINES) -> list[str]:
    """'path (N lines)' for each file over the limit."""
    out = []
    for path in paths:
        n = len(path.read_text(encoding="utf-8").splitlines())
        if n > limit:
            out.append(f"{path.relative_to(ROOT) if path.is_relative_to(ROOT) else path} "
                       f"({n} lines)")
    return out


def _is_command(dec: ast.expr) -> bool:
    """A decorator registering a typer command: `X.command(...)` or `X.command` (typer's
    `app.command`, a sub-app's `sim_app.command`, or `register(app)`'s inner ones)."""
    target = dec.func if isinstance(dec, ast.Call) else dec
    return isinstance(target, ast.Attribute) and target.attr == "command"


def handler_bodies(source: str) -> list[tuple[str, int]]:
    """(name, body lines after the docstring) of every function the source registers as a
    command, at any depth (register(app) defines its handlers inside it)."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        if not any(_is_command(d) for d in node.decorator_list):
            continue
        body = node.body
        if (body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)):
            body = body[1:]  # the docstring is the command's --help, not its work
        n = body[-1].end_lineno - body[0].lineno + 1 if body else 0
        out.append((node.name, n))
    return out


def long_handlers(paths: list[Path], limit: int = MAX_HANDLER_BODY_LINES) -> list[str]:
    """'path:handler (N lines)' for each command handler whose body is over the limit."""
    out = []
    for path in paths:
        for name, n in handler_bodies(path.read_text(encoding="utf-8")):
            if n > limit:
                out.append(f"{path.relative_to(ROOT) if path.is_relative_to(ROOT) else path}"
                           f":{name} ({n} lines)")
    return out


def _command_modules() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).glob("commands/*.py"))


def test_no_module_of_ours_is_over_520_lines():
    offenders = long_modules(_modules())
    assert not offenders, ("modules over ~500 lines; split them by what each part does: "
                           + ", ".join(offenders))


def test_no_command_handler_body_is_over_60_lines():
    offenders = long_handlers(_command_modules())
    assert not offenders, ("command handlers over ~60 lines; move the run into a *_run.py "
                           "module beside them: " + ", ".join(offenders))


def test_the_scan_sees_every_command_and_measures_bodies_without_docstrings():
    """The scan must find the handlers it polices: every command the two CLIs list is a
    registered function it measures, and a body is counted from after its docstring."""
    from calibkit.cli import COMMANDS as CALIBKIT_COMMANDS
    from daemon.cli import COMMANDS as MOCAPD_COMMANDS

    for pkg, commands in (("calibkit", CALIBKIT_COMMANDS), ("daemon", MOCAPD_COMMANDS)):
        for name, entry in commands.items():
            module = entry[0]
            found = handler_bodies((ROOT / pkg / "commands" / f"{module}.py")
                                   .read_text(encoding="utf-8"))
            assert found, f"{pkg}/commands/{module}.py ({name}): no command handler found"
            assert all(n > 0 for _, n in found), (module, found)
    source = ('import typer\napp = typer.Typer()\n'
              'def register(app):\n'
              '    @app.command("x")\n'
              '    def x(a: int = 1) -> None:\n'
              '        """Help\n\n        more help."""\n'
              + "        a += 1\n" * 61 +
              '    def helper():\n' + "        pass\n" * 70 +
              '@app.command()\ndef y():\n    return 1\n')
    assert sorted(handler_bodies(source)) == [("x", 61), ("y", 1)]


def test_the_limits_name_their_offenders(tmp_path):
    """A file over each limit is named with its count; one at the limit is not."""
    at, over = tmp_path / "at.py", tmp_path / "over.py"
    at.write_text("x = 1\n" * MAX_MODULE_LINES, encoding="utf-8")
    over.write_text("x = 1\n" * (MAX_MODULE_LINES + 1), encoding="utf-8")
    assert long_modules([at, over]) == [f"{over} ({MAX_MODULE_LINES + 1} lines)"]
    cmd = tmp_path / "cmd.py"
    cmd.write_text("@app.command('ok')\ndef ok():\n" + "    pass\n" * 60
                   + "@app.command('big')\ndef big():\n" + "    pass\n" * 61,
                   encoding="utf-8")
    assert long_handlers([cmd]) == [f"{cmd}:big (61 lines)"]
