"""The static-calibration section of ``accelcal demo``."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from .._core import CalibrationError
from .._quiet import recording
from ..dwell import DwellSet
from ..static import StaticFit, WeakDesignWarning, fit_static

__all__ = ["demo_section", "fit_section"]


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
    return fit_section(dwells, g, truth=truth, model=model)[0]


def fit_section(
    dwells: DwellSet,
    g: float,
    *,
    truth: ArrayLike | None = None,
    model: str = "lower",
) -> tuple[str, StaticFit | None]:
    """:func:`demo_section`'s text and the fit behind it (None when no model could be fitted)."""
    lines = [f"Static field calibration ({len(dwells)} dwells, g = {g} m/s^2)"]
    with recording() as rec:
        try:
            fit = fit_static(dwells, g, model=model)
        except CalibrationError as e:
            lines.append(f"  cannot calibrate model {model!r}: {e}")
            if model != "diag":
                lines.append("  falling back to model 'diag' (bias + scale):")
                text, diag = fit_section(
                    dwells, g, truth=None if truth is None else np.asarray(truth)[:6],
                    model="diag",
                )
                return "\n".join(lines) + "\n" + text, diag
            return "\n".join(lines), None
    lines.append(fit.summary(truth=truth))
    if not fit.weak:  # the summary already lists weak parameters
        for w in rec:
            if issubclass(w.category, WeakDesignWarning):
                lines.append(f"  note: {w.message}")
    return "\n".join(lines), fit
