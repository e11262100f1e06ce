"""Labelling 3D points with a marker set: the sets, the frame-by-frame labeller and its
stages, whole takes, and the daemon's live stage."""
