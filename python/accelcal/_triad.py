"""The one copy of the triad helpers: parameter vector <-> K, tilts -> specific force, and
near-uniform points on the sphere.

Parameter vector, always in this order: ``[sx, sy, sz, bx, by, bz, m1, m2, m3]`` (the first 6
for ``model="diag"``):

- ``"lower"``: ``K = [[sx, 0, 0], [m1, sy, 0], [m2, m3, sz]]``;
- ``"upper"``: ``K = [[sx, m1, m2], [0, sy, m3], [0, 0, sz]]``;
- ``"diag"``: ``K = diag(sx, sy, sz)``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._core import CalibrationError
from ._validate import real_array

__all__ = [
    "MODELS",
    "PARAM_NAMES",
    "attitudes_to_force",
    "fibonacci_sphere",
    "gravity_from_tilts",
    "k_matrix",
    "n_params",
    "vector_from_k",
]

PARAM_NAMES = ("sx", "sy", "sz", "bx", "by", "bz", "m1", "m2", "m3")
MODELS = ("lower", "diag", "upper")

#: Golden angle, rad: pi (3 - sqrt 5).
_GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


def n_params(model: str) -> int:
    """Number of parameters of ``model`` (9, or 6 for ``"diag"``); clear error otherwise."""
    if model not in MODELS:
        raise CalibrationError(
            f"unknown model {model!r}; use 'lower' (9 parameters: scale, bias and "
            "lower-triangular non-orthogonality), 'diag' (6: bias + scale) or 'upper' (9, the "
            "upper triangle)"
        )
    return 6 if model == "diag" else 9


def k_matrix(vector: ArrayLike, model: str = "lower") -> NDArray[np.float64]:
    """``K`` (3, 3) from a parameter vector (misalignment terms ignored for ``"diag"``)."""
    v = np.asarray(vector, dtype=np.float64).reshape(-1)
    n_params(model)
    sx, sy, sz = v[0], v[1], v[2]
    if model == "diag" or v.size < 9:
        return np.diag([sx, sy, sz])
    m1, m2, m3 = v[6], v[7], v[8]
    if model == "upper":
        return np.array([[sx, m1, m2], [0.0, sy, m3], [0.0, 0.0, sz]])
    return np.array([[sx, 0.0, 0.0], [m1, sy, 0.0], [m2, m3, sz]])


def vector_from_k(K: ArrayLike, bias: ArrayLike, model: str = "lower") -> NDArray[np.float64]:
    """Parameter vector from ``K`` (3, 3) and ``bias`` (3,); entries outside the model's
    pattern are ignored."""
    k = np.asarray(K, dtype=np.float64)
    b = np.asarray(bias, dtype=np.float64).reshape(-1)
    v = [k[0, 0], k[1, 1], k[2, 2], b[0], b[1], b[2]]
    if n_params(model) == 9:
        if model == "lower":
            v += [k[1, 0], k[2, 0], k[2, 1]]
        else:
            v += [k[0, 1], k[0, 2], k[1, 2]]
    return np.array(v, dtype=np.float64)


def gravity_from_tilts(tx_rad: ArrayLike, ty_rad: ArrayLike, g: float) -> NDArray[np.float64]:
    """Specific force at rest for two-axis platform tilts (radians).

    Returns ``[-g sin ty, g sin tx cos ty, g cos tx cos ty]`` (shape ``(..., 3)``, units of g).
    """
    tx = np.asarray(tx_rad, dtype=np.float64)
    ty = np.asarray(ty_rad, dtype=np.float64)
    return np.stack(
        [-g * np.sin(ty), g * np.sin(tx) * np.cos(ty), g * np.cos(tx) * np.cos(ty)], axis=-1
    )


def attitudes_to_force(attitudes: ArrayLike, g: float) -> NDArray[np.float64]:
    """Specific force at rest (n, 3), units of ``g``, from tilts (n, 2) in degrees or gravity
    directions (n, 3) (normalised here)."""
    a = real_array(attitudes, "attitudes", "tilts in deg or gravity directions")
    if a.ndim != 2 or a.shape[1] not in (2, 3) or a.shape[0] == 0:
        raise CalibrationError(
            "attitudes must be tilts (n, 2) in degrees or gravity directions (n, 3) with n >= 1; "
            f"got shape {a.shape}"
        )
    if not np.all(np.isfinite(a)):
        raise CalibrationError("attitudes contain NaN or inf")
    if a.shape[1] == 3:
        nrm = np.linalg.norm(a, axis=1, keepdims=True)
        if np.any(nrm == 0):
            raise CalibrationError("a gravity direction is the zero vector")
        return g * a / nrm
    return gravity_from_tilts(np.radians(a[:, 0]), np.radians(a[:, 1]), g)


def fibonacci_sphere(n: int) -> NDArray[np.float64]:
    """``n`` near-uniform unit vectors (n, 3) on the sphere (Fibonacci lattice)."""
    i = np.arange(int(n)) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = _GOLDEN_ANGLE * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
