"""The linear assignment solver, without loading SciPy's optimiser package.

Why: `scipy.optimize` loads the whole package (linear programming, FFT, sparse linear
algebra) to give `linear_sum_assignment`: 0.38 s of CPU on every `mocapd label`, more
than labelling a short take. The solver is one compiled module of SciPy's
(`scipy/optimize/_lsap`), whose function is the very one `scipy.optimize` exports; it is
loaded here on its own. Where SciPy lays its files out otherwise, the public import is
used (slower to load, the same answers).
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
from pathlib import Path


def _load():
    try:
        import scipy

        folder = Path(scipy.__file__).parent / "optimize"
        for suffix in importlib.machinery.EXTENSION_SUFFIXES:
            path = folder / f"_lsap{suffix}"
            if path.is_file():
                loader = importlib.machinery.ExtensionFileLoader("_lsap", str(path))
                spec = importlib.util.spec_from_file_location("_lsap", path, loader=loader)
                module = importlib.util.module_from_spec(spec)
                loader.exec_module(module)
                return module.linear_sum_assignment
    except (ImportError, OSError, AttributeError):
        pass
    # deferred on purpose: loads all of scipy.optimize only where the module above is not
    from scipy.optimize import linear_sum_assignment

    return linear_sum_assignment


linear_sum_assignment = _load()
