"""Import boundaries: the estimate never sees the simulator, and calibkit never the daemon.

Estimating code (calibration, detection, correspondence, tracking, labelling, publishing)
gets only what hardware would give. The simulator and the scorers that read its truth sit in
`calibkit.synthetic` and `daemon.synthetic`; only the edges that set a run up (the command
handlers, the CLIs and the daemon's service, which plugs simulated cameras in for `--sim`)
may import them.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SYNTHETIC = ("calibkit.synthetic", "daemon.synthetic")
# the edges that wire a run together; everything else under calibkit/ and daemon/ estimates
EDGES = ("calibkit/synthetic/", "daemon/synthetic/", "calibkit/commands/", "daemon/commands/",
         "calibkit/cli.py", "daemon/cli.py", "daemon/service/daemon.py")


def _module(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """Every module a file imports, at any level (function-level imports included)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = _module(path).rsplit(".", 1)[0] if path.name != "__init__.py" else _module(path)
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return found


def _estimating_files() -> list[Path]:
    files = sorted((ROOT / "calibkit").rglob("*.py")) + sorted((ROOT / "daemon").rglob("*.py"))
    return [f for f in files
            if not any(str(f.relative_to(ROOT)).startswith(e) for e in EDGES)]


def _hits(path: Path, prefixes) -> list[str]:
    return sorted(m for m in _imports(path)
                  if any(m == p or m.startswith(p + ".") for p in prefixes))


def test_the_estimating_modules_are_many():
    # A guard against the scan silently covering nothing (a moved folder, a bad glob).
    names = {_module(f) for f in _estimating_files()}
    assert {"calibkit.vision.detect", "calibkit.calibrate.wand_solve",
            "calibkit.vision.correspondence",
            "daemon.tracking.tracker", "daemon.labelling.labeller",
            "daemon.capture.pipeline"} <= names
    assert not any(n.startswith(SYNTHETIC) for n in names)


@pytest.mark.parametrize("path", _estimating_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_estimating_code_never_imports_the_simulator(path):
    assert _hits(path, SYNTHETIC) == []


def test_calibkit_never_imports_the_daemon():
    files = sorted((ROOT / "calibkit").rglob("*.py"))
    offenders = {str(f.relative_to(ROOT)): _hits(f, ("daemon",)) for f in files}
    assert {k: v for k, v in offenders.items() if v} == {}


def test_the_scan_sees_function_level_and_relative_imports(tmp_path, monkeypatch):
    pkg = tmp_path / "calibkit"
    pkg.mkdir()
    probe = pkg / "probe.py"
    probe.write_text("def f():\n    from calibkit.synthetic import sim\n"
                     "from .synthetic.truthcheck import score_points\n", encoding="utf-8")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert _hits(probe, SYNTHETIC) == ["calibkit.synthetic", "calibkit.synthetic.sim",
                                       "calibkit.synthetic.truthcheck",
                                       "calibkit.synthetic.truthcheck.score_points"]


def test_importing_every_estimating_module_loads_no_simulator():
    # At run time too: nothing reaches the simulator through another module's imports.
    names = [_module(f) for f in _estimating_files()]
    code = ("import importlib, sys\n"
            f"for name in {names!r}:\n    importlib.import_module(name)\n"
            f"bad = sorted(m for m in sys.modules if m.startswith({SYNTHETIC!r}))\n"
            "print(' '.join(bad))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, check=True)
    assert out.stdout.strip() == ""
