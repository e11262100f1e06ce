"""Vision: finding markers in images, matching them across cameras, and the gates that
follow the rig's measured residual."""
