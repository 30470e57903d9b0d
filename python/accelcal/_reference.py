"""Slow pure-NumPy reference implementations of the Rust kernels, used only by the parity
tests (each kernel is checked against its reference on the same inputs)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["demodulate_reference"]


def demodulate_reference(
    accel: ArrayLike, phase: ArrayLike, start: int, stop: int, radius_m: float
) -> tuple[float, float]:
    """Slow pure-NumPy reference of :func:`demodulate` on samples ``[start, stop)``."""
    a = np.asarray(accel, dtype=np.float64)[start:stop]
    ph = np.asarray(phase, dtype=np.float64)[start:stop]
    d = (a[:, 0] + a[:, 2]) - (a[:, 1] + a[:, 3])
    x = np.column_stack(
        [np.ones_like(ph), np.cos(ph), np.sin(ph), np.cos(2 * ph), np.sin(2 * ph)]
    )
    beta = np.linalg.lstsq(x, d - d[0], rcond=None)[0]
    g = 1.0 / (4.0 * radius_m * 1e-9)
    return float(beta[4] * g), float(-beta[3] * g)
