"""The example acquisition script runs online and recovers the simulator's truth."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
from accelcal.sim import SEED000_TRUTH

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "acquisition.py"


def test_acquisition_example_streams_and_calibrates() -> None:
    spec = importlib.util.spec_from_file_location("acquisition", EXAMPLE)
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    fit = mod.run(n_dwells=14, dwell_s=2.0, verbose=False)
    assert fit is not None
    z = (fit.vector - SEED000_TRUTH) / fit.std
    assert np.all(np.abs(z) < 5), z
