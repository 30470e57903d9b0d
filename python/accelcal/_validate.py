"""Input coercion shared by the public API: clear errors in Python, strict types for Rust.

Every array argument may come in any memory layout (C- or Fortran-ordered, strided, sliced,
negative strides), any byte order, as a NumPy array of a real numeric dtype or as anything with
``__array__`` (a pandas DataFrame or Series). The helpers here turn it into what the Rust glue
reads (native byte order, one of the dtypes it accepts) or raise a :class:`CalibrationError`
naming the argument, what was received and what is valid. Complex, boolean, object and text
arrays are refused rather than cast (a cast would drop the imaginary part or read ``True`` as
1 without saying so).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import _quiet
from ._core import CalibrationError

_NATIVE = (np.dtype(np.float64), np.dtype(np.float32), np.dtype(np.int16), np.dtype(np.int32))


def _describe(x: Any) -> str:
    r = repr(x)
    return r if len(r) <= 60 else r[:57] + "..."


def _table_order(x: Any, name: str) -> list[int] | None:
    """For a table of three named columns (a pandas or polars DataFrame): the storage
    indices of its x, y, z, chosen by name exactly as :func:`accelcal.io.read_stream`
    chooses them (``az, ay, ax`` gives ``[2, 1, 0]``); None for anything else, and for
    names that say nothing about the axes (``0, 1, 2``, ``a, b, c``: storage order). Names
    that point at some axes but not at one column each are refused, naming the columns."""
    if isinstance(x, np.ndarray) or not hasattr(x, "columns"):
        return None
    try:
        names = [str(c) for c in x.columns]
    except TypeError:
        return None
    if len(names) != 3:
        return None  # the shape check refuses it
    from .io import _auto_acc  # the one copy of read_stream's choice by name

    try:
        order = _auto_acc(names, name)
    except CalibrationError:
        raise CalibrationError(
            f"{name}: cannot tell which of the DataFrame's columns {names} are the "
            "accelerometer x, y, z (their names point at some axes but not at one column "
            "each); select them in x, y, z order (df[['ax', 'ay', 'az']]), or read the "
            "DataFrame with accelcal.io.read_stream(df, columns=[...])"
        ) from None
    return None if order is None or order == [0, 1, 2] else order


def numeric_array(x: Any, name: str) -> NDArray[Any]:
    """``x`` as a NumPy array of a real numeric dtype in native byte order (no copy when it
    already is one); complex, boolean, object and text input is refused by name.

    A DataFrame of three named columns gives them in x, y, z order by name, as
    :func:`accelcal.io.read_stream` takes them (``az, ay, ax`` is reordered); three columns
    whose names do not say which axis (``0, 1, 2``) keep their order."""
    order = _table_order(x, name)
    try:
        a = np.asarray(x)
    except (TypeError, ValueError) as e:
        raise CalibrationError(f"{name} cannot be read as an array: {e}") from None
    if order is not None and a.ndim == 2 and a.shape[1] == 3:
        a = a[:, order]
    kind = a.dtype.kind
    if kind == "c":
        raise CalibrationError(
            f"{name} has complex dtype {a.dtype}; give real values (e.g. x.real) explicitly"
        )
    if kind == "b":
        raise CalibrationError(f"{name} has boolean dtype {a.dtype}; give numeric values")
    if kind not in "fiu":
        raise CalibrationError(
            f"{name}: unsupported dtype {a.dtype}; give a real numeric array "
            "(float64, float32, int16 or int32)"
        )
    if not a.dtype.isnative:
        a = a.astype(a.dtype.newbyteorder("="))
    if not a.flags.aligned:  # e.g. a view into a packed record array: Rust reads aligned data
        a = a.copy()
    return a


def samples_array(x: Any, name: str = "samples") -> NDArray[Any]:
    """Return ``x`` as an (N, 3) array of a dtype the Rust kernels read without copying.

    float64/float32/int16/int32 pass through in any layout (the kernels read any strides).
    Non-native byte order is converted; other integer types are widened exactly (uint16 raw
    counts to int32, int64 to float64 when exact); float16 and long double become float64.
    """
    a = numeric_array(x, name)
    if a.ndim != 2 or a.shape[1] != 3:
        hint = (f": it looks like a (3, N) array of x, y, z rows; give its transpose "
                f"{name}.T" if a.ndim == 2 and a.shape[0] == 3 and a.shape[1] > 3 else "")
        raise CalibrationError(
            f"{name} must have shape (N, 3) (x, y, z per row); got {a.shape}{hint}")
    if a.shape[0] == 0:
        raise CalibrationError(f"{name} are empty (0 rows)")
    if a.dtype in _NATIVE:
        return a
    if a.dtype.kind == "f":  # float16, longdouble
        return a.astype(np.float64)
    if a.dtype.itemsize <= 2:
        return a.astype(np.int32)
    big = float(np.abs(a.astype(np.float64)).max())
    if big >= 2.0**53:
        raise CalibrationError(f"{name}: integer values up to {big:.3g} cannot be held exactly")
    return a.astype(np.float64)


def stored_signed16(a: NDArray[Any]) -> bool:
    """Whether uint16 samples (N, 3) hold signed 16-bit values stored as unsigned (65404 for
    -132), judged on the first rows exactly as :func:`accelcal.io.read_stream` judges a
    file's accelerometer columns. A 16-bit output that is unsigned by design (mid-scale
    32768) is not: read as signed, its axes would spread more."""
    if a.dtype != np.uint16 or a.ndim != 2 or a.shape[0] == 0:
        return False
    from .io import _SNIFF_ROWS, _stored_unsigned

    return _stored_unsigned(a[:_SNIFF_ROWS])


def signed16_text(name: str) -> str:
    """The note of :func:`stored_signed16`'s finding for the array called ``name``."""
    from .io import STORED_UNSIGNED_TEXT

    return f"{name}: the uint16 words {STORED_UNSIGNED_TEXT}"


def signed16_samples(a: NDArray[Any], name: str = "samples") -> NDArray[Any]:
    """uint16 samples read as :func:`accelcal.io.read_stream` reads them: viewed as int16
    (no copy), with a warning, when they hold signed 16-bit values stored as unsigned
    (:func:`stored_signed16`); otherwise ``a`` as it is."""
    if not stored_signed16(a):
        return a
    _quiet.warn(
        f"{signed16_text(name)}: read as signed, as accelcal.io.read_stream reads them (give "
        f"{name}.view(np.int16) to say so and silence this, or {name}.astype(np.int32) to "
        "keep them unsigned)", UserWarning, stacklevel=3)
    return a.view(np.int16)


def channel(x: Any, n: int, name: str) -> NDArray[np.float64] | None:
    """A per-sample channel (time, temperature) as contiguous float64 of length ``n``."""
    if x is None:
        return None
    a = numeric_array(x, name)
    if a.ndim != 1 or a.shape[0] != n:
        raise CalibrationError(f"{name} must have shape ({n},) to match the samples; got {a.shape}")
    return np.require(a, dtype=np.float64, requirements=["C", "A"])


def bounds_array(b: Any) -> NDArray[np.int64]:
    """Dwell bounds as (k, 2) int64 [start, stop) sample indices."""
    try:
        a = np.asarray(b)
    except (TypeError, ValueError) as e:
        raise CalibrationError(f"bounds cannot be read as an array: {e}") from None
    if a.ndim == 1 and a.size == 2:
        a = a.reshape(1, 2)
    if a.ndim != 2 or a.shape[1] != 2:
        raise CalibrationError(f"bounds must have shape (k, 2) [start, stop); got {a.shape}")
    if a.shape[0] == 0:
        raise CalibrationError("bounds are empty: give at least one [start, stop) dwell")
    if a.dtype.kind == "f":
        if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
            raise CalibrationError("bounds must be integer sample indices")
        if np.any(np.abs(a) >= 2.0**62):
            raise CalibrationError("bounds must be integer sample indices below 2**62")
    elif a.dtype.kind == "u":
        if np.any(a >= 2**62):
            raise CalibrationError("bounds must be integer sample indices below 2**62")
    elif a.dtype.kind != "i":
        raise CalibrationError(f"bounds must be integer sample indices; got dtype {a.dtype}")
    return np.ascontiguousarray(a.astype(np.int64))


def _to_float(x: Any) -> float | None:
    """``float(x)`` for a real scalar (or 0-d array); None for None, bool, text, complex or a
    value too large for a float."""
    if x is None or isinstance(x, (bool, np.bool_, str, bytes, complex, np.complexfloating)):
        return None
    if isinstance(x, np.ndarray) and (x.ndim != 0 or x.dtype.kind not in "fiu"):
        return None
    try:
        return float(x)
    except (TypeError, ValueError, OverflowError):
        return None


def positive(x: Any, name: str, unit: str = "") -> float:
    """A positive finite float, or a CalibrationError naming it."""
    v = _to_float(x)
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
    v = _to_float(x)
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
        raise CalibrationError(f"{name} must be {kind} in {rng}; got {_describe(x)}")
    assert v is not None
    return int(v) if integer else v


def real_array(x: Any, name: str, unit: str = "") -> NDArray[np.float64]:
    """``x`` (array, list, DataFrame/Series, any layout, integer or float dtype, either byte
    order) as aligned float64 in logical order; boolean, complex, text and object arrays are
    refused. A DataFrame of three named columns gives them in x, y, z order by name, as
    :func:`numeric_array` does (``az, ay, ax`` is reordered)."""
    order = _table_order(x, name)
    a = np.asarray(x)
    if order is not None and a.ndim == 2 and a.shape[1] == 3:
        a = a[:, order]
    if a.dtype.kind not in "fiu":
        what = {"b": "boolean", "c": "complex", "O": "object", "U": "text", "S": "text"}.get(
            a.dtype.kind, str(a.dtype))
        raise CalibrationError(
            f"{name} must be real numbers{f' ({unit})' if unit else ''}; got a {what} array"
        )
    a = np.asarray(a, dtype=np.float64)
    return a if a.flags.aligned else a.copy()
