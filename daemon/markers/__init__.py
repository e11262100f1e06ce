"""Marker-set tools that work on takes: labelling, gap filling, skeletons, file formats
(C3D, Motive CSV), identities for anonymous 3D markers, and trajectory scoring."""
