"""calibkit: calibration of multi-camera optical motion-capture rigs."""

__version__ = "0.1.0"
