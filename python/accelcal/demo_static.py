"""The static-calibration section of ``accelcal demo``."""

from __future__ import annotations

import warnings

import numpy as np
from numpy.typing import ArrayLike

from ._core import CalibrationError
from .dwell import DwellSet
from .static import WeakDesignWarning, fit_static

__all__ = ["demo_section"]


def demo_section(
    dwells: DwellSet,
    g: float,
    *,
    truth: ArrayLike | None = None,
    model: str = "lower",
) -> str:
    """Fit the dwells and return printable text: parameters with their std (beside ``truth``
    when given), norm statistics before/after, and any weak-design or degeneracy diagnosis
    (reported in the text instead of raised)."""
    lines = [f"Static field calibration ({len(dwells)} dwells, g = {g} m/s^2)"]
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always", WeakDesignWarning)
        try:
            fit = fit_static(dwells, g, model=model)
        except CalibrationError as e:
            lines.append(f"  cannot calibrate model {model!r}: {e}")
            if model != "diag":
                lines.append("  falling back to model 'diag' (bias + scale):")
                return "\n".join(lines) + "\n" + demo_section(
                    dwells, g, truth=None if truth is None else np.asarray(truth)[:6],
                    model="diag",
                )
            return "\n".join(lines)
    lines.append(fit.summary(truth=truth))
    if not fit.weak:  # the summary already lists weak parameters
        for w in rec:
            if issubclass(w.category, WeakDesignWarning):
                lines.append(f"  note: {w.message}")
    return "\n".join(lines)
