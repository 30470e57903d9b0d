"""Input coercion shared by the public API: clear errors in Python, strict types for Rust."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ._core import CalibrationError

_NATIVE = (np.dtype(np.float64), np.dtype(np.float32), np.dtype(np.int16), np.dtype(np.int32))


def samples_array(x: Any, name: str = "samples") -> NDArray[Any]:
    """Return ``x`` as an (N, 3) array of a dtype the Rust kernels read without copying.

    float64/float32/int16/int32 pass through untouched (any strides). Other integer types are
    widened exactly (uint16 raw counts to int32, int64 to float64 when exact); bool, complex,
    object and text arrays are refused.
    """
    a = np.asarray(x)
    if a.dtype.kind not in "fiu":
        raise CalibrationError(
            f"{name}: unsupported dtype {a.dtype}; give float64, float32, int16 or int32 samples"
        )
    if a.ndim != 2 or a.shape[1] != 3:
        raise CalibrationError(f"{name} must have shape (N, 3) (x, y, z per row); got {a.shape}")
    if a.shape[0] == 0:
        raise CalibrationError(f"{name} are empty (0 rows)")
    if not a.dtype.isnative:
        a = a.astype(a.dtype.newbyteorder("="))
    if a.dtype in _NATIVE:
        return a
    if a.dtype.kind == "f":  # float16, longdouble
        return a.astype(np.float64)
    if a.dtype.itemsize <= 2 or a.dtype == np.dtype(np.uint16):
        return a.astype(np.int32)
    big = np.abs(a.astype(np.float64)).max()
    if big >= 2.0**53:
        raise CalibrationError(f"{name}: integer values up to {big:.3g} cannot be held exactly")
    return a.astype(np.float64)


def channel(x: Any, n: int, name: str) -> NDArray[np.float64] | None:
    """A per-sample channel (time, temperature) as contiguous float64 of length ``n``."""
    if x is None:
        return None
    a = np.ascontiguousarray(np.asarray(x, dtype=np.float64))
    if a.ndim != 1 or a.shape[0] != n:
        raise CalibrationError(f"{name} must have shape ({n},) to match the samples; got {a.shape}")
    return a


def bounds_array(b: Any) -> NDArray[np.int64]:
    """Dwell bounds as (k, 2) int64 [start, stop) sample indices."""
    a = np.asarray(b)
    if a.ndim == 1 and a.size == 2:
        a = a.reshape(1, 2)
    if a.ndim != 2 or a.shape[1] != 2:
        raise CalibrationError(f"bounds must have shape (k, 2) [start, stop); got {a.shape}")
    if a.shape[0] == 0:
        raise CalibrationError("bounds are empty: give at least one [start, stop) dwell")
    if a.dtype.kind == "f":
        if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
            raise CalibrationError("bounds must be integer sample indices")
    elif a.dtype.kind not in "iu":
        raise CalibrationError(f"bounds must be integer sample indices; got dtype {a.dtype}")
    return np.ascontiguousarray(a.astype(np.int64))


def positive(x: Any, name: str, unit: str = "") -> float:
    """A positive finite float, or a CalibrationError naming it."""
    v = None
    if not isinstance(x, (bool, str, bytes)) and x is not None:
        try:
            v = float(x)
        except (TypeError, ValueError):
            v = None
    if v is None or not math.isfinite(v) or v <= 0:
        raise CalibrationError(
            f"{name} must be positive and finite{unit}, a number in (0, inf); got {x!r}"
        )
    return v


def number(
    x: Any,
    name: str,
    *,
    lo: float = -np.inf,
    hi: float = np.inf,
    lo_open: bool = False,
    integer: bool = False,
    unit: str = "",
) -> Any:
    """A finite number in ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``), an int when ``integer``;
    otherwise a CalibrationError naming the argument, the value received and the valid range."""
    v = None
    if not isinstance(x, (bool, str, bytes)) and x is not None:
        try:
            v = float(x)
        except (TypeError, ValueError):
            v = None
    ok = (
        v is not None
        and math.isfinite(v)
        and (v > lo if lo_open else v >= lo)
        and v <= hi
        and (not integer or v == int(v))
    )
    if not ok:
        left = "(" if lo_open else "["
        right = ")" if math.isinf(hi) else "]"
        rng = f"{left}{lo:g}, {hi:g}{right}" + (f" {unit}" if unit else "")
        kind = "an integer" if integer else "a number"
        raise CalibrationError(f"{name} must be {kind} in {rng}; got {x!r}")
    assert v is not None
    return int(v) if integer else v


def real_array(x: Any, name: str, unit: str = "") -> NDArray[np.float64]:
    """``x`` (array, list, DataFrame/Series, any layout, integer or float dtype, either byte
    order) as float64 in logical order; boolean, complex, text and object arrays are refused."""
    a = np.asarray(x)
    if a.dtype == np.float64:
        return a
    if a.dtype.kind not in "fiu":
        what = {"b": "boolean", "c": "complex", "O": "object", "U": "text", "S": "text"}.get(
            a.dtype.kind, str(a.dtype))
        raise CalibrationError(
            f"{name} must be real numbers{f' ({unit})' if unit else ''}; got a {what} array"
        )
    return np.asarray(a, dtype=np.float64)
