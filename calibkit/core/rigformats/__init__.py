"""Other tools' calibration files read into a Rig, and the TOML ones written back."""
