"""The `calibkit` command line: one Typer app; each command lives in calibkit/commands/."""

from __future__ import annotations

from calibkit import __version__
from calibkit.clitools import build_app, run_app

# Command name -> (its module in calibkit/commands/, which defines register(app); the first
# paragraph of its help, as `calibkit --help` shows it). Order here is the order of
# `calibkit --help`. The modules are imported only when their command runs (issue 31);
# tests/test_cli_startup.py checks this table against the commands themselves.
COMMANDS = {
    "demo": ("demo_cmd", "The whole calibration chain on a simulated rig, as a user runs it: "
             "intrinsics\nfrom a monitor, poses from a projector, then a wand; check the result "
             "against the\nsimulator's truth, reconstruct a capture with it, then track rigid "
             "bodies with\nmocapd and score the poses."),
    "detect": ("detect_cmd", "Find markers in images and print them; tune the options with "
               "--preview."),
    "mask": ("detect_cmd", "Build a mask of static reflections and lamps from frames with no "
             "markers."),
    "triangulate": ("triangulate_cmd", "Match unlabelled blobs across cameras and triangulate "
                    "them, frame by frame."),
    "displays": ("displays_cmd", "List monitors: index, resolution, physical size and pixel "
                 "pitch (the scale of\n`calibkit intrinsic --display`)."),
    "intrinsic": ("intrinsic_cmd", "Calibrate one camera's intrinsics (focal lengths, principal "
                  "point, distortion)."),
    "extrinsic": ("extrinsic_cmd", "Every camera's pose from projected dots on the floor and a "
                  "table top."),
    "wand": ("wand_cmd", "Calibrate every camera at once from a wand waved through the volume."),
    "floor": ("floor_cmd", "Set the world frame from the floor."),
    "compare": ("compare_cmd", "Per camera: position (mm), orientation (deg), focal length (%) "
                "and principal point\n(px) differences; the RMS 3D difference of a grid of "
                "points filling the volume; how\nmuch longer B measures lengths than A (the "
                "alignment's scale); and a verdict."),
    "convert": ("convert_cmd", "Convert observations between our recording format and the "
                "plain CSV\n(frame,camera,t_ns,u,v,area,peak), or read a DLTdv/easyWand xypts "
                "file into either\n(docs/easywand.md); ground truth travels along."),
    "sim": ("sim_cmd", "Simulated rigs and captures with ground truth."),
    "rig": ("rig_cmd", "Show rig files; import and export other tools' calibrations."),
}

app = build_app("calibkit", "Calibrate a rig of motion-capture cameras. Add --sim to any "
                "command that reads cameras, a monitor or a capture to use the built-in "
                "simulated rig; the others say in their help what they read.", __version__,
                "calibkit.commands", COMMANDS)


def main() -> None:
    run_app(app, "calibkit")


if __name__ == "__main__":
    main()
