"""Drawing calibration dot patterns on monitors and projectors (moderngl)."""
