"""The shared core: cameras, rig files, observations, recordings, and the geometry
(projection, triangulation) every step uses. It imports nothing else of calibkit."""
