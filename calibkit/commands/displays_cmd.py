"""`calibkit displays`: the monitors and projectors attached, with their pixel pitch."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from calibkit.clitools import print_table, write_json
from projector.screens import list_screens, parse_pixel_pitch


def register(app: typer.Typer) -> None:
    @app.command("displays")
    def displays_command(
        pixel_pitch_text: Annotated[str | None, typer.Option(
            "--pixel-pitch", help="Override the pixel pitch the monitors report: mm per "
                                  "pixel, or WIDTH_MM/WIDTH_PX.")] = None,
        json_path: Annotated[Path | None, typer.Option(
            "--json", help="Write the list as JSON.")] = None,
        sim: Annotated[bool, typer.Option(
            "--sim", help="The simulated computer's monitor, the one `calibkit intrinsic "
                          "--display --sim` draws on.")] = False,
    ) -> None:
        """List monitors: index, resolution, physical size and pixel pitch (the scale of
        `calibkit intrinsic --display`).

        Reads the display server this computer runs (glfw, else xrandr), or with --sim the
        simulated one."""
        pixel_pitch = parse_pixel_pitch(pixel_pitch_text)
        if sim:
            from calibkit.synthetic.monitor import MonitorSimConfig
            from calibkit.synthetic.monitor_bench import sim_screens

            screens = sim_screens(MonitorSimConfig())
        else:
            screens = list_screens()
        rows, data = [], []
        for s in screens:
            pitch = pixel_pitch if pixel_pitch is not None else s.pixel_pitch_mm
            rows.append([s.index, s.name, f"{s.width_px}x{s.height_px}",
                         f"{s.width_mm:.0f}x{s.height_mm:.0f}" if s.width_mm else "unknown",
                         float(pitch) if pitch else float("nan"), s.refresh_hz])
            data.append({"index": s.index, "name": s.name, "width_px": s.width_px,
                         "height_px": s.height_px, "width_mm": s.width_mm,
                         "height_mm": s.height_mm, "pixel_pitch_mm": pitch or None,
                         "x_px": s.x_px, "y_px": s.y_px, "refresh_hz": s.refresh_hz})
        print_table(rows, ["#", "name", "pixels", "size_mm", "pitch_mm", "hz"])
        if any(not d["pixel_pitch_mm"] for d in data):
            print("a monitor without a size: measure its picture width and pass "
                  "--pixel-pitch WIDTH_MM/PIXELS to calibkit intrinsic")
        if json_path is not None:
            write_json(json_path, {"displays": data})
