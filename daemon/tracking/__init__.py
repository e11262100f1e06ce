"""Tracking live frames: 3D markers with identities, rigid bodies, their compiled kernels,
and defining a body from what was seen."""
