"""The daemon's configuration: mocapd.toml read, checked and turned into a Config."""
