"""`mocapd build-kernels`: compile every numba kernel any command uses into the on-disk cache.

Why: the tracker, rigid-body, correspondence, detection, labelling and offline-tracking
kernels are compiled by numba the first time they run (tens of seconds to minutes on a small
machine), and cached on disk (next to the modules in __pycache__ when that folder is
writable, else in numba's user-wide cache or NUMBA_CACHE_DIR). A daemon that compiles at
its first start tracks nothing meanwhile, and a first `mocapd track` sits silent for
minutes. This runs each kernel once, on the same paths the commands run them (a short
simulated capture tracked, defined and posed live; a camera image detected; a marker set
labelled live and offline; a file of 3D markers tracked offline; blobs triangulated), so
later runs load them from the cache. A kernel is cached per argument types: each step calls
the commands' own functions, so the types are theirs. `mocapd install-unit` runs it, and so
does the test suite before its live tests; tests/test_kernels_cache.py proves each command
then compiles nothing.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Annotated

import typer

from calibkit.core.errors import UserError


def _tracking(folder: Path) -> None:
    """The tracker, the epipolar correspondence, rigid bodies defined live and posed: a
    second of a small simulated rig, as fast as it goes."""
    from daemon.config.mocapd import Config, SimConfig
    from daemon.service.daemon import Daemon

    sim = SimConfig(cameras=4, bodies=2, fps=60.0, seed=1, realtime=False)
    Daemon(Config(sim=sim, fps=sim.fps, runtime_dir=folder / "rt")).run(frames=40)


def _detection(folder: Path) -> None:
    """Blob detection on a live camera's image: grey and colour, every mode."""
    import numpy as np

    from calibkit.vision.detect import DetectorConfig, detect

    rng = np.random.default_rng(0)
    grey = rng.integers(0, 12, (120, 160), dtype=np.uint8)
    for y, x in ((30, 40), (80, 110), (60, 20)):
        grey[y - 2:y + 3, x - 2:x + 3] = 220
    colour = np.repeat(grey[:, :, None], 3, axis=2)
    for cfg in (DetectorConfig(), DetectorConfig(threshold=100.0),
                DetectorConfig(mode="multi"), DetectorConfig(min_roundness=0.3)):
        detect(grey, cfg)
    detect(colour, DetectorConfig(hsv_ranges=(((0, 0, 150), (179, 60, 255)),)))
    stripes = np.zeros((120, 160), dtype=np.uint8)
    stripes[:, ::2] = 200  # more runs than the first guess holds: the bound's kernel too
    detect(stripes, DetectorConfig(threshold=100.0))


def _labelling(folder: Path) -> None:
    """Live marker-set labelling: the simulated person in its shipped marker set."""
    from daemon.config.mocapd import Config, SimConfig
    from daemon.labelling.markerset import SHIPPED
    from daemon.service.daemon import Daemon

    sim = SimConfig(cameras=6, bodies=0, fps=60.0, seed=1, realtime=False, person=True)
    Daemon(Config(sim=sim, fps=sim.fps, markerset=SHIPPED / "sim_person.toml",
                  runtime_dir=folder / "rt-label")).run(frames=40)


def _offline_tracking(folder: Path) -> None:
    """`mocapd track`: identities of anonymous 3D points and the rigid tracker over a take
    (steady runs fitted at once and frames through update()), as track_file runs it."""
    import numpy as np

    from calibkit.synthetic import sim
    from daemon.analysis.offline_track import cloud_from_points
    from daemon.analysis.track_file import track_file
    from daemon.formats.c3dio import Points
    from daemon.tracking.rigid import BodyDef, RigidConfig

    truth, bodies = sim.rigid_body_motion(2, 240, fps=120.0, markers_per_body=[4, 5], seed=1)
    keep = np.random.default_rng(1).random(len(truth.frame)) > 0.05  # some markers hidden
    points = Points(truth.frame[keep], truth.xyz[keep])
    defs = [BodyDef(b.name, b.id, b.markers_body, np.zeros(3), 4, 3, 0.0) for b in bodies]
    track_file(cloud_from_points(points, 120.0), None, defs, RigidConfig(), 30.0, 20.0)


def _offline_labelling(folder: Path) -> None:
    """`mocapd label` and `mocapd markerset check` on unlabelled points: the start from the
    set alone on a window, tracking, verification; the compiled labeller (label_take uses
    it on long takes), on a take with hidden markers and ghosts so every stage runs."""
    from calibkit.synthetic import person
    from daemon.formats.c3dio import Take
    from daemon.labelling.markerset import SHIPPED, MarkerSet
    from daemon.labelling.markerset_fit import check_points
    from daemon.labelling.offline import label_take
    from daemon.synthetic.labelling import hide_spans, points_with_ghosts

    ms = MarkerSet.load(SHIPPED / "sim_person.toml")
    walk = person.walk(240, 120.0, noise_m=0.0005, seed=1)
    take = hide_spans(Take(walk.labels, walk.markers_m, 120.0).select(ms.labels), 0.1, seed=1)
    points, _ = points_with_ghosts(take, 2, seed=1)
    for compiled in (True, False):
        label_take(points, ms, 120.0, options={"compiled": compiled})
    check_points(ms, points.split()[1])


def _triangulation(folder: Path) -> None:
    """`calibkit triangulate`: blobs of a simulated recording, written and read back as the
    command reads them, matched and triangulated."""
    from calibkit.core.recording import load_observations, save_observations
    from calibkit.synthetic import sim
    from calibkit.vision.correspondence import CorrespondenceConfig
    from calibkit.vision.reconstruct import reconstruct

    rig = sim.make_rig(4, seed=1)
    truth, _ = sim.rigid_body_motion(2, 20, fps=60.0, seed=1)
    save_observations(folder / "blobs.mcrec", sim.observe(rig, truth, noise_px=0.1,
                                                           fps=60.0, seed=1), truth, rig)
    obs, _ = load_observations(folder / "blobs.mcrec", rig)
    reconstruct(rig, obs, CorrespondenceConfig(), None, False, set())


STEPS = (("tracking (tracker, correspondence, rigid bodies)", _tracking),
         ("detection (camera images)", _detection),
         ("labelling (marker sets, live)", _labelling),
         ("offline tracking (mocapd track)", _offline_tracking),
         ("offline labelling (mocapd label, markerset check)", _offline_labelling),
         ("triangulation (calibkit triangulate)", _triangulation))


def build_kernels(echo=print) -> float:
    """Compile every kernel into the cache, each step's time echoed; the total in s."""
    import logging

    # deferred on purpose: loads numba, which `mocapd --help` must not wait for
    from calibkit.core.jit import set_compile_notice

    quiet = logging.getLogger("mocapd")
    level = quiet.level
    quiet.setLevel(logging.WARNING)  # the runs' own progress lines are not the user's
    set_compile_notice(False)  # compiling is this command's purpose: its steps say so
    began = time.monotonic()
    try:
        with tempfile.TemporaryDirectory(prefix="mocapd-kernels-") as tmp:
            for k, (name, step) in enumerate(STEPS, 1):
                t0 = time.monotonic()
                echo(f"[{k}/{len(STEPS)}] {name} ...")
                step(Path(tmp))
                echo(f"[{k}/{len(STEPS)}] {name}: {time.monotonic() - t0:.1f} s")
    finally:
        quiet.setLevel(level)
        set_compile_notice(True)
    return time.monotonic() - began


def cache_location() -> str:
    """Where numba keeps the compiled kernels of this installation."""
    import os

    import daemon

    if os.environ.get("NUMBA_CACHE_DIR"):
        return os.environ["NUMBA_CACHE_DIR"]
    pkg = Path(daemon.__file__).parent  # each kernel beside its module: tracking/, labelling/...
    if os.access(pkg, os.W_OK):
        return f"{pkg}/*/__pycache__ (and calibkit's, beside its modules)"
    return "numba's user-wide cache (~/.cache/numba), or set NUMBA_CACHE_DIR"


def register(app: typer.Typer) -> None:
    @app.command("build-kernels")
    def build(
        quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Only the total.")]
        = False,
    ) -> None:
        """Compile the daemon's kernels into the on-disk cache now (about a minute on a
        small machine), so that `mocapd start` tracks from its first second. Run it once
        after installing or upgrading; `mocapd install-unit` runs it for you.

        Reads nothing: it runs every kernel on small simulated scenes of its own."""
        try:
            total = build_kernels((lambda _: None) if quiet else typer.echo)
        except UserError:
            raise
        except Exception as exc:  # noqa: BLE001 - a compiler failure: one clear line
            raise UserError(f"building the kernels failed: {exc}") from None
        typer.echo(f"kernels built in {total:.1f} s; cached in {cache_location()}")
