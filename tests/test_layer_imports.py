"""Layer boundaries besides the simulator's: calibration and vision code never import the
OpenGL display (a capture is handed a display object by its command), and the daemon never
imports calibkit's command handlers (what both share lives in calibkit.clitools or
calibkit.core)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DISPLAY = "projector.display"


def _imports(path: Path) -> set[str]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return found


def _offenders(folders: list[str], prefix: str) -> dict[str, list[str]]:
    out = {}
    for folder in folders:
        for f in sorted((ROOT / folder).rglob("*.py")):
            hits = sorted(m for m in _imports(f) if m == prefix or m.startswith(prefix + "."))
            if hits:
                out[str(f.relative_to(ROOT))] = hits
    return out


def test_calibration_and_vision_never_import_the_display():
    assert _offenders(["calibkit/calibrate", "calibkit/vision", "calibkit/core"], DISPLAY) == {}


def test_the_daemon_never_imports_calibkit_commands():
    assert _offenders(["daemon"], "calibkit.commands") == {}


def test_importing_the_calibration_modules_loads_no_display():
    names = sorted(".".join(f.relative_to(ROOT).with_suffix("").parts)
                   for f in (ROOT / "calibkit" / "calibrate").glob("*.py")
                   if f.name != "__init__.py")
    assert "calibkit.calibrate.extrinsic_capture" in names
    code = ("import importlib, sys\n"
            f"for name in {names!r}:\n    importlib.import_module(name)\n"
            f"print({DISPLAY!r} in sys.modules, 'moderngl' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, check=True)
    assert out.stdout.split() == ["False", "False"]
