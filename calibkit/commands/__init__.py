"""The `calibkit` subcommands: one module each, every one with register(app).

A handler imports the library modules its work needs inside itself, on purpose: the CLI
loads a command's module for its --help too (and cli.py's COMMANDS table, not the modules,
gives `calibkit --help`), so a module imports only typer and light things at its top;
numpy, OpenCV, GTSAM and matplotlib would otherwise load for a help screen (issue 31).
"""
