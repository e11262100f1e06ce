"""The `mocapd` subcommands: one module each, every one with register(app).

A handler imports the library modules its work needs inside itself, on purpose: the CLI
loads a command's module for its --help too (cli.py's COMMANDS table, not the modules,
gives `mocapd --help`; issue 31), and `mocapd start` must reach its first pose
quickly, without loading the labelling, file-format or report stacks it does not use.
"""
