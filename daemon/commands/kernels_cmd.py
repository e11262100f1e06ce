"""`mocapd build-kernels`: compile the daemon's numba kernels into the on-disk cache ahead
of its first start.

Why: the tracker, rigid-body, correspondence, detection and labelling kernels are compiled
by numba the first time they run (tens of seconds on a small machine), and cached on disk
(next to the modules in __pycache__ when that folder is writable, else in numba's user-wide
cache or NUMBA_CACHE_DIR). A daemon that compiles at its first start tracks nothing
meanwhile. This runs each kernel once, on the same paths the daemon runs them (a short
simulated capture tracked, defined and posed; a camera image detected; a marker set
labelled), so the next start loads them from the cache. `mocapd install-unit` runs it, and
so does the test suite before its live tests.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from calibkit.core.errors import UserError


def _tracking(folder: Path) -> None:
    """The tracker, the epipolar correspondence, rigid bodies defined live and posed: a
    second of a small simulated rig, as fast as it goes."""
    from daemon.config import Config, SimConfig
    from daemon.service import Daemon

    sim = SimConfig(cameras=4, bodies=2, fps=60.0, seed=1, realtime=False)
    Daemon(Config(sim=sim, fps=sim.fps, runtime_dir=folder / "rt")).run(frames=40)


def _detection(folder: Path) -> None:
    """Blob detection on a live camera's image: grey and colour, every mode."""
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


def _labelling(folder: Path) -> None:
    """Live marker-set labelling: the simulated person in its shipped marker set."""
    from daemon.config import Config, SimConfig
    from daemon.markers.markerset import SHIPPED
    from daemon.service import Daemon

    sim = SimConfig(cameras=6, bodies=0, fps=60.0, seed=1, realtime=False, person=True)
    Daemon(Config(sim=sim, fps=sim.fps, markerset=SHIPPED / "sim_person.toml",
                  runtime_dir=folder / "rt-label")).run(frames=40)


STEPS = (("tracking (tracker, correspondence, rigid bodies)", _tracking),
         ("detection (camera images)", _detection),
         ("labelling (marker sets)", _labelling))


def build_kernels(echo=print) -> float:
    """Compile every kernel into the cache, each step's time echoed; the total in s."""
    import logging

    quiet = logging.getLogger("mocapd")
    level = quiet.level
    quiet.setLevel(logging.WARNING)  # the runs' own progress lines are not the user's
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
    return time.monotonic() - began


def cache_location() -> str:
    """Where numba keeps the compiled kernels of this installation."""
    import os

    import daemon

    if os.environ.get("NUMBA_CACHE_DIR"):
        return os.environ["NUMBA_CACHE_DIR"]
    pkg = Path(daemon.__file__).parent / "__pycache__"
    if os.access(pkg if pkg.exists() else pkg.parent, os.W_OK):
        return f"{pkg} (and calibkit's, beside its modules)"
    return "numba's user-wide cache (~/.cache/numba), or set NUMBA_CACHE_DIR"


def register(app: typer.Typer) -> None:
    @app.command("build-kernels")
    def build(
        quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Only the total.")]
        = False,
    ) -> None:
        """Compile the daemon's kernels into the on-disk cache now (about a minute on a
        small machine), so that `mocapd start` tracks from its first second. Run it once
        after installing or upgrading; `mocapd install-unit` runs it for you."""
        try:
            total = build_kernels((lambda _: None) if quiet else typer.echo)
        except UserError:
            raise
        except Exception as exc:  # noqa: BLE001 - a compiler failure: one clear line
            raise UserError(f"building the kernels failed: {exc}") from None
        typer.echo(f"kernels built in {total:.1f} s; cached in {cache_location()}")
