"""Work on whole takes: gap filling, skeletons, trajectory evaluation, and rigid bodies
tracked offline from files of 3D markers."""
