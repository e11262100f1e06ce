"""Calibration methods: intrinsics from a monitor or a printed board, extrinsics from
projected dots, the wand's factor-graph bundle adjustment, and the floor's world frame."""
