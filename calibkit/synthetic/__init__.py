"""The simulated rig and everything that knows its truth.

Scenes, rendered images, monitor/projector/wand captures, the walking person, and the
scorers that compare an estimate with the truth. Estimating code (calibration, detection,
correspondence, tracking, labelling) never imports this package (tests/test_boundary.py);
commands, tests and benchmarks use it to make inputs and to score outputs.
"""
