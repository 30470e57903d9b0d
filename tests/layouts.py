"""Every memory layout, dtype and container an array argument can arrive in.

``layout_variants(a)`` yields ``(name, value)`` pairs holding the same logical values as ``a``
(a C-ordered float64 array of whole numbers, so every dtype variant is exact): C-ordered,
Fortran-ordered, row-strided, column-strided, negatively strided, a slice at an offset,
unaligned, float32, int16, int32, int64, uint16 (when non-negative), big-endian float64 and
int16, a pandas DataFrame/Series, and an object with ``__array__``. A public function given any
of them must return exactly what it returns for ``a``.

Reusable by any module's layout test::

    @pytest.mark.parametrize("layout", LAYOUT_NAMES)
    def test_x(layout):
        v = dict(layout_variants(a))[layout]
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

try:  # pandas is in the test extra; the variants without it still run
    import pandas as pd
except ImportError:  # pragma: no cover
    pd = None

LAYOUT_NAMES = [
    "C",
    "F",
    "rows_strided",
    "cols_strided",
    "negative_stride",
    "offset_slice",
    "unaligned",
    "float32",
    "int16",
    "int32",
    "int64",
    "uint16",
    "big_endian_f8",
    "big_endian_i2",
    "pandas",
    "pandas_int16",
    "array_protocol",
]


class ArrayLike:
    """A minimal non-NumPy container exposing ``__array__`` (as many libraries do)."""

    def __init__(self, a: np.ndarray) -> None:
        self._a = a

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        return self._a if dtype is None else self._a.astype(dtype)


def _unaligned(a: np.ndarray) -> np.ndarray:
    """The same values one byte off alignment (e.g. a view into a packed record)."""
    buf = np.empty(a.nbytes + 1, dtype=np.uint8)
    buf[1:] = np.frombuffer(np.ascontiguousarray(a).tobytes(), dtype=np.uint8)
    u = np.frombuffer(buf.data, dtype=a.dtype, count=a.size, offset=1).reshape(a.shape)
    assert not u.flags.aligned
    return u


def layout_variants(a: Any) -> Iterator[tuple[str, Any]]:
    """Every layout of ``a`` (1-D or 2-D, whole-number values) named as in ``LAYOUT_NAMES``."""
    a = np.ascontiguousarray(a, dtype=np.float64)
    if not np.all(a == np.round(a)) or np.abs(a).max() > 32767:
        raise ValueError("layout_variants needs whole numbers within int16 range")
    two_d = a.ndim == 2
    yield "C", a
    yield "F", np.asfortranarray(a)
    big = np.zeros((2 * a.shape[0], *a.shape[1:]))
    big[::2] = a
    yield "rows_strided", big[::2]
    if two_d:
        wide = np.zeros((a.shape[0], 2 * a.shape[1] + 1))
        wide[:, 1::2] = a
        yield "cols_strided", wide[:, 1::2]
    else:
        yield "cols_strided", np.column_stack([np.zeros_like(a), a])[:, 1]
    yield "negative_stride", np.ascontiguousarray(a[::-1])[::-1]
    pad = np.zeros((a.shape[0] + 7, *a.shape[1:]))
    pad[5 : 5 + a.shape[0]] = a
    yield "offset_slice", pad[5 : 5 + a.shape[0]]
    yield "unaligned", _unaligned(a)
    yield "float32", a.astype(np.float32)
    yield "int16", a.astype(np.int16)
    yield "int32", a.astype(np.int32)
    yield "int64", a.astype(np.int64)
    if a.min() >= 0:
        yield "uint16", a.astype(np.uint16)
    else:
        yield "uint16", a.astype(np.int16)  # (negative values: int16 stands in)
    yield "big_endian_f8", a.astype(">f8")
    yield "big_endian_i2", a.astype(">i2")
    if pd is not None:
        if two_d:
            yield "pandas", pd.DataFrame(a, columns=[f"c{i}" for i in range(a.shape[1])])
            yield "pandas_int16", pd.DataFrame(
                {f"c{i}": a[:, i].astype(np.int16) for i in range(a.shape[1])}
            )
        else:
            yield "pandas", pd.Series(a)
            yield "pandas_int16", pd.Series(a.astype(np.int16))
    yield "array_protocol", ArrayLike(a)
