"""The helpers several modules share (one copy each): the JSON converter ``plain``, the table
of output units of g, the robust spread (median and 1.4826 MAD) and the median calibrated
norm. Each against the formula its callers wrote before they shared it."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from accelcal._plain import plain
from accelcal._triad_model import _UNIT_G, median_norm, units_of_g
from accelcal.static import median_and_spread, unit_label


def _jsonable_before(x: Any) -> Any:
    """The command line's converter before it called ``plain(strict=True)``."""
    if isinstance(x, dict):
        return {str(k): _jsonable_before(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable_before(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable_before(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if np.isfinite(v) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


@dataclass
class _Row:
    name: str
    value: Any


MIXED = {
    "arr": np.array([[1.0, np.nan], [np.inf, -2.5]]),
    "f32": np.float32(0.1),
    "i8": np.int8(-3),
    "u64": np.uint64(2**63),
    "t": (np.float64(-np.inf), 1, "x", None, True),
    3: [np.arange(3), {"inner": np.float64(np.nan)}],
    "ints": np.arange(4, dtype=np.int16),
}


def test_plain_keeps_nan_and_keys_and_reads_dataclasses() -> None:
    got = plain({"rows": (_Row("a", np.array([1.0, np.nan])),), 7: np.int64(7)})
    assert list(got) == ["rows", 7]
    assert got[7] == 7 and type(got[7]) is int
    assert got["rows"][0]["name"] == "a" and got["rows"][0]["value"][0] == 1.0
    assert math.isnan(got["rows"][0]["value"][1])
    assert plain(np.arange(3.0)) == [0.0, 1.0, 2.0] and plain(np.float32(1.5)) == 1.5
    assert plain("text") == "text" and plain(None) is None


def test_plain_strict_writes_the_command_lines_json_as_before() -> None:
    assert json.dumps(plain(MIXED, strict=True)) == json.dumps(_jsonable_before(MIXED))
    assert plain(MIXED, strict=True) == _jsonable_before(MIXED)
    assert plain({1: [np.nan, np.float32(np.inf)]}, strict=True) == {"1": [None, None]}


def test_units_of_g_ranges_and_the_file_tables_gravity_agree() -> None:
    cases = {0.9: "g", 1.1: "g", 1.1000001: "", 9.0: "m/s^2", 10.5: "m/s^2", 10.51: "",
             900.0: "cm/s^2", 989.999: "cm/s^2", 990.0: "mg", 1100.0: "mg", 1100.1: "",
             math.nan: "", 0.0: ""}
    for g, unit in cases.items():
        assert units_of_g(g) == unit, g
    assert unit_label(50.0) == "units of g"
    # Gravity in each unit named from g lies in the range that names it.
    for unit in ("m/s^2", "g", "mg", "cm/s^2"):
        assert units_of_g(_UNIT_G[unit]) == unit


@pytest.mark.parametrize("seed", range(5))
def test_median_and_spread_is_the_formula_of_its_callers(seed: int) -> None:
    x = np.random.default_rng(seed).standard_t(3, size=17 + seed) * 10.0 ** (seed - 2)
    med = float(np.median(x))
    assert median_and_spread(x) == (med, float(1.4826 * np.median(np.abs(x - med))))
    assert median_and_spread(np.full(5, 2.0)) == (2.0, 0.0)


def test_median_norm_of_rows_with_dropouts() -> None:
    rows = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 2.0], [np.nan, 0.0, 0.0], [1.0, 0.0, 0.0]])
    assert math.isnan(median_norm(rows))
    assert median_norm(rows, finite=True) == 2.0
    assert median_norm(rows[[0, 1, 3]]) == 2.0
    assert math.isnan(median_norm(rows[2:3], finite=True))
    assert math.isnan(median_norm(np.empty((0, 3))))


def test_median_norm_of_a_few_rows_is_numpys() -> None:
    """A few rows (a service applying row by row) take a plain-Python path (NumPy's median
    alone cost 35 us a row): the same value as NumPy's, NaN and inf rows included."""
    import math

    from accelcal._triad_model import _FEW_ROWS, median_norm

    rng = np.random.default_rng(7)
    for trial in range(200):
        for n in range(_FEW_ROWS + 3):
            r = rng.normal(size=(n, 3)) * 5
            if n > 3 and trial % 2:
                r[rng.integers(n), 0] = np.nan
            if n > 5 and trial % 3 == 0:
                r[rng.integers(n), 1] = np.inf
            for finite in (False, True):
                norms = np.sqrt(np.einsum("ij,ij->i", r, r))
                if finite:
                    norms = norms[np.isfinite(norms)]
                want = float(np.median(norms)) if norms.size else math.nan
                got = median_norm(r, finite=finite)
                assert (math.isnan(want) and math.isnan(got)) or got == pytest.approx(
                    want, rel=1e-13), (n, finite, want, got)
