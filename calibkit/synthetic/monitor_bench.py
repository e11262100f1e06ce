"""The hardware of `calibkit intrinsic --display --sim`: a simulated monitor showing what the
display code draws, and a simulated camera watching it.

The command runs its real monitor path (the screen and its pixel pitch, the schedule made
for that screen, the capture, the guidance between views) with two things swapped at the
edge. The full-screen window becomes the same renderer drawing off-screen
(projector.display.OffscreenDisplay): every frame the capture asks it to show is drawn by
the display code and handed, as drawn, to the simulated monitor's glass. The camera becomes
a FrameSource whose frames are that glass as the simulated camera sees it, tilted in front
of it, through its true lens, with the display's latency, blur and sensor noise
(calibkit.synthetic.monitor). The user's "tilt the monitor, then press Enter" becomes the
simulator moving to its next view. The estimate gets only the frames; the true camera stays
here, in `SimBench.truth`, for scorers.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

from calibkit.cameras import Capabilities, Frame, FrameSource
from calibkit.core.camera import Camera
from calibkit.core.errors import UserError
from calibkit.synthetic.monitor import MonitorSim, MonitorSimConfig, make_monitor_sim
from projector.display import OffscreenDisplay
from projector.screens import Screen

REFRESH_HZ = 60.0


def sim_screens(config: MonitorSimConfig) -> list[Screen]:
    """The monitors of the simulated computer, as `calibkit displays` lists real ones: one,
    its physical size in whole millimetres as an EDID reports it (so the pitch the command
    reads is off by the rounding, as on real hardware; intrinsics do not depend on it)."""
    w, h = config.screen_px
    pitch = config.pixel_pitch_mm
    return [Screen(0, "simulated monitor", w, h, float(round(w * pitch)),
                   float(round(h * pitch)), 0, 0, REFRESH_HZ)]


def pick_sim_screen(index: int, pixel_pitch_mm: float | None, config: MonitorSimConfig
                    ) -> tuple[Screen, float]:
    """The simulated screen to draw on and its pitch (an override wins over the EDID's),
    with the same checks as projector.screens.pick_screen."""
    screens = sim_screens(config)
    if not 0 <= index < len(screens):
        raise UserError(f"no monitor {index}: the simulated computer has {len(screens)} "
                        "(see `calibkit displays --sim`)")
    screen = screens[index]
    return screen, pixel_pitch_mm if pixel_pitch_mm is not None else screen.pixel_pitch_mm


class MonitorCamera(FrameSource):
    """The simulated camera as a live source: each frame is the next one it delivers."""

    capabilities = Capabilities(live=True)

    def __init__(self, simulator: MonitorSim, name: str) -> None:
        self.simulator = simulator
        self.camera = name
        self.fps = simulator.config.fps
        self._index = 0

    def __iter__(self) -> Iterator[Frame]:
        while True:
            image = self.simulator.grab()
            start_s = self.simulator.t_s - 1.0 / self.simulator.config.fps
            yield Frame(self.camera, self._index, round(start_s * 1e9), image)
            self._index += 1

    def close(self) -> None:
        self.simulator.close()


@dataclass(eq=False)
class SimBench:
    """What the command's monitor path needs (a screen, its pitch, a window, a camera, and a
    way to tilt the monitor), simulated; `truth` is the true camera, for scorers only."""

    screen: Screen
    pitch_mm: float
    window: OffscreenDisplay
    source: MonitorCamera
    truth: Camera

    def tilt(self, view: int, n_views: int) -> None:
        """The user holds the monitor in view `view`, tilted (takes a moment)."""
        self.source.simulator.set_view(view)

    def close(self) -> None:
        self.window.close()
        self.source.close()

    def __enter__(self) -> SimBench:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_bench(truth: Camera, n_views: int, fill: float, config: MonitorSimConfig,
               monitor: int = 0, pixel_pitch_mm: float | None = None) -> SimBench:
    """The simulated monitor `monitor` (its pitch as reported, or `pixel_pitch_mm`) and the
    camera `truth` watching it over `n_views` tilted views."""
    screen, pitch = pick_sim_screen(monitor, pixel_pitch_mm, config)
    simulator = make_monitor_sim(n_views, truth.size, config.seed, config, camera=truth,
                                 fill=fill)
    try:
        window = OffscreenDisplay((screen.width_px, screen.height_px))
    except BaseException:
        simulator.close()
        raise
    window.watch(simulator.show_image)
    return SimBench(screen, pitch, window, MonitorCamera(simulator, truth.name), truth)
