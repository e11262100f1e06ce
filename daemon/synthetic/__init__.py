"""The daemon's simulated capture and the scorers that read its truth (never the tracker)."""
