"""Small per-row tables: a centrifuge's per-position mean outputs, a gradiometer's per-azimuth
averages. Delimited text (comma, semicolon, tab or spaces; ``#`` comment lines; a decimal comma
beside another delimiter) with one header row whose columns are found by name and unit.

A column is recognised by its name without separators and case (``omega_rad_s``, ``Omega``,
``rpm``), its unit given in brackets (``omega [rpm]``, ``ax (m/s^2)``), in a units row under the
header (``-, rad/s, -, g, g, g``, as DAQ exports write it) or implied by the name (``N_ax_g``,
``azimuth_deg``); values are converted to the unit the fit works in.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ._core import CalibrationError
from .io import _field_kind, _guess_delim, _is_number, _norm, _split, _split_unit, _units_row

__all__ = ["Col", "read_table"]


def _unit_key(unit: str) -> str:
    """``'m/s^2'``, ``'m/s²'``, ``'m s-2'`` -> ``'m/s2'``-like keys, lower case."""
    u = unit.strip().lower().replace("²", "2").replace("^", "").replace("**", "")
    u = u.replace("°", "deg").replace("µ", "u").replace(" ", "")
    return {"ms-2": "m/s2", "m.s-2": "m/s2", "mps2": "m/s2", "ms2": "m/s2", "m/s/s": "m/s2",
            "s-2": "1/s2", "/s2": "1/s2", "r/min": "rpm", "rev/min": "rpm", "rev/s": "hz",
            "eotvos": "e", "degrees": "deg", "degree": "deg", "radians": "rad",
            "sec": "s", "minutes": "min", "hours": "h", "hr": "h"}.get(u, u)


@dataclass(frozen=True)
class Col:
    """One column a table reader looks for.

    key : the name the reader returns it under.  what : words for messages.
    names : normalised names (see :func:`accelcal.io._norm`) -> the unit the name implies
        ("" when it implies none).
    units : unit key (:func:`_unit_key`) -> factor to the working unit.
    default : unit key used when neither the header nor the name states one.
    required : False for a column that may be absent.
    """

    key: str
    what: str
    names: Mapping[str, str]
    units: Mapping[str, float]
    default: str = ""
    required: bool = True

    def accepted(self) -> str:
        units = ", ".join(u for u in self.units if u) or "no unit"
        return f"{self.what} ({self.key}; units {units})"


def _number(field: str, delim: str | None) -> float:
    """The value of a field the text reader calls a number (decimal comma included)."""
    kind = _field_kind(field, delim)
    if kind == "num":
        return float(field)
    if kind == "dc":
        return float(field.replace(",", ".", 1))
    raise ValueError(field)


#: What a units row writes for a column without a unit.
_NO_UNIT = {"", "-", "1"}


def _table_units_row(path: str | os.PathLike[str], body: list[tuple[int, str]],
                     names: list[str], delim: str | None) -> list[str] | None:
    """The units of the row under the header (``-, rad/s, -, g, g, g``), read as the stream
    reader reads one (:func:`accelcal.io._units_row`); None when the first row under the
    header is data. A row of as many fields as the header with no number in it that is not
    a row of known units is refused."""
    if not body:
        return None
    no, line = body[0]
    fields = [f.strip().strip("'\"") for f in _split(line, delim)]
    if len(fields) != len(names) or any(_is_number(f) for f in fields if f):
        return None
    units = _units_row(fields)
    if units is not None:
        return units
    # Each field on its own ([f, f]: the helper wants two units to call a row one). Mostly
    # units with some unknown (``-, furlong/fortnight, -, g, g, g``): a units row this reader
    # cannot read; mostly not units (a second line of text): left to the checks below.
    given = [(f, n) for f, n in zip(fields, names, strict=True) if f.strip("[]() ")]
    unknown = [f"{f!r} ({n!r})" for f, n in given if _units_row([f, f]) is None]
    if 2 * len(unknown) > len(given):
        return None
    raise CalibrationError(
        f"{path}: line {no} looks like a units row: {', '.join(fields)}; "
        + (f"not a unit this reader knows: {', '.join(unknown)}; " if unknown else "")
        + "write each unit in the header instead (ax [m/s^2], omega [rpm]) or remove the row"
    )


def read_table(path: str | os.PathLike[str], cols: Sequence[Col], what: str,
               with_lines: bool = False) -> dict[str, NDArray[np.float64]]:
    """Read ``path`` and return each of ``cols`` it has (converted to its working unit) by
    key; an optional column the file does not have is absent. ``with_lines``: also the file's
    line number (1-based) of each row, under ``"_line"``."""
    try:
        with open(path, encoding="utf-8-sig", newline="") as fh:
            text = fh.read()
    except OSError as e:
        raise CalibrationError(f"cannot read {what} {str(path)!r}: {e.strerror}") from None
    except UnicodeDecodeError:
        raise CalibrationError(f"{path}: not a text table ({what})") from None
    lines = [(i + 1, ln.strip()) for i, ln in enumerate(text.splitlines())
             if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise CalibrationError(f"{path}: no header row ({what})")
    head_no, header = lines[0]
    body = lines[1:]
    delim = _guess_delim(body[0][1] if body else header)
    names = [h.strip().strip("'\"") for h in _split(header, delim)]
    row_units = _table_units_row(path, body, names, delim)
    if row_units is not None:
        units_no, body = body[0][0], body[1:]
    found: dict[str, tuple[int, float]] = {}
    for j, name in enumerate(names):
        base, unit = _split_unit(name)
        key = _norm(base)
        if row_units is not None:
            row_unit = "" if row_units[j] in _NO_UNIT else row_units[j]
            if unit and row_unit and _unit_key(unit) != _unit_key(row_unit):
                raise CalibrationError(
                    f"{path}: column {name!r} says {unit!r} in its name but {row_unit!r} in "
                    f"the units row (line {units_no}): keep one"
                )
            unit = unit or row_unit
        for c in cols:
            if key not in c.names:
                continue
            u = _unit_key(unit or c.names[key] or c.default)
            if u not in c.units:
                raise CalibrationError(
                    f"{path}: column {name!r} ({c.what}) is in {unit or u!r}, a unit this "
                    f"reader does not know; use one of: {', '.join(x for x in c.units if x)}"
                )
            if c.key in found:
                raise CalibrationError(
                    f"{path}: columns {names[found[c.key][0]]!r} and {name!r} are both "
                    f"{c.what}: keep one"
                )
            found[c.key] = (j, c.units[u])
    missing = [c for c in cols if c.required and c.key not in found]
    if missing:
        raise CalibrationError(
            f"{path}: missing column(s) for " + "; ".join(c.accepted() for c in missing)
            + f"; the header (line {head_no}) has {names}"
        )
    if not body:
        raise CalibrationError(f"{path}: no data rows ({what})")
    vals = np.empty((len(body), len(names)))
    for r, (no, ln) in enumerate(body):
        fields = _split(ln, delim)
        if len(fields) != len(names):
            raise CalibrationError(
                f"{path}: line {no} has {len(fields)} fields where the header has {len(names)}"
            )
        for j, f in enumerate(fields):
            if not any(found[k][0] == j for k in found):
                continue
            try:
                vals[r, j] = _number(f, delim)
            except ValueError:
                raise CalibrationError(
                    f"{path}: line {no}, column {names[j]!r}: {f!r} is not a number"
                ) from None
    out: dict[str, NDArray[np.float64]] = {}
    for k, (j, factor) in found.items():
        col = vals[:, j] * factor
        if not np.all(np.isfinite(col)):
            bad = int(np.flatnonzero(~np.isfinite(col))[0])
            raise CalibrationError(
                f"{path}: line {body[bad][0]}, column {names[j]!r}: not a finite number"
            )
        out[k] = col
    if with_lines:
        out["_line"] = np.array([no for no, _ in body], dtype=np.float64)
    return out


#: Angular rate units -> rad/s.
RATE_UNITS = {"rad/s": 1.0, "rpm": 2.0 * math.pi / 60.0, "deg/s": math.pi / 180.0,
              "hz": 2.0 * math.pi}
#: Angle units -> degrees.
ANGLE_UNITS = {"deg": 1.0, "rad": 180.0 / math.pi}
#: Gravity-gradient units -> E (1 E = 1e-9 s^-2).
GRADIENT_UNITS = {"e": 1.0, "me": 1e-3, "1/s2": 1e9}
#: Time units -> s.
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "min": 60.0, "h": 3600.0}
