"""Capture and pairing: blob sources, each camera's clock, the multiplexer, and the live
pipeline's threads."""
