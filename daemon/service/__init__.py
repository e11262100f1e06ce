"""The daemon as a running service: built from a Config, started, controlled through its
socket, feeding its outputs."""
