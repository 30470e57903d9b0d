"""Slow pure-NumPy reference implementations of the Rust kernels, used only by the parity
tests (each kernel is checked against its reference on the same inputs)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "allan_inflation_reference",
    "apply_triad_reference",
    "centrifuge_fit_reference",
    "allan_inflation_sample_stride",
    "demodulate_reference",
    "dwell_edges_reference",
    "dwell_reference",
    "lsb_reference",
    "static_fit_reference",
    "static_ml_residuals_reference",
]


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


def centrifuge_fit_reference(
    out: ArrayLike, omega: ArrayLike, radius: float, g: float, x0: ArrayLike
) -> tuple[np.ndarray, Any]:
    """Independent centrifuge fit: ``scipy.optimize.least_squares`` on the norm residual
    ``(|f|^2 - t) / (2 sqrt t)``, ``t = (omega^2 R / g)^2 + 1``, with the K2 model inverted
    exactly, ``f = 2h / (1 + sqrt(1 + 4 D h))``, ``h = (out - b) / s`` (outputs in g).
    Parameters ``[s (3), b (3), D (3)]``; returns them and the residual function."""
    from scipy.optimize import least_squares

    o = np.asarray(out, dtype=np.float64)
    w = np.asarray(omega, dtype=np.float64)
    t = (w**2 * radius / g) ** 2 + 1.0

    def res(p: NDArray[np.float64]) -> NDArray[np.float64]:
        s, b, d = p[:3], p[3:6], p[6:9] * 1e-4
        h = (o - b) / s
        f = 2 * h / (1 + np.sqrt(1 + 4 * d * h))
        return ((f**2).sum(1) - t) / (2 * np.sqrt(t))  # type: ignore[no-any-return]

    x0 = np.asarray(x0, dtype=np.float64)
    x = least_squares(res, np.r_[x0[:6], x0[6:9] * 1e4], xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    return np.r_[x[:6], x[6:9] * 1e-4], res


def apply_triad_reference(raw: ArrayLike, k: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """Calibrated specific force ``K^-1 (raw - b)`` by a NumPy solve, row by row."""
    r = np.asarray(raw, dtype=np.float64)
    return np.linalg.solve(np.asarray(k, dtype=np.float64), (r - np.asarray(b)).T).T


# ---- dwell statistics ------------------------------------------------------------------------
def _round_half_up(v: float) -> int:
    """Rust's ``f64::round`` for non-negative values (Python's round is to even)."""
    return int(np.floor(v + 0.5))


def dwell_edges_reference(start: int, stop: int) -> NDArray[np.int64]:
    """Sub-block edges of a dwell given by bounds: 64 equal sub-blocks (2 below 64 samples)."""
    n = stop - start
    s = 64 if n >= 64 else 2
    return start + (np.arange(s + 1, dtype=np.int64) * n) // s


def allan_inflation_reference(seg: ArrayLike, edges: ArrayLike) -> NDArray[np.float64]:
    """Slow reference of the dwell kernel's Allan noise inflation, per axis.

    ``seg`` holds the dwell's samples (L, 3); ``edges`` the segment boundaries relative to the
    dwell (0 ... L). Clusters of J whole segments start at every segment boundary; J = S/16 and
    S/4 of S segments. ``r(J) = ADEV(J) sqrt(m) / ADEV(1)`` with ``m`` = J L / S samples,
    extrapolated to tau = L along the clipped log-log slope.
    """
    x = np.asarray(seg, dtype=np.float64)
    e = np.asarray(edges, dtype=np.int64)
    big_l, s = x.shape[0], e.size - 1
    out = np.full(3, np.nan)
    if big_l < 64 or s < 8:
        return out
    j16 = max(1, _round_half_up(s / 16))
    j4 = min(max(_round_half_up(s / 4), j16 + 1), s // 2)
    if j4 <= j16:
        return out

    def avar(j: int) -> NDArray[np.float64]:
        y = np.array([x[e[i] : e[i + j]].mean(axis=0) for i in range(s - j + 1)])
        d = y[j:] - y[:-j]
        return 0.5 * np.mean(d * d, axis=0)

    a1 = np.sum(np.diff(x, axis=0) ** 2, axis=0) / (2 * (big_l - 1))
    m16, m4 = j16 * big_l / s, j4 * big_l / s
    with np.errstate(divide="ignore", invalid="ignore"):
        r16 = np.sqrt(avar(j16) * m16 / a1)
        r4 = np.sqrt(avar(j4) * m4 / a1)
        slope = np.clip(
            np.log(np.maximum(r4, 1e-12) / np.maximum(r16, 1e-12)) / np.log(m4 / m16), 0, 1
        )
        f = r4 * (big_l / m4) ** slope
    return np.where((a1 > 0) & np.isfinite(f), f, np.nan)


def allan_inflation_sample_stride(seg: ArrayLike) -> NDArray[np.float64]:
    """The sample-stride definition the kernel approximates: overlapping Allan deviation at
    cluster sizes 1, L//16 and L//4 samples (every start sample), extrapolated to tau = L."""
    x = np.asarray(seg, dtype=np.float64)
    big_l = x.shape[0]
    c = np.vstack([np.zeros((1, 3)), np.cumsum(x - x.mean(axis=0), axis=0)])

    def avar(m: int) -> NDArray[np.float64]:
        avg = (c[m:] - c[:-m]) / m
        d = avg[m:] - avg[:-m]
        return 0.5 * np.mean(d * d, axis=0)

    m16, m4 = max(big_l // 16, 2), max(big_l // 4, 4)
    a1 = avar(1)
    r16 = np.sqrt(avar(m16) * m16 / a1)
    r4 = np.sqrt(avar(m4) * m4 / a1)
    slope = np.clip(np.log(np.maximum(r4, 1e-12) / np.maximum(r16, 1e-12)) / np.log(m4 / m16), 0, 1)
    return np.asarray(r4 * (big_l / m4) ** slope)


def dwell_reference(
    x: ArrayLike, start: int, stop: int, edges: ArrayLike | None = None
) -> dict[str, NDArray[np.float64]]:
    """Slow reference of one dwell's statistics: mean, var (ddof=1), half means (split at the
    middle segment edge) and Allan inflation. ``edges`` default to the bounds sub-blocks."""
    e = dwell_edges_reference(start, stop) if edges is None else np.asarray(edges)
    seg = np.asarray(x, dtype=np.float64)[start:stop]
    h = int(e[(e.size - 1) // 2]) - start
    return {
        "mean": seg.mean(axis=0),
        "var": seg.var(axis=0, ddof=1),
        "half_mean": np.stack([seg[:h].mean(axis=0), seg[h:].mean(axis=0)]),
        "inflation": allan_inflation_reference(seg, e - start),
    }


def lsb_reference(x: ArrayLike, cap: int = 4096) -> NDArray[np.float64] | None:
    """Slow reference of the output-resolution estimate: the rows at multiples of the smallest
    power-of-two step leaving at most ``cap`` rows; per axis the gcd of the gaps between distinct
    values (integers), or the common spacing of which every gap is a multiple within 10 %."""
    a = np.asarray(x)
    n = a.shape[0]
    step = 1
    while -(-n // step) > cap:
        step *= 2
    sub = a[::step].astype(np.float64)
    out = np.empty(3)
    for ax in range(3):
        v = np.unique(sub[np.isfinite(sub[:, ax]), ax])
        d = np.diff(v)
        if a.dtype.kind in "iu":
            out[ax] = float(np.gcd.reduce(d.astype(np.int64))) if d.size else 1.0
            if out[ax] == 0:
                out[ax] = 1.0
            continue
        if d.size == 0 or not d.min() > 0:
            return None
        k = np.round(d / d.min())
        q = d.sum() / k.sum()
        if np.any(np.abs(d - k * q) > 0.1 * q):
            return None
        out[ax] = q
    return out


def output_faults_reference(
    x: ArrayLike, bounds: ArrayLike, lsb: ArrayLike | None = None, min_samples: int = 30,
    bias_se: float = 0.5,
) -> list[tuple[int, int | None, str]]:
    """Slow reference of ``DwellSet.faults`` from the samples themselves: an axis is constant
    in a dwell when its samples' peak-to-peak range is zero (not from the variance); it counts
    where the dwell holds ``min_samples`` or more and the axis's upper-quartile dwell variance
    (nearest rank, over dwells of ``min_samples`` or more) is positive and at least
    ``lsb^2``. Constant on every axis: "frozen"; on one axis at the largest / smallest
    dwell mean of that axis: "saturated_high" / "saturated_low"; otherwise "stuck". A dwell
    whose mean on an axis with a saturated value r lies delta typical std inside r is
    "partly_saturated_high" / "_low" when the clipped tail's mean excess, the standard normal
    pdf(delta) - delta sf(delta) (scipy.stats.norm), exceeds ``bias_se / sqrt(n)``."""
    from scipy.stats import norm

    a = np.asarray(x, dtype=np.float64)
    b = np.asarray(bounds, dtype=np.int64)
    segs = [a[s:e] for s, e in b]
    mean = np.array([s.mean(axis=0) for s in segs])
    var = np.array([s.var(axis=0, ddof=1) for s in segs])
    flat = np.array([np.ptp(s, axis=0) == 0 for s in segs])
    n = np.array([len(s) for s in segs])
    long = n >= min_samples
    typical = np.full(3, np.nan)
    for ax in range(3):
        v = np.sort(var[long, ax])
        if v.size:
            q = v[-(-3 * (v.size - 1) // 4)]
            floor = 0.0 if lsb is None else float(np.asarray(lsb)[ax]) ** 2
            if q > 0 and q >= floor:
                typical[ax] = q
    ok = np.isfinite(typical)
    out: list[tuple[int, int | None, str]] = []
    for k in np.flatnonzero(long):
        if flat[k].all():
            if ok.any():
                out.append((int(k), None, "frozen"))
            continue
        for j in np.flatnonzero(flat[k] & ok):
            kind = ("saturated_high" if mean[k, j] == mean[:, j].max() else
                    "saturated_low" if mean[k, j] == mean[:, j].min() else "stuck")
            out.append((int(k), int(j), kind))
    constant = list(out)
    for j in np.flatnonzero(ok):
        s = np.sqrt(typical[j])
        for side, sign in (("high", 1.0), ("low", -1.0)):
            rails = [mean[k, j] for k, ax, kind in out if ax == j and kind == f"saturated_{side}"]
            if not rails:
                continue
            for k in np.flatnonzero(long):
                if any(kk == k and ax in (None, j) for kk, ax, _ in constant):
                    continue
                d = max(sign * (rails[0] - mean[k, j]) / s, 0.0)
                if (norm.pdf(d) - d * norm.sf(d)) * np.sqrt(n[k]) > bias_se:
                    out.append((int(k), int(j), f"partly_saturated_{side}"))
    return sorted(out, key=lambda f: (f[0], -1 if f[1] is None else f[1]))
