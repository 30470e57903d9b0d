"""Slow pure-NumPy reference implementations of the Rust kernels, used only by the parity
tests (each kernel is checked against its reference on the same inputs)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "allan_inflation_reference",
    "allan_inflation_sample_stride",
    "demodulate_reference",
    "dwell_edges_reference",
    "dwell_reference",
    "lsb_reference",
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
