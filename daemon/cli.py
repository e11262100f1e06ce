"""The `mocapd` command line: one Typer app; each command lives in daemon/commands/."""

from __future__ import annotations

from calibkit import __version__
from calibkit.clitools import build_app, run_app

# Command name -> (its module in daemon/commands/, which defines register(app); the first
# paragraph of its help, as `mocapd --help` shows it). Order here is the order of
# `mocapd --help`. The modules are imported only when their command runs (issue 31);
# tests/test_cli_startup.py checks this table against the commands themselves.
COMMANDS = {
    "start": ("start_cmd", "Track markers and rigid bodies and serve their poses until stopped "
              "(SIGTERM)."),
    "status": ("control_cmd", "Rate per camera, dropped frames, latency, bodies tracked, "
               "outputs."),
    "stop": ("control_cmd", "Stop the daemon cleanly (as SIGTERM does)."),
    "reload": ("control_cmd", "Re-read the configuration (as SIGHUP does)."),
    "record": ("control_cmd", "Record the cameras' blobs (.mcrec) or the poses and markers "
               "(.mcap), or stop."),
    "install-unit": ("unit_cmd", "Write mocapd.service, compile the daemon's kernels ahead of "
                     "its first start, and\nprint the systemctl commands that enable it."),
    "build-kernels": ("kernels_cmd", "Compile the daemon's kernels into the on-disk cache now "
                      "(about a minute on a\nsmall machine), so that `mocapd start` tracks "
                      "from its first second. Run it once\nafter installing or upgrading; "
                      "`mocapd install-unit` runs it for you."),
    "label": ("markerset_cmd", "Name every point of every frame; ghosts are left out."),
    "fill": ("markerset_cmd", "Fill the gaps of hidden markers; filled samples are marked (CSV "
             "column filled)."),
    "skeleton": ("markerset_cmd", "Joint centres by sphere fits, bone lengths; export motion "
                 "as BVH."),
    "evaluate": ("evaluate_cmd", "Line up a trajectory's clock and world frame with a "
                 "reference, then measure its\nabsolute and relative pose errors."),
    "track": ("track_cmd", "Find and pose rigid bodies in a file of 3D markers with the "
              "daemon's own rigid\ntracker; one CSV row per frame and body (see "
              "docs/track.md)."),
    "view": ("view_cmd", "Scrub through a take or a recording in the browser: a frame slider, "
             "play, the\nmarkers of the chosen frame with their names and a marker set's "
             "sticks."),
    "node": ("node_cmd", "Open cameras, detect blobs and publish them over Zenoh to a mocapd "
             "elsewhere."),
    "rigid-body": ("rigid_cmd", "Rigid-body definitions in the configuration."),
    "markerset": ("markerset_cmd", "Marker sets: learn one from labelled takes; check one on a "
                  "take."),
}

app = build_app("mocapd", "Track markers and rigid bodies with a calibrated rig and serve "
                "their poses over UDP, serial lines, NatNet and VRPN.", __version__,
                "daemon.commands", COMMANDS)


def main() -> None:
    try:
        run_app(app, "mocapd")
    except SystemExit as exc:
        from daemon.process.ending import end_now_if_armed

        end_now_if_armed(exc.code)  # `mocapd start` done and flushed: no teardown
        raise


if __name__ == "__main__":
    main()
