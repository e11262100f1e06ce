"""Layer boundaries besides the simulator's: calibration and vision code never import the
OpenGL display (a capture is handed a display object by its command), the daemon never
imports calibkit's command handlers (what both share lives in calibkit.clitools or
calibkit.core), calibkit's core layer (calibkit.core, calibkit.cameras) imports nothing
above it, no module of ours imports itself through others (no import cycles), the daemon's
packages import only the layers below them (the order in DAEMON_LAYERS, as
docs/architecture.md draws it), and projector needs nothing of calibkit above its core."""

from __future__ import annotations

import ast
import functools
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DISPLAY = "projector.display"


@functools.cache  # each file parsed once a run, not once per test (the sets stay unchanged)
def _imports(path: Path) -> frozenset[str]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return frozenset(found)


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


# ---- the core layer and import cycles --------------------------------------------------------

PACKAGES = ("calibkit", "daemon", "projector")
# what calibkit's core layer (the camera model, files, errors, and the cameras) stays below
UPPER = ("calibkit.commands", "calibkit.synthetic", "daemon", "moderngl", DISPLAY)
CORE = ["calibkit/core", "calibkit/cameras"]


def test_the_core_and_the_cameras_import_no_upper_layer():
    assert (ROOT / "calibkit" / "cameras" / "spec.py").is_file()  # the scan covers them
    for prefix in UPPER:
        assert _offenders(CORE, prefix) == {}, prefix


def test_importing_the_core_and_the_cameras_loads_no_upper_layer():
    names = sorted(_module_name(f) for folder in CORE for f in (ROOT / folder).glob("*.py"))
    assert "calibkit.cameras.basler" in names and "calibkit.core.rigfile" in names
    code = ("import importlib, sys\n"
            f"for name in {names!r}:\n    importlib.import_module(name)\n"
            f"print(sorted(m for m in sys.modules if m.startswith({UPPER!r})))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, check=True)
    assert out.stdout.strip() == "[]"


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    return ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)


def _runtime_imports(tree: ast.AST):
    """Import statements that run, at any level (inside functions too: a lazy import is
    still a dependency), but not those under `if TYPE_CHECKING:` (annotations only)."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            yield from (n for child in node.orelse for n in _runtime_imports_of(child))
            continue
        yield from _runtime_imports_of(node)


def _runtime_imports_of(node: ast.AST):
    if isinstance(node, (ast.Import, ast.ImportFrom)):
        yield node
    else:
        yield from _runtime_imports(node)


def import_graph() -> dict[str, set[str]]:
    """Module -> the modules of our packages it imports. `from a.b import c` names module
    a.b.c when there is one, else a.b (an import of a name defined in it). Built once a run
    (four tests read it; parsing every file took seconds each time); each caller gets its
    own copy."""
    return {name: set(deps) for name, deps in _import_graph().items()}


@functools.cache
def _import_graph() -> dict[str, frozenset[str]]:
    files = {_module_name(f): f for pkg in PACKAGES for f in (ROOT / pkg).rglob("*.py")}

    def ours(name: str) -> str | None:
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name or None

    graph = {}
    for name, path in files.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        found = set()
        for node in _runtime_imports(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                found.update(ours(a.name) for a in node.names)
                continue
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            found.update(ours(f"{base}.{a.name}") for a in node.names)
        graph[name] = frozenset(found - {None, name})
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(out)


def test_the_cycle_finder_finds_cycles():
    g = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"d"}, "f": {"g"},
         "g": {"f"}}
    assert cycles(g) == [["a", "b", "c"], ["f", "g"]]


def test_our_packages_have_no_import_cycles():
    graph = import_graph()
    # the scan sees lazy imports and resolves package-relative names
    assert "calibkit.core.rigfile" in graph["calibkit.core.camera"]
    assert "calibkit.cameras.spec" in graph["calibkit.cameras"]
    assert sum(len(v) for v in graph.values()) > 300
    assert cycles(graph) == []


# ---- the daemon's layers ---------------------------------------------------------------------

# Bottom to top; a package imports its own modules and those of lower layers only, never a
# package of its own layer or above (packages sharing a layer do not know each other).
DAEMON_LAYERS = [
    ("process",),                          # plumbing of a long-running process
    ("tracking",),                         # live 3D markers and rigid bodies
    ("formats",),                          # files of markers and poses
    ("labelling",),                        # marker sets and the labeller
    ("analysis", "capture", "publish"),    # whole takes; frame sets; one file per protocol
    ("config",),                           # mocapd.toml
    ("nodes",),                            # capture nodes and their daemon-side source
    ("synthetic",),                        # the simulator and its scorers
    ("service",),                          # the running daemon
    ("view",),                             # the live view
    ("commands",),                         # the command lines' handlers and their runs
    ("cli",),                              # the entry point
]


def _daemon_part(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "daemon" and len(parts) > 1 else None


def daemon_layer_violations(graph: dict[str, set[str]]) -> list[str]:
    level = {pkg: i for i, layer in enumerate(DAEMON_LAYERS) for pkg in layer}
    out = []
    for module, deps in sorted(graph.items()):
        own = _daemon_part(module)
        if own is None:
            continue
        for dep in sorted(deps):
            other = _daemon_part(dep)
            if other is not None and other != own and level[other] >= level[own]:
                out.append(f"{module} -> {dep}")
    return out


def test_every_daemon_package_has_a_layer():
    graph = import_graph()
    found = {_daemon_part(m) for m in graph} - {None}
    placed = {pkg for layer in DAEMON_LAYERS for pkg in layer}
    assert {"tracking", "labelling", "formats", "service"} <= found  # the scan sees them
    assert found == placed


def test_the_layer_check_finds_an_upward_import():
    graph = {"daemon.tracking.tracker": {"daemon.service.daemon"},
             "daemon.capture.pipeline": {"daemon.publish.base"},
             "daemon.service.daemon": {"daemon.capture.pipeline", "daemon.service.control"}}
    assert daemon_layer_violations(graph) == [
        "daemon.capture.pipeline -> daemon.publish.base",
        "daemon.tracking.tracker -> daemon.service.daemon"]


def test_the_daemon_packages_import_only_lower_layers():
    graph = import_graph()
    assert "daemon.tracking.tracker" in graph["daemon.capture.pipeline"]  # the scan sees them
    assert daemon_layer_violations(graph) == []


def test_only_the_entry_point_imports_the_command_handlers():
    graph = import_graph()
    # the scan sees an import of a command module (here one command's of another's run)
    assert "daemon.commands.start_run" in graph["daemon.commands.start_cmd"]
    users = {m for m, deps in graph.items() if not m.startswith("daemon.commands")
             and any(d.startswith("daemon.commands") for d in deps)}
    assert users <= {"daemon.cli"}  # daemon.cli loads them by name, when a command runs


def test_projector_needs_only_calibkits_core():
    hits = {f: [m for m in ms if not m.startswith("calibkit.core")]
            for f, ms in _offenders(["projector"], "calibkit").items()}
    assert {f: ms for f, ms in hits.items() if ms} == {}
    assert _offenders(["calibkit/core", "calibkit/cameras"], "projector") == {}
