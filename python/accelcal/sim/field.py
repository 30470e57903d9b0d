"""Simulator of a static field-calibration session: raw high-rate streams with known truth
(the setting of Huang et al.'s field calibration of an atomic gravimeter's accelerometer by
norm observation: a triad on a two-axis stabilised platform, tilts within +-30 deg)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._core import CalibrationError
from .._triad import gravity_from_tilts, k_matrix

__all__ = [
    "FIELD_TRUTH", "SEED000_TRUTH", "FieldSession", "field_session", "gravity_from_tilts",
]

#: The norm-observation paper's simulation truth [sx, sy, sz, bx, by, bz, m1, m2, m3]
#: (b in m/s^2).
FIELD_TRUTH: NDArray[np.float64] = np.array([1.1, 0.95, 1.2, 0.3, -0.6, 0.3, 0.01, 0.02, 0.03])
#: Former name of :data:`FIELD_TRUTH` (kept for existing scripts).
SEED000_TRUTH = FIELD_TRUTH



@dataclass
class FieldSession:
    """A simulated session: raw output stream plus the truth behind it.

    samples : (N, 3) raw output in m/s^2 (the norm-observation paper's model am = K a + b + noise).
    t : (N,) s.  fs : Hz.  g : reference gravity, m/s^2.
    truth : (9,) [sx, sy, sz, bx, by, bz, m1, m2, m3].
    tilts_deg : (n, 2) platform tilts (tx, ty) of each dwell.
    bounds : (n, 2) true [start, stop) sample indices of each static dwell.
    """

    samples: NDArray[np.float64]
    t: NDArray[np.float64]
    fs: float
    g: float
    truth: NDArray[np.float64]
    tilts_deg: NDArray[np.float64]
    bounds: NDArray[np.int64]
    sigma: float
    meta: dict[str, Any] = field(default_factory=dict)


def _smoothstep(u: NDArray[np.float64]) -> NDArray[np.float64]:
    return u * u * (3.0 - 2.0 * u)


def field_session(
    *,
    fs: float = 5000.0,
    n_dwells: int = 20,
    dwell_s: float = 20.0,
    move_s: float = 4.0,
    max_tilt_deg: float = 30.0,
    tilts_deg: ArrayLike | None = None,
    truth: ArrayLike = FIELD_TRUTH,
    g: float = 9.80665,
    sigma: float = 1e-3,
    rng: int | np.random.Generator | None = 0,
) -> FieldSession:
    """Simulate a field session on a two-axis platform as a raw stream.

    The platform holds ``n_dwells`` attitudes for ``dwell_s`` seconds each, tilts uniform in
    +-``max_tilt_deg`` (or the given ``tilts_deg`` (n, 2)), and moves between them over
    ``move_s`` seconds (smooth tilt change plus the kinematic acceleration of the motion).
    White noise of ``sigma`` m/s^2 per axis and sample (the paper's 1e-3).
    """
    gen = np.random.default_rng(rng)
    if fs <= 0 or not np.isfinite(fs):
        raise CalibrationError(f"fs must be positive (Hz); got {fs}")
    if tilts_deg is None:
        if n_dwells < 1:
            raise CalibrationError("n_dwells must be >= 1")
        tl = gen.uniform(-max_tilt_deg, max_tilt_deg, size=(n_dwells, 2))
    else:
        tl = np.asarray(tilts_deg, dtype=np.float64).reshape(-1, 2)
    n = tl.shape[0]
    nd = int(round(dwell_s * fs))
    nm = int(round(move_s * fs))
    if nd < 2 or (n > 1 and nm < 2):
        raise CalibrationError("dwell_s and move_s must each span at least two samples")
    total = n * nd + (n - 1) * nm
    tx = np.empty(total)
    ty = np.empty(total)
    kin = np.zeros((total, 3))
    bounds = np.empty((n, 2), dtype=np.int64)
    pos = 0
    for k in range(n):
        tx[pos : pos + nd] = tl[k, 0]
        ty[pos : pos + nd] = tl[k, 1]
        bounds[k] = (pos, pos + nd)
        pos += nd
        if k + 1 < n:
            u = (np.arange(nm) + 0.5) / nm
            s = _smoothstep(u)
            tx[pos : pos + nm] = tl[k, 0] + s * (tl[k + 1, 0] - tl[k, 0])
            ty[pos : pos + nm] = tl[k, 1] + s * (tl[k + 1, 1] - tl[k, 1])
            # Kinematic acceleration of the motion: a smooth bump of ~0.2 m/s^2
            # (handling, lever arm).
            bump = 0.2 * np.sin(np.pi * u) * np.sin(6 * np.pi * u)
            kin[pos : pos + nm] = bump[:, None] * gen.normal(size=3)[None, :]
            pos += nm
    a = gravity_from_tilts(np.radians(tx), np.radians(ty), g) + kin
    v = np.asarray(truth, dtype=np.float64)
    if v.shape != (9,):
        raise CalibrationError(
            f"truth must be the 9-vector [sx,sy,sz,bx,by,bz,m1,m2,m3]; got {v.shape}"
        )
    K = k_matrix(v, "lower")
    out = a @ K.T + v[3:6] + gen.normal(scale=sigma, size=(total, 3))
    t = np.arange(total) / fs
    return FieldSession(
        samples=out,
        t=t,
        fs=float(fs),
        g=float(g),
        truth=v.copy(),
        tilts_deg=tl,
        bounds=bounds,
        sigma=float(sigma),
        meta={"dwell_s": dwell_s, "move_s": move_s, "max_tilt_deg": max_tilt_deg},
    )
