"""`mocapd build-kernels` leaves nothing for any command to compile; a cold cache says so.

Each command runs in a child process (tests/kernel_probe.py) with its own NUMBA_CACHE_DIR,
first filled by `mocapd build-kernels`. The probe counts every compile numba announces
("numba:compile", which any dispatcher triggers and a cache load never does) and, per kernel
made through calibkit.core.jit, numba's cache counters. A command passes when nothing
compiled and it loaded kernels from the cache (so it did run compiled code, not numpy
twins). The inputs differ from build-kernels' own (sizes, seeds, files written and read
back) because a kernel is cached per argument types, not per data. Last, every kernel the
code base defines must have been loaded by at least one command, or be one only other
kernels call (inlined or linked into its callers' cached code, so never loaded alone).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tomli_w

ROOT = Path(__file__).resolve().parents[1]
PROBE = ROOT / "tests" / "kernel_probe.py"
NOTICE = "compiling the "
DOTS_YX = ((40, 50), (120, 200), (200, 90), (60, 280))  # the dots drawn in the camera image


def _env(cache: Path | None) -> dict:
    """The child's environment: numba's cache in `cache`, or (None) where the project keeps
    it, the cache `mocapd build-kernels` fills for every command."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    if cache is not None:
        env["NUMBA_CACHE_DIR"] = str(cache)
    return env


def _probe(cache: Path, out: Path, prog: str, *args, env: dict | None = None
           ) -> tuple[dict, str]:
    proc = subprocess.run([sys.executable, str(PROBE), str(out), prog, *map(str, args)],
                          cwd=out.parent, env=_env(cache) | (env or {}), capture_output=True,
                          text=True, timeout=900)
    assert out.exists(), proc.stderr[-2000:]
    report = json.loads(out.read_text())
    assert report["code"] == 0, proc.stderr[-2000:]
    return report, proc.stderr


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    """Small files for each command: rigid bodies' points, a person's points, a simulated
    recording of blobs with its rig, a camera image, daemon configurations."""
    import cv2

    from calibkit.synthetic import person, sim
    from daemon.formats.c3dio import Points, Take, write_points_csv
    from daemon.labelling.markerset import SHIPPED, MarkerSet

    d = tmp_path_factory.mktemp("kernels-inputs")
    truth, bodies = sim.rigid_body_motion(3, 300, fps=100.0, markers_per_body=[4, 4, 5],
                                          seed=5)
    keep = np.random.default_rng(5).random(len(truth.frame)) > 0.08
    write_points_csv(d / "rigid.csv", Points(truth.frame[keep], truth.xyz[keep]))
    late_first = np.argsort((truth.frame[keep] + 150) % 300, kind="stable")  # 150-299, 0-149
    write_points_csv(d / "rigid_unsorted.csv", Points(truth.frame[keep][late_first],
                                                      truth.xyz[keep][late_first]))
    (d / "bodies.toml").write_text(tomli_w.dumps({"rigid_body": [
        {"name": b.name, "id": int(b.id), "markers": b.markers_body.tolist()}
        for b in bodies]}))
    ms = MarkerSet.load(SHIPPED / "sim_person.toml")
    walk = person.walk(150, 100.0, noise_m=0.0008, seed=4)
    take = Take(walk.labels, walk.markers_m, 100.0).select(ms.labels)
    write_points_csv(d / "person.csv", Points.from_take(take, seed=4))
    image = np.random.default_rng(3).integers(0, 15, (240, 320), dtype=np.uint8)
    for y, x in DOTS_YX:
        cv2.circle(image, (x, y), 3, 230, -1)
    cv2.imwrite(str(d / "cam.png"), image)
    (d / "person.toml").write_text('markerset = "sim_person"\n[sim]\nperson = true\n'
                                   "cameras = 6\nbodies = 0\n")
    return d


@pytest.fixture(scope="module")
def built_cache() -> None:
    """The project's own kernel cache after `mocapd build-kernels`, as a user has it: on a
    fresh checkout the session's build (conftest) compiled it already, so this build only
    checks it (a second cold build in a private cache cost CI a minute and proved nothing
    more: the cold-cache test below is the control that compiles)."""
    cache = None
    proc = subprocess.run([sys.executable, "-m", "daemon.cli", "build-kernels"], cwd=ROOT,
                          env=_env(cache), capture_output=True, text=True, timeout=1800)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "kernels built in" in proc.stdout
    assert NOTICE not in proc.stderr  # build-kernels says what it compiles itself
    return cache


def _commands(d: Path, work: Path) -> dict[str, tuple]:
    """Each command that runs a compiled kernel, once; `mocapd track` on a points CSV both
    ways it runs (in windows, and whole when the frames are out of order)."""
    return {
        "mocapd track (points CSV)": ("mocapd", "track", d / "rigid.csv", "--bodies",
                                      d / "bodies.toml", "--rate", "100", "--out",
                                      work / "poses.csv"),
        "mocapd track (points CSV out of frame order: the whole take at once)": (
            "mocapd", "track", d / "rigid_unsorted.csv", "--bodies", d / "bodies.toml",
            "--rate", "100", "--out", work / "poses3.csv"),
        "mocapd track (Motive CSV)": (
            "mocapd", "track", ROOT / "fixtures/optitrack_rigidbody_csv/sample_optitrack_take.csv",
            "--bodies-from-file", "--out", work / "poses2.csv"),
        "mocapd label": ("mocapd", "label", d / "person.csv", "--markerset", "sim_person",
                         "--rate", "100", "--out", work / "labelled.csv"),
        "mocapd markerset check": ("mocapd", "markerset", "check", d / "person.csv",
                                   "--markerset", "sim_person"),
        "mocapd fill": ("mocapd", "fill", work / "labelled.csv", "--out", work / "filled.csv"),
        "calibkit sim rigid": ("calibkit", "sim", "rigid", "--cameras", "5", "--frames", "30",
                               "--out", work / "blobs.mcrec"),
        "calibkit triangulate": ("calibkit", "triangulate", "--rig", work / "blobs.rig.toml",
                                 "--from", work / "blobs.mcrec", "--out", work / "tri.csv"),
        "calibkit detect": ("calibkit", "detect", d / "cam.png", "--json", work / "b.json"),
        "mocapd start --sim": ("mocapd", "start", "--sim", "--fast", "--frames", "60",
                               "--sim-cameras", "4", "--runtime-dir", work / "rt1"),
        "mocapd start --sim (live labelling)": (
            "mocapd", "start", "--config", d / "person.toml", "--sim", "--fast", "--frames",
            "40", "--runtime-dir", work / "rt2"),
    }


def test_build_kernels_leaves_nothing_to_compile(built_cache, inputs, tmp_path):
    for k, (name, cmd) in enumerate(_commands(inputs, tmp_path).items()):
        report, err = _probe(built_cache, tmp_path / f"probe{k}.json", *cmd)
        assert report["compiled"] == [], f"{name} compiled {report['compiled']}"
        assert all(c["compiled"] == 0 for c in report["kernels"].values()), name
        assert NOTICE not in err, name
        if name.startswith("mocapd track (points CSV"):  # both of track's ways were taken
            assert ("frame numbers go back" in err) == ("out of frame order" in name), name
        if name.startswith(("mocapd track", "mocapd start", "calibkit tri", "calibkit det")):
            assert any(c["loaded"] for c in report["kernels"].values()), \
                f"{name} ran no compiled kernel"


def test_build_kernels_caches_every_kernel_of_the_code_base(built_cache):
    """Paths the commands above do not reach on small inputs (the compiled labeller of
    long takes, detection's rare second pass...) are built too: every kernel of every
    module that defines one has code in the cache, except those numba inlines into their
    callers (inline="always": never compiled alone)."""
    proc = subprocess.run([sys.executable, "-c", _LIST_ALL], env=_env(built_cache),
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    found = json.loads(proc.stdout.strip().splitlines()[-1])
    assert {n.rsplit(".", 1)[0] for n in found} >= {
        "daemon.analysis.point_tracks", "daemon.tracking.rigid_kernel",
        "daemon.tracking.tracker_kernel", "daemon.labelling.kernels",
        "calibkit.vision.detect_kernels", "calibkit.core.geometry_kernels"}
    missing = [n for n, (cached, inline) in found.items() if not cached and not inline]
    assert missing == []


_LIST_ALL = """
import importlib, json, pathlib
for path in sorted(pathlib.Path('.').glob('[cdp]*/**/*.py')):
    if 'calibkit.core.jit import jit' in path.read_text(encoding='utf-8'):
        importlib.import_module('.'.join(path.with_suffix('').parts))
from calibkit.core.jit import is_cached, kernel_name, kernels
print(json.dumps({kernel_name(k): (is_cached(k), k.targetoptions.get('inline') == 'always')
                  for k in kernels()}))
"""


def test_a_cold_cache_compiles_and_says_so(inputs, tmp_path):
    """The control: with an empty cache the same probe sees the compiles, and the command
    prints the one notice line per kernel module on stderr. The command is `calibkit
    detect` on one small image, the cheapest that compiles: two kernel modules, about 13 s
    of CPU where `mocapd track` (point tracks and rigid fits) took 19 s; what is checked,
    a real compile seen and said once per module, is the same for any kernel. LLVM's
    optimisation is off (NUMBA_OPT=0: 12.7 s instead of 17.9 s, load about 1): numba types,
    lowers, compiles and caches each kernel as ever, and announces it the same; only the
    machine code is slower, in a private cache thrown away after."""
    report, err = _probe(tmp_path / "cold", tmp_path / "probe.json", "calibkit", "detect",
                         inputs / "cam.png", "--json", tmp_path / "b.json",
                         env={"NUMBA_OPT": "0"})
    assert "calibkit.vision.detect_kernels.find_regions" in report["compiled"]
    assert report["kernels"]["calibkit.vision.detect_kernels.find_regions"]["compiled"] == 1
    assert not any(c["loaded"] for c in report["kernels"].values())  # nothing was cached
    notices = [ln for ln in err.splitlines() if ln.startswith(NOTICE)]
    assert any("calibkit.vision.detect_kernels" in ln for ln in notices)
    assert len(notices) == len(set(notices)) and all("build-kernels" in ln for ln in notices)
    # and the freshly compiled code found the four dots the fixture drew, where it drew them
    blobs = json.loads((tmp_path / "b.json").read_text())["blobs"]
    found = sorted((round(b["u"]), round(b["v"])) for b in blobs)
    assert found == sorted((x, y) for y, x in DOTS_YX), found
