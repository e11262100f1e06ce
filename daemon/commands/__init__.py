"""The `mocapd` subcommands: one module each, every one with register(app)."""
