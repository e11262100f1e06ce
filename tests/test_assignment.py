"""calibkit.core.assignment: SciPy's assignment solver loaded without scipy.optimize gives
scipy.optimize's answers, and `mocapd label` no longer loads that package."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_the_solver_gives_scipy_optimizes_answers():
    from scipy.optimize import linear_sum_assignment as public

    from calibkit.core.assignment import linear_sum_assignment

    rng = np.random.default_rng(4)
    for shape in [(5, 5), (7, 3), (3, 9), (41, 47), (1, 1), (0, 0)]:
        cost = rng.normal(size=shape)
        for maximize in (False, True):
            ours = linear_sum_assignment(cost, maximize=maximize)
            theirs = public(cost, maximize=maximize)
            assert all(np.array_equal(a, b) for a, b in zip(ours, theirs, strict=True))
    with pytest.raises(ValueError, match="infeasible"):
        linear_sum_assignment(np.full((2, 2), np.inf))


def test_labelling_does_not_load_scipy_optimize():
    """0.38 s of CPU on every `mocapd label`: the package stays unloaded."""
    code = ("import sys, daemon.labelling.offline, daemon.synthetic.evaluator; "
            "print('scipy.optimize' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, timeout=120, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
