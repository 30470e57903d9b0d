"""Slow pure-NumPy reference implementations of the Rust kernels, used only by the parity
tests (each kernel is checked against its reference on the same inputs)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["demodulate_reference", "static_fit_reference", "static_ml_residuals_reference"]


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


def static_ml_residuals_reference(
    p: ArrayLike, means: ArrayLike, g: float, var: ArrayLike | None = None, model: str = "lower"
) -> np.ndarray:
    """Slow NumPy reference of the static fit's maximum-likelihood residuals: for dwell k,
    ``(|K^-1 (am_k - b)| - g) / sigma_k`` with ``sigma_k^2 = w_k^T diag(var_k) w_k`` and
    ``w_k = K^-T a_k / |a_k|`` (``var`` None: isotropic unit variance)."""
    v = np.asarray(p, dtype=np.float64)
    m = np.asarray(means, dtype=np.float64)
    sx, sy, sz = v[0], v[1], v[2]
    if model == "diag":
        K = np.diag([sx, sy, sz])
    elif model == "upper":
        K = np.array([[sx, v[6], v[7]], [0.0, sy, v[8]], [0.0, 0.0, sz]])
    else:
        K = np.array([[sx, 0.0, 0.0], [v[6], sy, 0.0], [v[7], v[8], sz]])
    T = np.linalg.inv(K)
    a = (m - v[3:6]) @ T.T
    na = np.linalg.norm(a, axis=1)
    w = (a / na[:, None]) @ T
    s2 = (w * w * (1.0 if var is None else np.asarray(var, dtype=np.float64))).sum(axis=1)
    return (na - g) / np.sqrt(s2)  # type: ignore[no-any-return]


def static_fit_reference(
    means: ArrayLike,
    g: float,
    var: ArrayLike | None = None,
    model: str = "lower",
    starts: tuple[ArrayLike, ...] = (),
) -> tuple[np.ndarray, float]:
    """Independent maximum-likelihood static fit: ``scipy.optimize.least_squares`` (LM,
    numerical Jacobian, tight tolerances) on :func:`static_ml_residuals_reference` from each
    start (default the nominal ``K = I, b = 0``); returns the parameters and the cost
    ``sum e_k^2`` of the best finite result."""
    from scipy.optimize import least_squares

    p = 6 if model == "diag" else 9
    x0s = list(starts) or [np.r_[np.ones(3), np.zeros(p - 3)]]
    best: tuple[np.ndarray, float] | None = None
    for x0 in x0s:
        try:
            r = least_squares(
                static_ml_residuals_reference, np.asarray(x0, dtype=np.float64)[:p],
                args=(means, g, var, model), method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15,
                max_nfev=20000,
            )
        except (ValueError, np.linalg.LinAlgError):
            continue
        c = float(2.0 * r.cost)
        if np.all(np.isfinite(r.x)) and np.isfinite(c) and (best is None or c < best[1]):
            best = (r.x, c)
    if best is None:
        raise ValueError("no start gave a finite fit")
    return best
