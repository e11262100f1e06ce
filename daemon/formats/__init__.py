"""Files of markers and poses: C3D, Motive CSV, points CSV, pose trajectories (TUM, CSV)."""
