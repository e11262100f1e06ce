"""The `calibkit` subcommands: one module each, every one with register(app).

A handler imports the library modules its work needs inside itself, on purpose: the CLI
loads every command module to build its help, and the calibration stack (GTSAM, OpenCV's
solvers, matplotlib) would otherwise load for `calibkit --help` or a one-line check.
"""
