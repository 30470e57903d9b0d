"""Readers for accelerometer recordings: delimited text (with or without header and metadata
lines, from a file or ``-`` for standard input), ``.npy``, ``.npz``, HDF5, MATLAB ``.mat`` (v5
and v7.3), spreadsheets (``.xlsx``, ``.xls``, ``.ods``: phyphox's default export; through
pandas), Parquet and Feather tables (through pyarrow), National Instruments TDMS (LabVIEW;
through npTDMS), miniSEED (seismic loggers;
through ObsPy), ROS bags (through rosbags), and tables already in memory (a pandas or polars
DataFrame, anything with ``__array__``); plus chunked reading that streams large files into
:class:`~accelcal.DwellAccumulator` in one pass.

Text is parsed by the Rust core in blocks of whole lines, in parallel and with the
interpreter released: reading is faster than ``pandas.read_csv`` and streaming keeps memory
bounded whatever the file's length. A regular file is memory-mapped (read where it lies in
the file cache, each block's pages let go once parsed); set the environment variable
``ACCELCAL_MMAP=0`` to read it with plain reads instead, e.g. for a file that another program
may truncate while it is being read (a mapped file that shrinks ends the process with SIGBUS).

Layout rules for text files
---------------------------
* Fields are separated by tabs, semicolons, commas or runs of spaces (the first of these
  that splits the first data row into numbers). Fields may be quoted (CSV). Lines may end
  in ``\\n`` or ``\\r\\n``; the last line needs no line end.
* Numbers may use a decimal comma (``9,81``) when the delimiter is not a comma.
* A time column may hold ISO-8601 dates and times (``2024-03-01T12:00:00.125Z``, a space
  instead of ``T``, an optional UTC offset; no offset means UTC); it is read as seconds since
  the first row's time, which is kept in :attr:`Stream.t0`. Other time stamps (a time of day,
  ``23:59:59.990``, a day added where it passes midnight; a date day-first with ``.``,
  ``01.03.2024 23:59:00,000``, or with ``/`` or ``-`` in the order a number above 12, or the
  clock running on without a jump, tells; ``AM``/``PM``) are read the same way, through
  pandas; stamps in another format are refused naming the column (``time_column="none"``
  and ``fs=`` read the file without them).
* Lines before the data may be metadata: ``key,value``, ``key: value``, ``key = value``, each
  optionally commented with ``#``. A numeric ``Fs`` / ``fs`` / ``sample_rate`` / ``rate``
  (any case) gives the sample rate. Lines starting with ``#`` are comments anywhere.
* The last non-numeric line with at least three fields right before the data is the header.
* Accelerometer columns are chosen by name (``ax``/``ay``/``az``, ``acc_x``..., ``accx``...,
  ``accel_x``..., and only when none of those exist ``x``/``y``/``z``; unit suffixes such as
  ``acc_x [m/s^2]`` are ignored). A time column is recognised by name (``t``, ``time``,
  ``timestamp``, ``t[s]``, ``time_s``, ``time_ms`` ...; ``ms``/``us``/``ns`` units are converted
  to s, as are Unix epoch stamps in ms/us/ns under a name without a unit; without such a name,
  the first column of ISO-8601 times) and a temperature column by a name starting with
  ``temp``. A temperature written on some rows only (its other fields empty) holds its last
  value. A row whose accelerometer fields are all empty (a row of another sensor in a merged
  log) is left out, whatever else it leaves empty; in a row that is kept, an empty
  accelerometer or time field is an error. From a time column the sample rate is the average
  of its regular intervals (those within half the median interval).
* Without a header, three columns are ``x, y, z``; with ``columns`` given or four columns,
  a remaining column that increases strictly (over the first 10 000 rows) is the time in s,
  unless it counts 0, 1, 2, ... (a sample counter). Among more columns, the only three
  adjacent ones whose row norm stays at 1 g (m/s^2, g, mg or int16 counts, within 5 % in
  75 % of the head rows) are the accelerometer, with a note; anything else needs
  ``columns``.
"""

from __future__ import annotations

import collections
import contextlib
import errno
import itertools
import math
import os
import re
import stat
import sys
import weakref
import zipfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from . import _core
from ._core import CalibrationError
from ._pose_table import MEAN_NAME, POSE_TABLE_ROWS, pose_table, too_slow_for_detection
from ._validate import positive

__all__ = [
    "Bounds", "Stream", "iter_stream", "read_bounds", "read_means", "read_stream", "stream_dwells",
]

#: Rows sniffed at the start of a text file (layout, time-column check, fs estimate).
_SNIFF_ROWS = 10_000
#: Most lines accepted before the first data row (the sniffed head ends before that anyway).
_MAX_PREAMBLE = 100_000
#: Bytes read to decide the layout of a text file.
_HEAD_BYTES = 1 << 21
#: Fraction of repeated rows above which the sensor is taken to be read faster than it updates.
_REPEAT_FRACTION = 0.25

_FS_KEYS = {
    "fs",
    "fshz",
    "samplerate",
    "sampleratehz",
    "samplingrate",
    "samplingratehz",
    "samplingfrequency",
    "samplingfrequencyhz",
    "rate",
    "ratehz",
    "odr",
    "odrhz",
    "abtastrate",
    "abtastfrequenz",
    "frequenz",
}
_TIME_BASES = {
    "t", "ts", "time", "timestamp", "timestamps", "tstamp", "elapsed", "elapsedtime", "datetime",
    "unixtime", "epoch", "epochtime", "posixtime", "timeutc", "utc", "sec", "secs", "seconds",
    "xvalue",  # LabVIEW .lvm
    "timesincestart", "timeelapsed", "relativetime", "reltime",  # AndroSensor and others
}
#: Names that are a time with their unit in the name (Arduino's millis() and micros(), Xsens's
#: SampleTimeFine in ticks of 100 us).
_TIME_IMPLICIT = {"millis": 1e-3, "micros": 1e-6, "sampletimefine": 1e-4}  # Xsens: 100 us
_TIME_UNITS = {
    "": 1.0,
    "s": 1.0,
    "sec": 1.0,
    "secs": 1.0,
    "seconds": 1.0,
    "ms": 1e-3,
    "msec": 1e-3,
    "us": 1e-6,
    "usec": 1e-6,
    "µs": 1e-6,
    "ns": 1e-9,
    "nsec": 1e-9,
}
#: Accelerometer column names after `_norm`: an optional device prefix, the axis, and an
#: optional unit or kind suffix (``imu.acc.x``, ``Ax_g``, ``acc_x_mps2``, ``accel_x_raw``,
#: and ``AcX`` of the common MPU-6050 Arduino sketch).
_ACC_NAME = re.compile(
    r"^(?:imu|sensor|device|phone)?"
    r"(?:a|ac|acc|accl|accel|acceleration|accelerometer|linacc|rawacc|accraw|gf|gforce)([xyz])"
    r"(?:g|mg|ms2|mps2|mss|si|raw|counts|lsb|adc)?$"
)
_SAMPLE_KEYS = ("samples", "acc", "accel", "acceleration", "a", "data", "x")
_T_KEYS = ("t", "time", "timestamp", "timestamps", "t_s")
_FS_NPZ_KEYS = ("fs", "fs_hz", "sample_rate", "sampling_rate", "rate")
_TEMP_KEYS = ("temperature", "temp", "temperature_c", "temp_c")


@dataclass
class Stream:
    """A recording read from a file (or a table in memory).

    Attributes
    ----------
    samples : (N, 3) array
        Accelerometer output x, y, z in the file's units (float64 for text files; the stored
        dtype for ``.npy``/``.npz``/HDF5).
    t : (N,) float64 or None
        Sample times in s (from the time column, else ``arange(N) / fs``; None when neither).
        An ISO-8601 time column is given as seconds since its first row (see ``t0``).
    fs : float or None
        Sample rate in Hz: given > file metadata > average regular interval of the time column.
    metadata : dict
        ``key -> value`` strings from the lines before the data (and scalar ``.npz`` entries).
    names : tuple of str
        Names of the three chosen columns (``"0"``, ``"1"`` ... when the file has no header).
    path : str
        The file read (``"-"`` for standard input, ``"<table>"`` for a table in memory).
    temperature : (N,) float64 or None
        Temperature per sample when a temperature column was recognised.
    t0 : str or None
        The first row's ISO-8601 time when the time column holds dates and times.
    fs_source : str or None
        Where ``fs`` came from: ``"given"``, ``"metadata"``, ``"time column"`` or None.
    notes : list of str
        What a person should know about how the file was read (sample rate missing or in
        disagreement with the time column, repeated samples, a sample counter column ...).
    repeats : int
        Rows that repeat the previous row's x, y, z exactly.
    output_rate_hz : float or None
        The sensor's own output rate estimated from repeated rows when it is read faster
        than it updates (``fs * distinct rows / rows``); None when the rows rarely repeat.
    sections : Bounds or None
        The labelled static sections of an annotated session (a text column naming each
        row's section, ``x_p``, ``x_rot`` ...), as known dwells; None otherwise.
    """

    samples: NDArray[Any]
    t: NDArray[np.float64] | None
    fs: float | None
    metadata: dict[str, str] = field(default_factory=dict)
    names: tuple[str, ...] = ()
    path: str = ""
    temperature: NDArray[np.float64] | None = None
    t0: str | None = None
    fs_source: str | None = None
    notes: list[str] = field(default_factory=list)
    repeats: int = 0
    output_rate_hz: float | None = None
    sections: Any = None

    def __len__(self) -> int:
        return int(self.samples.shape[0])


# ---- name handling ----------------------------------------------------------------------------
def _split_unit(name: str) -> tuple[str, str]:
    """``'acc_x [m/s^2]' -> ('acc_x', 'm/s^2')``; ``'time_ms' -> ('time', 'ms')`` for time units."""
    s = name.strip().strip("\"'").strip()
    m = re.match(r"^(.*?)\s*[\[\(]\s*([^\]\)]*?)\s*[\]\)]\s*$", s)
    if m:
        return m.group(1), m.group(2)
    return s, ""


#: Accelerometer units a column name may declare, as the norm of gravity in them.
_DECLARED_G = {"g": 1.0, "m/s^2": 9.80665, "m/s2": 9.80665, "m/s²": 9.80665, "mps2": 9.80665,
               "ms2": 9.80665, "m s-2": 9.80665, "cm/s^2": 980.665, "mg": 1000.0}


def _column_units(names: Sequence[str]) -> list[str]:
    """The unit each accelerometer column's name declares (``aX (g)``, ``acc_x [m/s^2]``,
    ``ax_g``, ``acc_x_mps2``), or ``""``."""
    out = []
    for n in names:
        base, unit = _split_unit(n)
        if not unit:
            m = re.search(r"[_\s](g|mps2|ms2|mg)$", base.strip().lower())
            unit = m.group(1) if m else ""
        out.append(unit.strip())
    return out


def declared_unit(names: Sequence[str] | None) -> str:
    """The raw (input) unit the three accelerometer columns' names declare alike (``ax [mg]``,
    ``ay [mg]``, ``az [mg]`` -> ``"mg"``; ``acc_x_mps2`` -> ``"m/s^2"``), as a calibration
    records it; ``""`` when they declare none, differ, or hold an index (``acc[0]``)."""
    if not names or len(names) != 3:
        return ""
    units = _column_units(names)
    unit = units[0]
    if not unit or any(u != unit for u in units) or unit.isdigit():
        return ""
    return {"mps2": "m/s^2", "ms2": "m/s^2"}.get(unit.lower(), unit)


def declared_units_note(names: Sequence[str] | None, median_norm: float) -> str:
    """When the accelerometer columns' names declare a unit (``aX (g)``, ``acc_x [m/s^2]``,
    ``ax_g``, ``acc_x_mps2``) in which gravity's norm is not what the dwell means show
    (``median_norm``, their median norm): the note that says so, else ``""``."""
    if not names or not math.isfinite(median_norm) or median_norm <= 0:
        return ""
    units = {u.lower().replace(" ", "") for u in _column_units(names)}
    if len(units) != 1:
        return ""
    unit = units.pop()
    want = _DECLARED_G.get(unit)
    if want is None or 0.7 <= median_norm / want <= 1.4:
        return ""
    like = min(_DECLARED_G.items(), key=lambda kv: abs(math.log(median_norm / kv[1])))
    looks = (f": the outputs look like {like[0]}" if 0.7 <= median_norm / like[1] <= 1.4
             else " (raw counts?)")
    return (f"the accelerometer columns say {unit} ({', '.join(names)}), but the dwell means' "
            f"norms are about {median_norm:.4g}, where gravity in {unit} is {want:g}{looks}. The "
            "calibration maps whatever the columns hold to the units of --g; check the "
            "logger's conversion")


def _norm(name: str) -> str:
    base, _ = _split_unit(name)
    return re.sub(r"[^0-9a-zµ]", "", base.lower())


def _time_name(name: str) -> tuple[float, bool] | None:
    """``(factor to seconds, whether the name states the unit)`` when ``name`` is a time
    column, else None."""
    base, unit = _split_unit(name)
    b = base.lower().strip()
    if not unit:
        m = re.match(r"^(.*?)(?:[_\s-]+in)?[_\s-]+(s|sec|secs|seconds|ms|msec|us|usec|µs|ns|nsec)$",
                     b)
        if m:
            b, unit = m.group(1), m.group(2)
    if not unit:  # the unit glued on: ``ustime``, ``ms_time``, ``timeus``
        m = re.match(r"^(ms|us|µs|ns)[_\s-]*(time|timestamp)$", b)
        if m:
            b, unit = m.group(2), m.group(1)
        else:
            m = re.match(r"^(time|timestamp)(ms|us|ns)$", b)
            if m:
                b, unit = m.group(1), m.group(2)
    words = [w for w in re.split(r"[^0-9a-z]+", b) if w]
    b = "".join(words)
    if b in _TIME_IMPLICIT and not unit:
        return _TIME_IMPLICIT[b], True
    # A time stamp among other words (Shimmer's ``Shimmer_9A2F_Timestamp_Unix_CAL``).
    if b not in _TIME_BASES and not (
            {"time", "timestamp"}.intersection(words) and not {"x", "y", "z"}.intersection(words)
            and len(words) > 1):
        return None
    scale = _TIME_UNITS.get(unit.lower().strip())
    return None if scale is None else (scale, bool(unit))


#: Unix epoch times of the years 2000-2100 in s; a time column without a stated unit whose
#: first value is such a time in ms, us or ns is read in that unit.
_EPOCH_S = (9.46e8, 4.11e9)


def _epoch_unit(v0: float) -> tuple[str, float] | None:
    for unit, f in (("ms", 1e-3), ("us", 1e-6), ("ns", 1e-9)):
        if _EPOCH_S[0] <= v0 * f <= _EPOCH_S[1]:
            return unit, f
    return None


def _gravity_removed(name: str) -> bool:
    """A name of a gravity-free acceleration (phyphox's "Linear Acceleration x", Android's
    linear_acceleration, Core Motion's userAcceleration)."""
    n = _norm(name)
    return any(k in n for k in ("linear", "linacc", "useracc", "withoutg", "nogravity"))


def _is_temperature(name: str) -> bool:
    n = _norm(name)
    return n.startswith("temp") or n == "tmp"  # Tmp: the MPU-6050 sketch's temperature


def _auto_acc(names: Sequence[str], path: str) -> list[int] | None:
    """Indices of the x, y, z accelerometer columns chosen by name, or None."""
    norm = [_norm(n) for n in names]
    for tier in ("acc", "plain", "mean"):
        found: dict[str, list[int]] = {"x": [], "y": [], "z": []}
        for i, n in enumerate(norm):
            if tier == "acc":
                m = _ACC_NAME.match(n)
                if m:
                    found[m.group(1)].append(i)
            elif tier == "mean":  # a table of dwell means (x_mean, mean_ax ...)
                m = MEAN_NAME.match(n)
                if m:
                    found[next(g for g in m.groups() if g)].append(i)
            elif n in found:
                found[n].append(i)
        if not any(found.values()):
            continue
        if all(len(v) == 1 for v in found.values()):
            return [found["x"][0], found["y"][0], found["z"][0]]
        raise CalibrationError(
            f"{path}: cannot tell which columns are the accelerometer x, y, z among {list(names)}; "
            "give columns=[...] (3 names or 0-based indices)"
        )
    triads = _numbered_triads(names) or _worded_triads(names)
    if len(triads) == 1:  # one sensor with a number in its names (acc1_x, ...)
        return [list(names).index(n) for n in triads[0]]
    if len(triads) > 1:
        bare = [[_split_unit(n)[0] for n in t] for t in triads]
        listed = "; ".join(",".join(t) for t in bare)
        raise CalibrationError(
            f"{path}: {len(triads)} accelerometer triads ({listed}): a recording of several "
            f"sensors or ranges; calibrate one at a time, giving its three names with "
            f"columns=, e.g. {','.join(bare[0])!r}"
        )
    return None


#: Words that make a name an accelerometer's when it also has an axis word of its own.
_ACC_WORDS = {"acc", "accl", "accel", "acceleration", "accelerometer", "linacc", "gforce"}


def _worded_triads(names: Sequence[str]) -> list[tuple[str, str, str]]:
    """Accelerometer triads in names made of words, with the axis a word of its own among
    others (Shimmer's ``Shimmer_9A2F_Accel_LN_X_CAL``): names equal but for the axis form a
    triad, in the order of the file."""
    groups: dict[tuple[str, ...], dict[str, str]] = {}
    for n in names:
        words = [w for w in re.split(r"[^0-9a-z]+", _split_unit(n)[0].lower()) if w]
        axes = [i for i, w in enumerate(words) if w in ("x", "y", "z")]
        if len(axes) != 1 or not _ACC_WORDS.intersection(words):
            continue
        i = axes[0]
        groups.setdefault((*words[:i], "*", *words[i + 1:]), {})[words[i]] = n
    return [(g["x"], g["y"], g["z"]) for g in groups.values() if len(g) == 3]


def _numbered_triads(names: Sequence[str]) -> list[tuple[str, str, str]]:
    """Accelerometer triads told apart by a number in their names (``ax1..az1, ax2..az2``,
    ``acc1_x``, ``imu0.acc.x``), in the order of the file."""
    groups: dict[str, dict[str, str]] = {}
    for n in names:
        base = _norm(n)
        digits = "".join(re.findall(r"\d+", base))
        if not digits:
            continue
        m = _ACC_NAME.match(re.sub(r"\d+", "", base))
        if m:
            groups.setdefault(digits, {})[m.group(1)] = n
    return [(g["x"], g["y"], g["z"]) for g in groups.values() if len(g) == 3]


def _time_spec(c: Any, names: Sequence[str] | None) -> tuple[Any, float | None]:
    """A ``time_column`` given as ``"name [unit]"`` or ``"index [unit]"`` (unit s, ms, us or
    ns): the column and the factor to seconds (None when no unit is given)."""
    if not isinstance(c, str) or (names is not None and c in names):
        return c, None
    base, unit = _split_unit(c)
    if not unit:
        return c, None
    scale = _TIME_UNITS.get(unit.lower().strip())
    if scale is None:
        raise CalibrationError(
            f"time_column= {c!r}: unknown time unit {unit!r}; use s, ms, us or ns, e.g. "
            f"'{base} [ms]'"
        )
    return base, scale


def _three(columns: Any, what: str = "columns") -> list[Any]:
    """User ``columns`` (3 names/indices, or "a,b,c") as a list of three."""
    if isinstance(columns, str):
        columns = [c.strip() for c in columns.split(",")]
    try:
        cols = list(columns)
    except TypeError:
        raise CalibrationError(
            f"columns must be 3 names or 0-based indices; got {columns!r}"
        ) from None
    if len(cols) != 3:
        more = ", or 4 (x, y, z, temperature)" if what == "columns" else ""
        raise CalibrationError(f"columns must name exactly 3 {what} (x, y, z){more}; got "
                               f"{cols!r}")
    return cols


def _split_columns(columns: Any) -> tuple[list[Any], Any]:
    """User ``columns``: the accelerometer's x, y, z and, when a fourth is given, the
    temperature column (a file without a header cannot name it)."""
    cols = [c.strip() for c in columns.split(",")] if isinstance(columns, str) else columns
    try:
        cols = list(cols)
    except TypeError:
        cols = columns
    if isinstance(cols, list) and len(cols) == 4:
        return cols[:3], cols[3]
    return _three(cols), None


def _resolve_columns(columns: Any, names: Sequence[str] | None, ncols: int, path: str) -> list[int]:
    """User ``columns`` (3 names/indices or "a,b,c") to 0-based indices."""
    return [_resolve_one(c, names, ncols, path, "columns") for c in _three(columns)]


def _resolve_one(c: Any, names: Sequence[str] | None, ncols: int, path: str, what: str) -> int:
    if isinstance(c, (int, np.integer)) and not isinstance(c, bool):
        i = int(c)
        if not -ncols <= i < ncols:
            raise CalibrationError(f"{path}: {what} index {i} out of range for {ncols} columns")
        return i % ncols
    if isinstance(c, str):
        if c.strip().lstrip("-").isdigit() and (names is None or c not in names):
            return _resolve_one(int(c), names, ncols, path, what)
        if names is None:
            raise CalibrationError(
                f"{path}: the file has no header row, so {what} must be 0-based indices; got {c!r}"
            )
        if c in names:
            return list(names).index(c)
        hits = [i for i, n in enumerate(names) if _norm(n) == _norm(c)]
        if len(hits) == 1:
            return hits[0]
        raise CalibrationError(f"{path}: no column named {c!r} ({what}); columns are {list(names)}")
    raise CalibrationError(f"{what} entries must be names or 0-based indices; got {c!r}")


# ---- text layout ------------------------------------------------------------------------------
def _is_number(s: str) -> bool:
    if "_" in s:  # Python's float() takes 1_000; the file reader does not
        return False
    try:
        float(s)
    except ValueError:
        return False
    return True


def _split(line: str, delim: str | None) -> list[str]:
    if delim is None:
        return line.split()
    return [f.strip().strip('"').strip() for f in line.split(delim)]


#: Units a units row under a header may hold (besides the time units), lower case.
_ROW_UNITS = {
    "g", "mg", "ug", "µg", "m/s^2", "m/s2", "m/s²", "m/s/s", "ms^-2", "ms-2", "mps2", "counts",
    "count", "lsb", "digits", "adc", "raw", "v", "mv", "c", "°c", "degc", "deg c", "k", "°f",
    "-", "1",
    # rates and angles (a gyroscope's columns, a centrifuge table's rate)
    "rad/s", "deg/s", "°/s", "dps", "rpm", "hz", "deg", "rad", "°",
}


def _units_row(fields: list[str]) -> list[str] | None:
    """The units of a second header row (``s, m/s^2, m/s^2, m/s^2`` under the names, as DAQ
    exports write them; Shimmer writes ``m/(s^2)``), brackets removed; None when the row is
    not one."""
    units = [f.strip().strip("[]()").replace("(", "").replace(")", "").strip() for f in fields]
    known = [u.lower() in _ROW_UNITS or u.lower() in _TIME_UNITS for u in units if u]
    if len(known) >= 2 and all(known):
        return units
    return None


#: A row under the names that says whether each column is calibrated (Shimmer's ``CAL``).
_KIND_ROW = {"cal", "raw", "uncal", "calibrated", "uncalibrated"}


def _kind_row(fields: list[str]) -> bool:
    kinds = [f.strip().lower() for f in fields if f.strip()]
    return len(kinds) >= 2 and all(k in _KIND_ROW for k in kinds)


def _guess_delim(line: str) -> str | None:
    for d in ("\t", ";", ","):
        if d in line:
            return d
    return None


def _field_kind(f: str, delim: str | None) -> str | None:
    """"num", "dc" (decimal-comma number), "iso", "empty" or None (not data)."""
    if not f:
        return "empty"
    if _is_number(f):
        return "num"
    if delim != "," and "," in f and "." not in f and _is_number(f.replace(",", ".", 1)):
        return "dc"
    if len(f) >= 16 and f[4:5] == "-" and _core.parse_iso8601(f) is not None:
        return "iso"
    return None


@dataclass
class _RowFormat:
    delim: str | None
    fields: list[str]
    kinds: list[str]


def _data_row(s: str) -> _RowFormat | None:
    """How a line splits into a data row (numbers, decimal-comma numbers, ISO times), or None."""
    cands: list[str | None] = [d for d in ("\t", ";", ",") if d in s]
    cands.append(None)
    for d in cands:
        fields = _split(s, d)
        kinds = [_field_kind(f, d) for f in fields]
        if all(k is not None for k in kinds) and any(k in ("num", "dc") for k in kinds):
            return _RowFormat(d, fields, [str(k) for k in kinds])
    return None


def _numeric_columns(data: bytes, delim: str | None, ncols: int, lines: int = 200) -> list[int]:
    """Columns holding no text (numbers, ISO times or nothing) in the first ``lines`` data
    rows of ``data``."""
    text: set[int] = set()
    seen = 0
    for raw in data[: 1 << 16].split(b"\n")[:-1]:
        s = raw.decode("utf-8", "replace").strip()
        if not s or s.startswith(("#", "%", "//")):
            continue
        fields = _split(s, delim)
        if len(fields) == ncols:
            text.update(j for j, f in enumerate(fields) if _field_kind(f, delim) is None)
        seen += 1
        if seen >= lines:
            break
    return [j for j in range(ncols) if j not in text]


class _LongFormat(CalibrationError):
    """Data rows with a text label: a long-format log (one row per sensor reading)."""


class _LabelPairs(CalibrationError):
    """Rows of label-value pairs (``Ax 0.00 Ay -1.23 Az -10.12``): a serial monitor's log."""


#: Units a serial sketch prints after a number (``Z: 9.81 m/s^2``, ``X: 0.01g``).
_PAIR_UNIT = (r"(?:m/s\^?2|m/s²|m/s/s|m ?s\^?-2|\[m/s\^?2\]|\[g\]|mg|mG|g's|g|G|deg/s|dps"
              r"|rad/s|radians/s|°C|C|degC|LSB|counts|raw|uT)")
_PAIR_LABEL = r"[A-Za-z_][\w.\[\]/^]*"


def _pair_pattern(number: str) -> re.Pattern[str]:
    """A label, its number and an optional unit (``Ax 0.00``, ``ax: 0.0``, ``ax=0.0 g``):
    the label and the number apart (``c0`` is a name, not a pair)."""
    return re.compile(rf"({_PAIR_LABEL})(?:\s*[:=]\s*|\s+)({number})(?:\s*({_PAIR_UNIT}))?"
                      r"(?![\w./^²°'])")


#: A number as the serial rows print it (a sign, a decimal point, an exponent).
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_PAIR = _pair_pattern(_NUMBER.pattern)
#: The same with a decimal comma (``X: 0,11; Y: -0,18; Z: 10,16``).
_PAIR_DC = _pair_pattern(r"[-+]?\d+(?:,\d+)?(?!\d)")
#: A word of a sensor's name before its pairs (``Acceleration``, ``Accel:``, ``in g's``).
_PAIR_WORD = re.compile(r"[A-Za-z][\w'/]*:?")
#: At most this many words name a sensor, and labels of at most 2 characters take its name
#: (``Accel X``; a longer label, ``Temp: 25.3``, stands alone).
_PAIR_NAME_WORDS, _PAIR_SHORT = 4, 2


class _Pair(NamedTuple):
    label: str
    value: str
    unit: str


def _pairs_of(s: str, pattern: re.Pattern[str], dc: bool) -> list[_Pair] | None:
    """The pairs of ``s`` read with ``pattern``, each short label prefixed by the sensor's
    name before it (``Acceleration in g's X``, ``Gyro X``), or None when anything but
    pairs, names and separators (blanks, commas, semicolons, bars) is left."""
    out: list[_Pair] = []
    name: list[str] = []
    after_pair = False
    pos, n = 0, len(s)
    while pos < n:
        if s[pos] in " \t,;|":
            pos += 1
            continue
        m = pattern.match(s, pos)
        if m is not None:
            label, value, unit = m.group(1), m.group(2), m.group(3) or ""
            if len(label) > _PAIR_SHORT:
                name = []  # a label of its own: the name before it ends
            elif name:
                label = f"{' '.join(name)} {label}"
            out.append(_Pair(label, value.replace(",", ".") if dc else value, unit))
            after_pair, pos = True, m.end()
            continue
        w = _PAIR_WORD.match(s, pos)
        if w is None:
            return None
        if after_pair:
            name, after_pair = [], False
        name.append(w.group(0).rstrip(":"))
        if len(name) > _PAIR_NAME_WORDS:
            return None
        pos = w.end()
    return out if len(out) >= 3 and not (name and not after_pair) else None


#: A sensor's values in brackets, its unit in parentheses (SparkFun's ICM-20948 example:
#: ``Scaled. Acc (mg) [ 000689.88, 000229.33, 000943.60 ], Gyr (DPS) [ ... ]``).
_BRACKETS = re.compile(r"([A-Za-z][\w]*)\s*(?:\(([^)]*)\))?\s*\[\s*([-+\d.eE]+(?:\s*,\s*"
                       r"[-+\d.eE]+)*)\s*\]")


def _bracket_pairs(s: str) -> list[_Pair] | None:
    """The values of a row of bracketed triads (``Acc (mg) [ x, y, z ], Gyr (DPS) [ ... ]``)
    as pairs labelled ``Acc x`` ..., or None: at least one triad, and nothing else but words
    (``Scaled.``) and separators."""
    out: list[_Pair] = []
    for m in _BRACKETS.finditer(s):
        vals = [v.strip() for v in m.group(3).split(",")]
        if not all(_NUMBER.fullmatch(v) for v in vals):
            return None
        axes = ("x", "y", "z") if len(vals) == 3 else [str(i + 1) for i in range(len(vals))]
        labels = [m.group(1)] if len(vals) == 1 else [f"{m.group(1)} {a}" for a in axes]
        out += [_Pair(k, v, (m.group(2) or "").strip()) for k, v in zip(labels, vals,
                                                                         strict=True)]
    rest = _BRACKETS.sub(" ", s)
    if len(out) < 3 or any(ch.isdigit() for ch in rest):
        return None
    return out



def _label_pairs(line: str) -> list[_Pair] | None:
    """The (label, number, unit) pairs of a row of at least three label-value pairs and
    nothing else but separators and sensors' names, or None. A sensor's name before its
    pairs prefixes their labels (``Acceleration X``, Adafruit's examples; ``Acceleration in
    g's X`` then ``Rotation in deg/sec X``, SparkFun's); the numbers may have a decimal comma
    and a unit after them. Bracketed triads (``Acc (mg) [ x, y, z ]``) read as ``Acc x``..."""
    s = line.strip()
    pairs = _pairs_of(s, _PAIR, False)
    if pairs is None and "," in s:
        pairs = _pairs_of(s, _PAIR_DC, True)
    if pairs is None and "[" in s:
        pairs = _bracket_pairs(s)
    return pairs


def _acc_name(label: str) -> bool:
    """Whether a pair's label carries a sensor's name that says accelerometer."""
    if " " not in label:
        return False
    head = label.rsplit(" ", 1)[0].lower()
    return head in _ACC_LABELS | {"linear acceleration"} or head.split()[0] in _ACC_LABELS


def _names_acceleration(labels: tuple[str, ...]) -> bool:
    """Whether labels with a sensor's name before them (``Acceleration X``) name an
    accelerometer: exactly three of them do."""
    return sum(map(_acc_name, labels)) == 3


def _triads(pairs: list[_Pair]) -> tuple[list[str], list[int]]:
    """A row's labels made distinct (a label that repeats gets ``.2``, ``.3``: the LIS3DH
    example prints raw counts and m/s^2 as ``X: ... Y: ... Z: ... X: ... m/s^2``), and the
    indices of the accelerometer's three: those named so (``Accel X`` beside ``Gyro X``), else
    of repeated triads the one with a unit; [] when the labels alone decide."""
    seen: dict[str, int] = {}
    labels = []
    for p in pairs:
        seen[p.label] = seen.get(p.label, 0) + 1
        labels.append(p.label if seen[p.label] == 1 else f"{p.label}.{seen[p.label]}")
    acc = [i for i, p in enumerate(pairs) if _acc_name(p.label)]
    if len(acc) == 3 and len(acc) < len(pairs):
        return labels, acc
    if len(pairs) % 3 == 0 and len(seen) == 3 and len(pairs) > 3:  # repeated triads
        groups = [list(range(i, i + 3)) for i in range(0, len(pairs), 3)]
        with_unit = [g for g in groups if any(pairs[i].unit for i in g)]
        if len(with_unit) == 1:
            return labels, with_unit[0]
    return labels, []


def _label_pairs_source(src: _TextSource, columns: Any, fs: float | None,
                        time_column: Any) -> _ArraySource:
    """A log of label-value pairs (``Ax 0.00 Ay -1.23 Az -10.12``, as an Arduino sketch prints
    them; cuspaceflight/kestrel's ``acc_data.txt``; the Adafruit and SparkFun examples'
    ``Acceleration X: ...``): read in memory (such logs are small), the labels naming the
    columns. Rows with other labels (a line of another sensor, a message) are left out with a
    note; more than a quarter of them is an error, unless the rows kept name their sensor an
    accelerometer. Of rows with the same labels, those with a unit are kept when some have
    one (the others: raw counts on alternate lines, or rows cut short)."""
    import pandas as pd

    name = src.path
    rows: dict[tuple[tuple[str, ...], bool], list[list[float]]] = {}
    pick: dict[tuple[str, ...], list[int]] = {}
    other = 0
    try:
        with open(src.opened, encoding="utf-8-sig", errors="replace") as fh:
            for ln in fh:
                t = ln.strip()
                if not t or t.startswith(("#", "%", "//")):
                    continue
                pairs = _label_pairs(t)
                if pairs is None:
                    other += 1
                    continue
                row_labels, row_acc = _triads(pairs)
                key = tuple(row_labels)
                pick.setdefault(key, row_acc)
                rows.setdefault((key, any(p.unit for p in pairs)), []).append(
                    [float(p.value) for p in pairs])
    except OSError as e:
        raise CalibrationError(f"{name}: cannot read file ({e.strerror})") from None
    # Of rows with the same labels, those with a unit when some have one.
    unitless = {k: len(v) for (k, u), v in rows.items() if not u and (k, True) in rows}
    sets = {k: v for (k, u), v in rows.items() if u or (k, True) not in rows}
    # Rows that name their sensor (Adafruit's examples print `Acceleration X: ...`, then
    # `Rotation X: ...` and `Temperature: ...`): the accelerometer's, however many others.
    named = [kv for kv in sets.items() if _names_acceleration(kv[0])]
    labels, values = max(named or sets.items(), key=lambda kv: len(kv[1]))
    dropped = unitless.get(labels, 0)
    left = other + sum(len(v) for k, v in sets.items() if k != labels) + dropped
    total = left + len(values)
    if left > total / 4 and len(named) != 1 and not dropped:
        raise CalibrationError(
            f"{name}: a log of label-value pairs ({' '.join(labels)}) in only {len(values)} of "
            f"its {total} rows; write the accelerometer's rows to a file of their own")
    acc = pick.get(labels, [])
    chosen = columns if columns is not None or not acc else [labels[i] for i in acc]
    out = _dataframe_source(pd.DataFrame(values, columns=list(labels)), chosen, fs,
                            time_column, path=name, named=True)
    note = (f"rows of label-value pairs ({', '.join(labels)}): the labels name the columns")
    if chosen is not columns:
        note += f"; the accelerometer's: {', '.join(chosen)} (columns= picks others)"
    if dropped:
        note += (f"; {dropped} row(s) of the same labels without the unit the others carry "
                 "(raw counts on alternate lines, or rows cut short) left out")
    others = {k[0].rsplit(" ", 1)[0] if " " in k[0] else " ".join(k): len(v)
              for k, v in sets.items() if k != labels}
    if others:
        note += (f"; {sum(others.values())} row(s) of other sensors' pairs "
                 f"({', '.join(others)}) left out")
    if other:
        note += f"; {other} row(s) of other text left out"
    out.lay.notes.append(note)
    return out


#: Labels of accelerometer rows in a long-format log (lower case).
_ACC_LABELS = {
    "acc", "accel", "acceleration", "accelerometer", "a", "imu_acc", "acc_raw", "accraw",
    "android.sensor.accelerometer", "type_accelerometer", "accelerometer_uncalibrated",
}


class _Uncommented:
    """A text file without its comment lines (``#``, ``%``, ``//`` first), as a file object
    that hands out at most ``size`` characters per read."""

    def __init__(self, fh: Any) -> None:
        self._lines = (ln for ln in fh if not ln.lstrip().startswith(("#", "%", "//")))
        self._buf = ""

    def read(self, size: int = -1) -> str:
        want = size if size is not None and size >= 0 else None
        parts, n = [self._buf], len(self._buf)
        while want is None or n < want:
            ln = next(self._lines, "")
            if not ln:
                break
            parts.append(ln)
            n += len(ln)
        text = "".join(parts)
        if want is None:
            self._buf = ""
            return text
        self._buf = text[want:]
        return text[:want]

    def __iter__(self) -> Any:
        buf, self._buf = self._buf, ""
        yield from buf.splitlines(keepends=True)
        yield from self._lines


def _long_format_source(src: _TextSource, columns: Any, fs: float | None,
                        time_column: Any) -> _ArraySource:
    """A long-format log (``0.01,ACC,0.1,0.2,9.8``: a text column names each row's sensor):
    the rows whose label names an accelerometer, read through pandas (in memory), the label
    column dropped. ``src`` is the text whose head was read (its file may be a decompressed
    copy; messages name ``src.path``)."""
    name = src.path
    try:
        import pandas as pd
    except ImportError:
        raise CalibrationError(
            f"{name}: a long-format log (a text label in each row names its sensor); reading it "
            "needs pandas: pip install pandas") from None
    first, second = (list(itertools.islice(
        (ln.strip() for _, ln in _head_lines(src)
         if ln.strip() and not ln.strip().startswith(("#", "%", "//"))), 2)) + ["", ""])[:2]
    delim = _guess_delim(first)
    has_header = not any(_field_kind(f, delim) in ("num", "dc") for f in _split(first, delim))
    # Numbers with a decimal comma beside a ';' or tab delimiter (-8,4209): numbers to pandas
    # too, not labels.
    data_row = second if has_header else first
    decimal = ("," if delim != "," and any(_field_kind(f, delim) == "dc"
                                          for f in _split(data_row, delim)) else ".")
    # Comment lines left out here: pandas' comment= would also cut a '#' inside a field
    # (a label such as 'pose #3'). pandas reads the file through the filter, in pieces, so the
    # text is never held whole beside the table.
    try:
        with open(src.opened, encoding="utf-8-sig", errors="replace") as fh:
            df = pd.read_csv(_Uncommented(fh), sep=delim if delim else r"\s+",
                             header=0 if has_header else None, decimal=decimal,
                             skipinitialspace=True, low_memory=False)
    except OSError as e:
        raise CalibrationError(f"{name}: cannot read file ({e.strerror})") from None
    except (ValueError, pd.errors.ParserError) as e:
        raise CalibrationError(f"{name}: a long-format log (a text label in each row) that pandas "
                               f"cannot read: {e}") from None
    df.columns = [str(c).strip() for c in df.columns]
    text = [c for c in df.columns if not pd.api.types.is_numeric_dtype(df[c])
            and not pd.api.types.is_datetime64_any_dtype(df[c])]
    df, time_column, clock = _clock_columns(df, text, time_column, name, has_header)
    text = [c for c in text if c in df.columns and not pd.api.types.is_numeric_dtype(df[c])]
    out = _long_format_table(df, text, columns, fs, time_column, name, has_header)
    if clock is not None:
        c, t0_text, note = clock
        lay = out.lay
        if lay.time is not None and (
                str(lay.time) if lay.names is None else lay.names[lay.time]) == c:
            lay.t0_text = t0_text
            lay.notes.append(note)
    return out


def _long_format_table(df: Any, text: list[str], columns: Any, fs: float | None,
                       time_column: Any, name: str, has_header: bool) -> _ArraySource:
    """The source of a table read by :func:`_long_format_source` whose text columns are
    ``text``."""
    import pandas as pd

    for c in text:
        val = df[c].astype(str).str.strip()
        found = sorted({v for v in val.unique()[:1000] if v.lower() in _ACC_LABELS})
        if len(found) != 1:
            continue
        keep = (val == found[0]).to_numpy()
        sub = df.loc[keep].drop(columns=[c])
        for k in list(sub.columns):
            if k in text:
                num = pd.to_numeric(sub[k], errors="coerce")
                if num.notna().sum() >= 0.9 * max(sub[k].notna().sum(), 1):
                    sub[k] = num
                    continue
                when = pd.to_datetime(sub[k], format="ISO8601", errors="coerce")
                if when.notna().all() and when.size:
                    sub[k] = when  # ISO-8601 times: s since the first row
                else:
                    sub = sub.drop(columns=[k])
        counts = val.value_counts()
        others = ", ".join(f"{k} {v}" for k, v in counts.items() if k != found[0])
        out = _dataframe_source(sub.reset_index(drop=True), columns, fs, time_column, path=name,
                                named=has_header)
        out.lay.notes.append(
            f"a long-format log: the {int(keep.sum())} rows labelled {found[0]!r} in column "
            f"{c!r} are the accelerometer's (of {len(df)} rows; the others: {others or 'none'})")
        return out
    wide = _wide_with_text(df, text)
    if wide is not None:  # no label: a wide table after all
        sub, notes, labels = wide
        out = _dataframe_source(sub, columns, fs, time_column, path=name, named=has_header)
        out.lay.notes += notes
        out.labels = labels
        return out
    annotated = _annotated_session(df, text, columns, fs, time_column, name, has_header)
    if annotated is not None:
        return annotated
    seen = {}
    for c in text:
        u = sorted(df[c].astype(str).str.strip().unique().tolist())
        seen[c] = ", ".join(u[:8]) + (f" ... ({len(u)} labels)" if len(u) > 8 else "")
    said = "; ".join(f"{c!r}: {v}" for c, v in seen.items())
    raise CalibrationError(
        f"{name}: a long-format log (a text label in each row, {said}) with no label that "
        "names an accelerometer (ACC, accel, accelerometer, ...) and no sections to take as "
        "dwells; write the accelerometer's rows to a file of their own, or select them in "
        "Python: df = pandas.read_csv(path); accelcal.io.read_stream(df[df[label] == "
        "value].drop(columns=label))")


#: A time stamp other than ISO 8601: a time of day (``23:59:59.990``, ``11:59:00.010 PM``),
#: optionally after a date (``01.03.2024``, ``03/01/2024``, ``2024/03/01``).
_CLOCK = re.compile(
    r"^(?:(?P<d1>\d{1,4})(?P<sep>[./-])(?P<d2>\d{1,2})(?P=sep)(?P<d3>\d{1,4})(?:\s+|T))?"
    r"(?P<H>\d{1,2}):(?P<M>\d{2})(?::(?P<S>\d{2})(?:[.,](?P<F>\d+))?)?"
    r"\s*(?P<ap>[AaPp]\.?[Mm]\.?)?$")


def _looks_like_clock(v: str) -> bool:
    """A field that looks like a time stamp (a time of day among digits), understood or not."""
    digits = sum(ch.isdigit() for ch in v)
    return (re.search(r"\d{1,2}:\d{2}", v) is not None
            and 2 * digits >= len(v.replace(" ", "")) and len(v) <= 40)


def _clock_columns(df: Any, text: list[str], time_column: Any, name: str, has_header: bool
                   ) -> tuple[Any, Any, tuple[str, str, str] | None]:
    """Text columns of time stamps the text reader does not parse (times of day, dates
    day-first or month-first, AM/PM): with ``time_column="none"`` left out; else read as s
    since the first stamp (the table, the ``time_column`` that names it, and its name, first
    stamp and a note). A column of stamps in a format not understood is refused, naming it,
    unless another time column is given."""
    import pandas as pd

    names = [str(c) for c in df.columns] if has_header else None
    clock = None
    for c in text:
        vals = df[c].dropna().astype(str).str.strip()
        sample = vals.iloc[:200]
        if not sample.size or not all(_looks_like_clock(v) for v in sample):
            continue
        if bool(pd.to_datetime(df[c], format="ISO8601", errors="coerce").notna().all()):
            continue  # ISO 8601 (WitMotion's unpadded dates): read by _wide_with_text
        if _no_time(time_column, names):
            df = df.drop(columns=[c])
            continue
        named = time_column is None or (
            names is not None and _time_spec(time_column, names)[0] == c) or (
            not isinstance(time_column, str) and str(time_column) == c)
        if not named or clock is not None:
            continue  # another column is the time
        t, how = _clock_seconds(name, c, df[c])
        first = str(df[c].iloc[0]).strip()
        df = df.assign(**{c: t})
        clock = (c, first, f"column {c!r} holds {how}: read as the time, s since the first "
                 f"stamp ({first})")
        if time_column is None:
            time_column = f"{c} [s]"
    return df, time_column, clock


def _clock_seconds(path: str, c: str, col: Any) -> tuple[NDArray[np.float64], str]:
    """Time stamps (see :data:`_CLOCK`) as s since the first, and words for what they are."""
    import pandas as pd

    vals = col.astype(str).str.strip()
    advice = "; give time_column='none', fs=RATE to read the file without its time column"
    unread = f"{path}: column {c!r} holds time stamps in a format not understood"
    m = vals.str.extract(_CLOCK)
    bad = m["H"].isna() | col.isna().to_numpy()
    dated = m["d1"].notna()
    if not bad.any() and dated.any() and not dated.all():
        bad = ~dated
    def ints(x: Any) -> NDArray[np.int64]:
        return pd.to_numeric(x.fillna("0"), errors="coerce").fillna(0).to_numpy(np.int64)

    hour, minute, sec = ints(m["H"]), ints(m["M"]), ints(m["S"])
    frac_ns = ints(m["F"].fillna("").str.ljust(9, "0").str[:9])
    ap = m["ap"].fillna("").str.upper().str[:1].to_numpy(dtype=str)
    has_ap = ap != ""
    bad = np.asarray(bad) | (minute >= 60) | (sec >= 61) | (has_ap & ((hour < 1) | (hour > 12)))
    bad |= ~has_ap & (hour > 23)
    hour = np.where(has_ap, hour % 12 + np.where(ap == "P", 12, 0), hour)
    # Integer nanoseconds of the day: 0.01 s steps stay 0.01 s after the subtraction.
    tod_ns = ((hour * 60 + minute) * 60 + sec) * 1_000_000_000 + frac_ns
    tod = tod_ns * 1e-9
    how = "times of day"
    days: NDArray[np.int64] | None = None
    if dated.all() and not bad.any():
        d1, d2, d3 = (pd.to_numeric(m[k]).to_numpy(np.int64) for k in ("d1", "d2", "d3"))
        sep = str(m["sep"].iloc[0])
        year_first = bool((m["d1"].str.len() == 4).all())

        def day_count(year: Any, month: Any, day: Any) -> tuple[NDArray[np.int64], Any]:
            year = np.where(year < 100, year + 2000, year)
            when = pd.to_datetime(pd.DataFrame({"year": year, "month": month, "day": day}),
                                  errors="coerce")
            ok = when.notna().to_numpy()
            d = ((when - when.iloc[0]) // pd.Timedelta(days=1)).fillna(0).to_numpy(np.int64)
            return d, ok

        if year_first:
            days, ok = day_count(d1, d2, d3)
            how = "dates (year first) and times"
        else:
            # Day-first unless a second number above 12 says otherwise; month-first unless a
            # first number above 12 or the '.' between them (01.03.2024: 1 March) says so.
            readings = {}
            if not (d2 > 12).any():
                readings["day-first"] = day_count(d3, d2, d1)
            if not (d1 > 12).any() and sep != ".":
                readings["month-first"] = day_count(d3, d1, d2)
            readings = {k: v for k, v in readings.items() if v[1].all()}
            if not readings:
                raise CalibrationError(
                    f"{unread} ({vals.iloc[0]!r} ...: dates that read neither day-first nor "
                    f"month-first){advice}")
            why = ""
            if len(readings) == 2:
                # Both orders read (no day above 12, no '.' between the numbers): the same
                # dates either way, or the one order whose clock runs on without a jump.
                if np.array_equal(readings["day-first"][0], readings["month-first"][0]):
                    readings.pop("day-first")
                else:
                    steps = {k: float(np.max(np.abs(np.diff(v[0] * 86400.0 + tod))))
                             for k, v in readings.items()}
                    worse = max(steps, key=steps.__getitem__)
                    better = min(steps, key=steps.__getitem__)
                    if steps[worse] < 100.0 * max(steps[better], 1.0):
                        raise CalibrationError(
                            f"{unread} ({vals.iloc[0]!r} ...: the dates read both day-first "
                            "and month-first, and no day above 12 tells which)" + advice)
                    readings.pop(worse)
                    why = (f"; no day above 12, but read {worse} the clock would jump "
                           f"{steps[worse] / 86400.0:.0f} days")
            order, (days, ok) = next(iter(readings.items()))
            how = f"dates ({order}{why}) and times"
        bad = bad | ~ok
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise CalibrationError(f"{unread} ({vals.iloc[i]!r}, data row {i + 1}){advice}")
    if days is None:
        # Times of day only: a day added where the clock goes back past midnight.
        back = np.r_[False, np.diff(tod) < -43200.0]
        days = np.cumsum(back).astype(np.int64)
        if back.any():
            how += f", past midnight {int(back.sum())} time(s) (a day added at each)"
    t_ns = days * 86_400_000_000_000 + tod_ns
    return (t_ns - t_ns[0]).astype(np.float64) / 1e9, how


#: Names of a column that counts samples, by which an annotated session's rows are ordered.
_SAMPLE_INDEX = {"sample", "samples", "nsamples", "sampleindex", "index", "idx", "n", "counter",
                 "count"}


def _annotated_session(df: Any, text: list[str], columns: Any, fs: float | None,
                       time_column: Any, name: str, has_header: bool) -> _ArraySource | None:
    """A session whose rows carry the section they belong to (imucal's annotated Ferraris
    session: ``part,samples,acc_x,...`` with parts ``x_p``, ``x_a``, ``x_rot`` ...; a
    ``static``/``moving`` flag): the samples, in the order of a sample-index or time column
    when there is one, with the runs of each static label as known dwells named by it
    (labels of motions, ``x_rot`` ..., left out). None when no text column reads so: one
    label column, at most 64 labels, none naming a sensor, at least two static runs of 8 rows
    or more."""
    import pandas as pd

    if len(text) != 1:
        return None
    c = text[0]
    val = df[c].astype(str).str.strip()
    uniq = val.unique()
    if len(uniq) > 64 or any(_names_a_sensor(str(u)) for u in uniq):
        return None
    sub = df.drop(columns=[c])
    order_by = next((k for k in sub.columns if _norm(str(k)) in _SAMPLE_INDEX
                     or _time_name(str(k)) is not None), None)
    if order_by is not None and pd.api.types.is_numeric_dtype(sub[order_by]):
        idx = np.argsort(sub[order_by].to_numpy(), kind="stable")
        sub, val = sub.iloc[idx].reset_index(drop=True), val.iloc[idx].reset_index(drop=True)
    lab = val.to_numpy()
    cut = np.flatnonzero(lab[1:] != lab[:-1]) + 1
    starts, stops = np.r_[0, cut], np.r_[cut, len(lab)]
    runs = [(str(lab[a]), int(a), int(b)) for a, b in zip(starts, stops, strict=True)]
    moving = sorted({r for r, _, _ in runs if _MOVING.search(r.lower())})
    static = [(r, a, b) for r, a, b in runs if r not in moving and b - a >= 8]
    if len(static) < 2 or len(runs) > 5000:
        return None
    out = _dataframe_source(sub, columns, fs, time_column, path=name, named=has_header,
                            dwells_known=True)
    short = len([1 for r, a, b in runs if r not in moving]) - len(static)
    how = f", ordered by {order_by!r}" if order_by is not None else ""
    note = (f"column {c!r} labels the session's sections{how}: its {len(static)} static "
            f"runs are the dwells ({', '.join(r for r, _, _ in static[:8])}"
            f"{' ...' if len(static) > 8 else ''})")
    if moving:
        note += f"; left out as motions: {', '.join(moving)}"
    if short:
        note += f"; {short} run(s) under 8 rows left out"
    out.lay.notes.append(note)
    out.sections = Bounds(np.array([[a, b] for _, a, b in static], dtype=np.float64),
                          names=[r for r, _, _ in static], path=name)
    return out


#: Words of a label that names a sensor (a long-format log's rows), not a pose.
_SENSOR_WORDS = {
    "acc", "accel", "acceleration", "accelerometer", "gyr", "gyro", "gyroscope", "mag",
    "magnetometer", "baro", "barometer", "pressure", "temp", "temperature", "gps", "imu",
    "quat", "quaternion", "orientation", "rotation", "gravity", "linacc", "light", "proximity",
}


def _label_words(label: str) -> set[str]:
    """The words of a row label, lower case (``imu_data_posZ`` -> imu, data, posz)."""
    return set(re.split(r"[^a-z]+", label.lower()))


def _names_a_sensor(label: str, shared: set[str] | frozenset[str] = frozenset()) -> bool:
    """A row label with a word of :data:`_SENSOR_WORDS` (``ACC``, ``gyro_z``), other than the
    ``shared`` words every label of its column has: it names the sensor of its row, not a pose
    or a section."""
    return bool(_SENSOR_WORDS.intersection(_label_words(label) - shared))


def _wide_with_text(df: Any, text: list[str]) -> tuple[Any, list[str], list[str] | None] | None:
    """A table whose text columns are all date-times (WitMotion's ``2023-10-9 16:14:27.564``,
    which the text reader's ISO-8601 parser does not take: its fields are not zero-padded),
    one value repeated in every row (a device name), or one column of row labels beside
    columns named as an accelerometer's (a lab's table of pose means: ``position, ax, ay,
    az`` with ``+X up`` ...). Returns the table with the times read as such and the
    constants and labels left out, notes saying so, and the labels (None without); None
    when a text column is none of these."""
    import pandas as pd

    notes: list[str] = []
    labels: list[str] | None = None
    for c in text:
        when = pd.to_datetime(df[c], format="ISO8601", errors="coerce")
        if when.size and bool(when.notna().all()):
            df = df.assign(**{c: when})
            continue
        vals = df[c].astype(str).str.strip()
        uniq = vals.unique()
        if len(uniq) != 1:
            # Row labels, not a sensor per row: a small table, labels mostly distinct, none
            # naming a sensor, and columns named as an accelerometer's beside them.
            # (A word every label shares, "imu" of imu_data_posZ ..., names no row's sensor.)
            shared = set.intersection(*(_label_words(str(v)) for v in uniq))
            if (labels is not None or len(vals) > POSE_TABLE_ROWS or 2 * len(uniq) < len(vals)
                    or any(_names_a_sensor(str(v), shared) for v in uniq)):
                return None
            rest = [str(k) for k in df.columns if k not in text]
            try:
                acc = _auto_acc(rest, "")
            except CalibrationError:
                acc = None
            if acc is None:
                return None
            labels = vals.tolist()
            df = df.drop(columns=[c])
            notes.append(f"column {c!r} holds a text label per row ({', '.join(labels[:3])}"
                         f"{' ...' if len(labels) > 3 else ''}): kept as the rows' names, not "
                         "read as data")
            continue
        df = df.drop(columns=[c])
        notes.append(f"column {c!r} holds {vals.iloc[0]!r} in every row (a device name?): "
                     "left out")
    return df, notes, labels


def _long_format_hint(line: str) -> str:
    """For a line of numbers with one or two text fields (``0.01,ACC,0.1,0.2,9.8``): the
    advice for a log that names each row's sensor in a column, else ``""``."""
    d = _guess_delim(line)
    fields = _split(line, d)
    text = [f for f in fields if f and _field_kind(f, d) is None]
    if 1 <= len(text) <= 2 and len(fields) - len(text) >= 3:
        return (f"; {text[0]!r} looks like a label: a log that names each row's sensor in a "
                "column? Keep the accelerometer rows and drop the label first, e.g. with "
                "pandas: df = pd.read_csv(path); read_stream(df[df[label] == value].drop("
                "columns=label))")
    return ""


def _split_datetime_hint(s: str) -> str | None:
    """A message when a line looks like data whose date and time were split by a space."""
    f = s.split()
    if len(f) >= 3 and re.match(r"^\d{4}-\d{2}-\d{2}$", f[0]) and re.match(r"^\d{2}:\d{2}", f[1]):
        if all(_is_number(x) for x in f[2:]):
            return (
                "the data rows start with a date and a time separated by a space in a "
                "space-separated file, which makes them two fields; join them with 'T' "
                "(2024-03-01T12:00:00) or use a comma, semicolon or tab delimiter"
            )
    return None


def _meta_pair(line: str) -> tuple[str, str] | None:
    s = line.strip().lstrip("#%").strip()
    if not s:
        return None
    # "=" and ":" first; of the delimiters, the first one in the line (``Abtastrate [Hz];100,0``
    # is a key and a decimal-comma value, not "Abtastrate [Hz];100" and "0").
    delims = sorted((s.index(d), d) for d in (",", ";", "\t") if d in s)
    for sep in ("=", ":", *(d for _, d in delims)):
        if sep in s:
            k, v = s.split(sep, 1)
            k, v = k.strip(), v.strip().rstrip(",;").strip()
            several = any(x in v for x in ",;\t") and not (
                sep != "," and re.fullmatch(r"[+-]?\d+,\d+(?:\s*\S+)?", v))
            if k and not _is_number(k) and sep in ",;\t" and several:
                return None  # a row of several fields, not key,value
            if k and not _is_number(k):
                return k, v
            return None
    return None


#: Metadata keys (as `_fs_from_meta` normalises them) that give the sample interval, whose
#: inverse is the rate.
_PERIOD_KEYS = {
    "period", "sampleperiod", "samplingperiod", "interval", "sampleinterval",
    "samplinginterval", "samplingtime", "dt", "timestep", "logginginterval", "loginterval",
    "measurementinterval", "recordinterval",
}
#: Rate units a metadata value or key may carry, as the factor to Hz.
_RATE_UNITS = {"hz": 1.0, "khz": 1e3, "mhz": 1e6, "sps": 1.0, "ksps": 1e3, "s/s": 1.0,
               "samples/s": 1.0, "/s": 1.0, "1/s": 1.0, "s-1": 1.0}


def _fs_from_meta(meta: dict[str, str], path: str = "",
                  lines: dict[str, tuple[int, str]] | None = None
                  ) -> tuple[float, str] | None:
    """The sample rate a metadata line states, in Hz, and where it comes from (``"the
    metadata line 2 ('# Sample rate: 1 kHz')"``), or None. The unit is read from the value
    (``1 kHz``) or the key (``Sample rate [Hz]``), Hz when neither says; a key naming an
    interval or period (``Sampling interval (s),0.01``, ``period = 10 ms``) gives 1/value,
    in s unless a unit says otherwise. A unit not understood is refused."""
    for k, v in meta.items():
        base, kunit = _split_unit(k)
        key = re.sub(r"[^0-9a-z]", "", base.lower())
        full = re.sub(r"[^0-9a-z]", "", k.lower())
        if key.endswith("hz") and key[:-2] in _FS_KEYS:
            key, kunit = key[:-2], kunit or "Hz"
        period = key in _PERIOD_KEYS
        if not period and key not in _FS_KEYS and full not in _FS_KEYS:
            continue
        val = v.strip()
        if re.fullmatch(r"[+-]?\d+,\d+(?:\s*\S+)?", val):  # a decimal comma
            val = val.replace(",", ".", 1)
        m = re.match(r"^([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)\s*(.*)$", val)
        if m is None:
            continue
        f = float(m.group(1))
        rest = m.group(2).strip()
        line = (lines or {}).get(k)
        where = (f"the metadata line {line[0]} ({line[1]!r})" if line is not None
                 else f"the metadata {k!r} = {v!r}")
        um = re.match(r"^([A-Za-zµ/0-9-]+)", rest)
        unit = um.group(1) if um is not None and re.match(r"[A-Za-zµ/]", rest) else ""
        if not period and rest.lower().startswith(("samples per second", "samples/sec",
                                                   "per second", "samples per s")):
            unit = "Hz"
        if not unit:
            unit = kunit
        u = unit.strip().lower()
        if period:
            scale = _TIME_UNITS.get(u)
            if scale is None:
                raise CalibrationError(
                    f"{path}: {where}: the interval's unit {unit!r} is not understood (s, ms, "
                    "us or ns); give the rate with fs= (Hz)")
            f = 1.0 / (f * scale) if f > 0 else f
        else:
            scale = _RATE_UNITS.get(u.replace(" ", ""), 1.0 if u == "" else None)
            if scale is None:
                raise CalibrationError(
                    f"{path}: {where}: the rate's unit {unit!r} is not understood (Hz, kHz or "
                    "MHz); give the rate with fs= (Hz)")
            f *= scale
        if np.isfinite(f) and f > 0:
            return f, where
    return None


@dataclass
class _Layout:
    path: str
    ncols: int
    names: tuple[str, ...] | None  # header names, None without header
    acc: list[int]
    time: int | None
    time_scale: float
    temp: int | None
    metadata: dict[str, str]
    fs: float | None
    fs_source: str | None = None
    notes: list[str] = field(default_factory=list)
    head: NDArray[np.float64] = field(repr=False, default_factory=lambda: np.empty((0, 0)))
    # text only
    delim: str | None = None
    offset: int = 0  # byte offset of the first data row
    first_line: int = 1  # its line number
    decimal_comma: bool = False
    iso: set[int] = field(default_factory=set)  # columns holding ISO-8601 times
    t0: tuple[int, int] | None = None
    t0_text: str | None = None
    bytes_per_row: float = 40.0
    signed16: bool = False  # the accelerometer's int16 values are stored as uint16

@dataclass
class _TextSource:
    path: str  # "-" for standard input
    head: bytes
    eof: bool  # head holds everything
    size: int | None  # bytes, None for a pipe
    file: str | None = None  # the file the reader opens, when not `path` (decompressed text)

    @property
    def opened(self) -> str:
        return self.file or self.path

    @property
    def stdin(self) -> bool:
        return self.path == "-"


def _open_bytes(path: str) -> Any:
    try:
        return open(path, "rb")
    except FileNotFoundError:
        raise CalibrationError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise CalibrationError(f"{path}: is a directory, not a recording file") from None
    except OSError as e:
        raise CalibrationError(f"{path}: cannot read file ({e.strerror})") from None


#: Magic bytes of the compressed text files that are read (through a temporary file).
_COMPRESSED = ((b"\x1f\x8b", "gzip"), (b"BZh", "bz2"), (b"\xfd7zXZ\x00", "xz"))
#: The file-name suffixes of those formats (written by ``apply -o out.csv.gz``).
COMPRESSED_SUFFIXES = {".gz": "gzip", ".bz2": "bz2", ".xz": "xz"}


def compression_open(kind: str) -> Any:
    """The ``open`` of a compression format of :data:`_COMPRESSED` ("gzip", "bz2", "xz")."""
    import bz2
    import gzip
    import lzma

    return {"gzip": gzip.open, "bz2": bz2.open, "xz": lzma.open}[kind]


def file_stem(path: str | os.PathLike[str]) -> str:
    """A file's name without its suffix, and without a compression suffix first
    (``b.csv.gz`` -> ``b``, not ``b.csv``)."""
    p = Path(path)
    if p.suffix.lower() in COMPRESSED_SUFFIXES:
        p = Path(p.stem)
    return p.stem


def _compression(head: bytes) -> str | None:
    """"gzip", "bz2" or "xz" when the first bytes of a file are that format's, else None."""
    return next((kind for m, kind in _COMPRESSED if head.startswith(m)), None)


def _is_mseed(head: bytes) -> bool:
    """The first bytes of a file are a miniSEED record header (v2: six digits of sequence
    number and a quality code D, R, Q or M; v3: ``MS3``): read as such whatever its name."""
    return head.startswith(b"MS3") or (
        len(head) >= 8 and head[:6].isdigit() and head[6:7] in b"DRQM" and head[7:8] in b" \0")


#: Errors of writing a file that say its folder (or the user's share of it) has no room left.
_NO_ROOM = {getattr(errno, n) for n in ("ENOSPC", "EDQUOT", "EFBIG") if hasattr(errno, n)}


def _decompressed(path: str, kind: str) -> tuple[str, Callable[[], None]]:
    """Decompress ``path`` (gzip, bz2 or xz) into a temporary file: the parser reads files in
    place (memory-mapped), so a compressed file is expanded first. Returns the path to read
    and the function that releases the file. Where the system allows, the file has no name
    from the start (unlinked, held open, read through ``/proc/self/fd/N``), so nothing is left
    behind when the process is killed: a batch scheduler's SIGTERM or the out-of-memory killer
    left a 393 MB expansion of a .gz recording in the temporary folder."""
    import lzma
    import shutil
    import tempfile

    opener = compression_open(kind)
    fd, tmp = tempfile.mkstemp(prefix="accelcal-", suffix=".txt")
    fd_dir = "/proc/self/fd"
    anonymous = os.path.isdir(fd_dir)
    if anonymous:
        os.unlink(tmp)
        read_as, release = f"{fd_dir}/{fd}", (lambda: _close_quiet(fd))
    else:
        read_as, release = tmp, (lambda: _unlink_quiet(tmp))
    try:
        with opener(path, "rb") as src, os.fdopen(fd, "wb", closefd=not anonymous) as dst:
            shutil.copyfileobj(src, dst, 1 << 20)
    except OSError as e:
        release()
        if e.errno in _NO_ROOM:  # the expansion's side, not the input's
            folder = os.path.dirname(tmp) or "."
            raise CalibrationError(
                f"{path}: cannot expand it ({kind}): the temporary folder {folder!r} is full "
                f"({os.strerror(e.errno or 0)}); free room there or point TMPDIR at a folder "
                "with room for the expanded text") from None
        raise CalibrationError(f"{path}: cannot decompress it ({kind}): {e}") from None
    except (EOFError, lzma.LZMAError) as e:
        release()
        raise CalibrationError(f"{path}: cannot decompress it ({kind}): {e}") from None
    except BaseException:
        release()
        raise
    return read_as, release


def _unlink_quiet(path: str) -> None:
    with contextlib.suppress(OSError):
        os.unlink(path)


def _close_quiet(fd: int) -> None:
    with contextlib.suppress(OSError):
        os.close(fd)


def _read_head(path: str) -> _TextSource:
    if path == "-":
        try:
            real = sys.stdin.fileno() == 0
        except (AttributeError, ValueError, OSError):
            real = False
        if not real:  # a replaced sys.stdin (an embedding program, a test runner)
            data = sys.stdin.buffer.read() if hasattr(sys.stdin, "buffer") else b""
            return _TextSource(path, data, True, None)
        parts: list[bytes] = []
        n = 0
        eof = False
        while n < _HEAD_BYTES:
            # os.read, not sys.stdin: nothing may sit in Python's buffer that the Rust reader,
            # which continues from file descriptor 0, would miss.
            b = os.read(0, _HEAD_BYTES - n)
            if not b:
                eof = True
                break
            parts.append(b)
            n += len(b)
        return _TextSource(path, b"".join(parts), eof, None)
    with _open_bytes(path) as fh:
        try:
            head = fh.read(_HEAD_BYTES)
            size = os.fstat(fh.fileno()).st_size
        except OSError as e:
            raise CalibrationError(f"{path}: cannot read file ({e.strerror})") from None
    return _TextSource(path, head, len(head) < _HEAD_BYTES or len(head) >= size, size)


def _head_lines(src: _TextSource) -> Iterator[tuple[int, str]]:
    """(byte offset, text) of each complete line of the head (a partial last line dropped)."""
    data = src.head
    if b"\x00" in data[:65536]:
        if data[:2] in (b"\xff\xfe", b"\xfe\xff"):
            raise CalibrationError(
                f"{src.path}: the text is UTF-16 (as Windows' 'Unicode text' saves it); save "
                "it as UTF-8 or plain ASCII (e.g. iconv -f UTF-16 -t UTF-8)"
            )
        comp = _compression(data)
        if comp is not None:  # only standard input gets here: files are expanded first
            raise CalibrationError(f"{src.path}: {comp}-compressed text on standard input: "
                                   "give the file's name instead, or decompress it first")
        raise CalibrationError(f"{src.path}: not a text file (it contains NUL bytes)")
    start = 3 if data.startswith(b"\xef\xbb\xbf") else 0
    pos = start
    while pos < len(data):
        nl = data.find(b"\n", pos)
        if nl < 0:
            if not src.eof:
                break
            nl = len(data)
        raw = data[pos:nl]
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            text = raw.decode("latin-1")  # a header in a legacy encoding; data rows are ASCII
        yield pos, text.rstrip("\r")
        pos = nl + 1


def _sniff(src: _TextSource, columns: Any, fs: float | None, time_column: Any) -> _Layout:
    path = src.path
    lines: list[tuple[int, str]] = []  # the lines up to the first data row
    meta: dict[str, str] = {}
    meta_lines: dict[str, tuple[int, str]] = {}  # the line of each metadata key, and its text
    header: str | None = None
    header_units: list[str] | None = None
    first: int | None = None
    fmt: _RowFormat | None = None
    for i, (pos, line) in enumerate(_head_lines(src)):
        lines.append((pos, line))
        s = line.strip()
        if not s:
            continue
        # Tabs are kept at the ends: a trailing tab is an (empty) field to the parser too.
        kept = line.strip(" \r\n")
        if not s.startswith(("#", "%", "//")):
            fmt = _data_row(kept if "\t" in kept else s)
            if fmt is not None:
                first = i
                break
            if _label_pairs(s) is not None:
                raise _LabelPairs(f"{path}: line {i + 1} is a row of label-value pairs")
            hint = _split_datetime_hint(s)
            if hint:
                raise CalibrationError(f"{path}: line {i + 1}: {hint}")
        if i >= _MAX_PREAMBLE:
            raise CalibrationError(
                f"{path}: no numeric data row in the first {_MAX_PREAMBLE} lines (line "
                f"{i + 1} is {s[:60]!r}); numbers, decimal-comma numbers and ISO-8601 times "
                "are read"
            )
        body = s.lstrip("#%/").strip()
        if "\t" in kept and not kept.startswith(("#", "%", "//")):
            body = kept
        bf = _split(body, _guess_delim(body))
        if len(bf) >= 3 and not any(_is_number(f) for f in bf if f) and "=" not in body:
            units = _units_row(bf)
            under = header is not None and len(_split(header, _guess_delim(header))) == len(bf)
            if under and units is not None and header_units is None:
                header_units = units  # a units row under the names
                continue
            if under and _kind_row(bf):
                continue  # CAL / RAW under the names: not the names themselves
            header, header_units = body, None
            continue
        header, header_units = None, None
        kv = _meta_pair(s)
        if kv:
            meta[kv[0]] = kv[1]
            meta_lines[kv[0]] = (i + 1, s)
    if first is None or fmt is None:
        if not src.head.strip(b"\xef\xbb\xbf"):
            raise CalibrationError(f"{path}: file is empty")
        if not src.eof and b"\n" not in src.head:  # not one whole line in the first block
            n = len(src.head)
            if b"\r" in src.head:
                raise CalibrationError(
                    f"{path}: no line end (\\n) in the first {n} bytes, only carriage "
                    "returns: lines end in a carriage return alone (classic Mac text); "
                    "convert them to \\n (e.g. tr '\\r' '\\n')")
            raise CalibrationError(
                f"{path}: no line end found in the first {n} bytes: the first line is longer "
                f"than {n} bytes (one line of samples, or not a text table?)")
        if all(not ln.strip() for _, ln in lines):
            raise CalibrationError(f"{path}: no numeric data rows (only blank lines)")
        last = next(ln.strip() for _, ln in reversed(lines) if ln.strip())
        if not src.eof and len(lines) <= _MAX_PREAMBLE:
            hint = _long_format_hint(last)
            raise (_LongFormat if hint else CalibrationError)(
                f"{path}: no numeric data row in the first {len(src.head)} bytes" + hint
            )
        if "\r" in last:
            raise CalibrationError(
                f"{path}: lines end in a carriage return alone (classic Mac text); convert "
                "them to \\n (e.g. tr '\\r' '\\n')"
            )
        hint = _long_format_hint(last)
        raise (_LongFormat if hint else CalibrationError)(
            f"{path}: no numeric data rows found (the last line is {last[:60]!r}); numbers, "
            "decimal-comma numbers and ISO-8601 times are read" + hint
        )
    stray = _stray_first_rows(src, first, fmt)
    if stray is not None:
        first, fmt, note = stray
        lines = list(itertools.islice(_head_lines(src), first + 1))
    delim, ncols = fmt.delim, len(fmt.fields)
    offset, first_line = lines[first][0], first + 1
    decimal_comma = delim != "," and b"," in src.head[offset:]
    iso = {j for j, k in enumerate(fmt.kinds) if k == "iso"}
    t0 = t0_text = None
    if iso:
        j = min(iso)
        t0_text = fmt.fields[j]
        t0 = _core.parse_iso8601(t0_text)
    names: tuple[str, ...] | None = None
    pre_notes: list[str] = [] if stray is None else [note]
    if header is not None:
        hf = _split(header, delim)
        if header_units is not None and len(header_units) == len(hf):
            hf = [f"{h} [{u}]" if u and not _split_unit(h)[1] else h
                  for h, u in zip(hf, header_units, strict=True)]
        if len(hf) == ncols:
            names = tuple(h.strip().strip("\"'") for h in hf)
        elif delim is not None and delim not in header:
            # Text without the data's delimiter: a logger's preamble (a serial capture's
            # banner and prompts), not the column names.
            preamble = sum(1 for _, ln in lines[:first] if ln.strip())
            pre_notes.append(f"the {preamble} line(s) before the first data row are text without "
                         f"its delimiter ({header[:40]!r} ...): a preamble, skipped; no column "
                         "names")
        else:
            raise CalibrationError(
                f"{path}: header has {len(hf)} names but data rows have {ncols} columns"
            )
    # Parse the head rows with the reader itself: the layout decisions see exactly what the
    # full read will see. Every column, empty fields reading NaN (the first data row of a
    # merged log may belong to another sensor); if a column empty in the first row holds
    # text further down, only those that hold a value in the first row.
    head_bytes = src.head[offset:]
    if not src.eof:
        head_bytes = head_bytes[: head_bytes.rfind(b"\n") + 1]

    def parse_head(cols: list[int]) -> tuple[Any, int, int]:
        arrays, rows, nbytes, _ = _located(
            path,
            None,
            _core.text_parse_head,
            head_bytes,
            ncols,
            [[(j, 1.0, j in iso) for j in cols]],
            delimiter=delim,
            decimal_comma=decimal_comma,
            names=list(names) if names is not None else None,
            first_line=first_line,
            t0=t0,
            max_rows=_SNIFF_ROWS,
            # Only to decide the layout: an empty field is an error of the full read.
            sparse_groups=[0],
        )
        return arrays, rows, nbytes

    cols = _numeric_columns(head_bytes, delim, ncols)
    try:
        arrays, rows, nbytes = parse_head(cols)
    except CalibrationError:
        cols = [j for j, k in enumerate(fmt.kinds) if k != "empty"]
        if len(cols) == ncols:
            raise
        arrays, rows, nbytes = parse_head(cols)
    head = np.full((rows, ncols), np.nan)
    if cols:
        head[:, cols] = arrays[0].reshape(rows, len(cols))
    lay = _decide(path, names, ncols, head, meta, columns, fs, time_column, iso,
                  meta_lines=meta_lines)
    lay.notes[:0] = pre_notes
    lay.delim, lay.offset, lay.first_line = delim, offset, first_line
    lay.decimal_comma, lay.iso, lay.t0, lay.t0_text = decimal_comma, iso, t0, t0_text
    if rows:
        lay.bytes_per_row = max(nbytes / rows, 1.0)
    if lay.time is not None and lay.time in iso:
        lay.time_scale = 1.0
    elif iso and lay.time is None:
        lay.t0 = lay.t0_text = None
    for j in (lay.acc + ([lay.temp] if lay.temp is not None else [])):
        if j in iso:
            raise CalibrationError(
                f"{path}: column {_label(lay, j)} holds dates and times, not numbers"
            )
    return lay


#: Data lines after the first that decide whether it is a stray row (:func:`_stray_first_rows`).
_STRAY_LOOKAHEAD = 40


def _stray_first_rows(src: _TextSource, first: int, fmt: _RowFormat
                      ) -> tuple[int, _RowFormat, str] | None:
    """When the head's first data lines split into fewer or more fields than the rows after
    them (a serial capture that starts mid-line: ``04`` before rows of 4 fields), the line of
    the first row like the others, its format and the note that says what was skipped; None
    when the first data line is like the rest."""
    rows: list[tuple[int, str, _RowFormat]] = []
    for i, (_, line) in enumerate(_head_lines(src)):
        if i < first:
            continue
        s = line.strip()
        if not s or s.startswith(("#", "%", "//")):
            continue
        f = _data_row(line.strip(" \r\n") if "\t" in line else s)
        if f is None:
            continue
        rows.append((i, s, f))
        if len(rows) > _STRAY_LOOKAHEAD:
            break
    shapes = collections.Counter((f.delim, len(f.fields)) for _, _, f in rows[1:])
    if len(rows) < 5 or not shapes:
        return None
    (delim, n), votes = shapes.most_common(1)[0]
    if (fmt.delim, len(fmt.fields)) == (delim, n) or votes < 0.75 * (len(rows) - 1):
        return None
    k = next(j for j, (_, _, f) in enumerate(rows) if (f.delim, len(f.fields)) == (delim, n))
    i0, s0, f0 = rows[0]
    words = "field" if len(f0.fields) == 1 else "fields"
    note = (f"the first {k} data line(s) (line {i0 + 1}: {s0[:30]!r}, {len(f0.fields)} "
            f"{words}) split unlike the rows after them ({n} fields): a logger's leftovers, "
            "skipped")
    return rows[k][0], rows[k][2], note


def _label_of(names: tuple[str, ...] | None, j: int) -> str:
    return repr(names[j]) if names is not None else f"{j} (0-based)"


def _columns_text(names: tuple[str, ...] | None, cols: Sequence[int]) -> str:
    """``'ax', 'ay', 'az'``, or ``1, 2, 3 (0-based)`` without names."""
    if names is not None:
        return ", ".join(repr(names[i]) for i in cols)
    return f"{', '.join(map(str, cols))} (0-based)"


def _label(lay: _Layout, j: int) -> str:
    return _label_of(lay.names, j)


#: How the reader's note on a missing sample rate begins (readers of a table of pose means,
#: and the fleet, which words its own, leave it out).
NO_RATE_NOTE = "the sample rate is not in the file"


def _no_time(time_column: Any, names: Sequence[str] | None) -> bool:
    """``time_column=False`` or ``"none"`` (unless a column is named so): no time column."""
    if time_column is False:
        return True
    return (isinstance(time_column, str) and time_column.strip().lower() == "none"
            and (names is None or time_column not in names))


def _not_a_clock(t: NDArray[Any]) -> str | None:
    """Why the head of a time column cannot be a clock (``"holds 0 in every one of the
    first 500 rows"``: a GPS clock never set), or None when it moves."""
    x = np.asarray(t, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.shape[0] < 2:
        return None
    if np.all(x == x[0]):
        return f"holds {x[0]:.6g} in every one of the first {x.shape[0]} rows"
    return None  # it moves: a clock, perhaps wrapping or reset (read as such later)


def _is_counter(x: NDArray[Any]) -> bool:
    """0, 1, 2, ... (or any start, step 1): a sample counter, not a time in s."""
    return bool(x.shape[0] >= 2 and np.all(np.diff(x) == 1.0) and np.all(x == np.round(x)))


def _decide(
    path: str,
    names: tuple[str, ...] | None,
    ncols: int,
    head: NDArray[Any],
    meta: dict[str, str],
    columns: Any,
    fs: float | None,
    time_column: Any,
    iso: set[int] | None = None,
    dwells_known: bool = False,
    meta_lines: dict[str, tuple[int, str]] | None = None,
) -> _Layout:
    """Choose accelerometer, time and temperature columns and the sample rate.

    ``iso`` : columns that hold ISO-8601 times (text files); the first of them not among the
    accelerometer columns is the time when no column is named as one.
    ``dwells_known`` : the file marks its dwells itself (an annotated session), so a missing
    rate only costs the dwells' times, not their detection.
    ``meta_lines`` : the line of each metadata key and its text (text files), for messages.
    """
    notes: list[str] = []
    tcol: int | None = None
    tscale = 1.0
    stated = False  # the time unit is stated (by the column's name or with time_column=)
    no_time = _no_time(time_column, names)
    if no_time:
        pass  # the file's time column, if any, is not used (time_column="none")
    elif time_column is not None:
        spec, unit_scale = _time_spec(time_column, names)
        tcol = _resolve_one(spec, names, ncols, path, "time_column")
        found = None if names is None else _time_name(names[tcol])
        if unit_scale is not None:
            tscale, stated = unit_scale, True
        elif found is not None:
            tscale, stated = found
    elif names is not None:
        for i, n in enumerate(names):
            found = _time_name(n)
            if found is not None:
                tcol, (tscale, stated) = i, found
                break
        why = None if tcol is None else _not_a_clock(head[:, tcol])
        if why is not None and tcol is not None:
            # A column named as a time that does not count time (a GPS clock never set, all
            # zeros): not the time; the rate must then come from fs= or the metadata.
            notes.append(f"column {names[tcol]!r} is named as a time but {why}: not used as "
                         "the time")
            tcol = None
    temp_spec = None
    if columns is not None:
        acc_spec, temp_spec = _split_columns(columns)
        acc = _resolve_columns(acc_spec, names, ncols, path)
    elif names is not None:
        by_name = _auto_acc(names, path)
        if by_name is None:
            # No name says accelerometer (``tx ty tz``, ``ch1 ch2 ch3``): the only three
            # adjacent columns whose norm stays at 1 g, as in a headerless file.
            quat = {i for i, n in enumerate(names) if _QUATERNION.match(_norm(n))}
            triads = [t for t in _triads_by_norm(head, tcol) if not quat.intersection(t[0])]
            if len(triads) != 1:
                raise CalibrationError(
                    f"{path}: no accelerometer columns recognised among {list(names)}"
                    f"{_triads_text(triads, names)}; give columns=[...] (3 names or 0-based "
                    "indices)"
                )
            (by_name, level, unit), = triads
            notes.append(
                f"columns {', '.join(repr(names[i]) for i in by_name)} taken as the "
                f"accelerometer x, y, z: no name says so, but they are the only three adjacent "
                f"columns whose norm stays near 1 g (median norm {level:.4g} in the file's "
                f"units: about 1 g if they are {unit}) over the first {head.shape[0]} rows; "
                "give columns= to choose others")
        acc = by_name
    else:
        rest = [i for i in range(ncols) if i != tcol]
        if len(rest) == 3:
            acc = rest
        elif ncols == 4 and tcol is None and _increasing(head[:, 0]):
            acc = [1, 2, 3]
            if _is_counter(head[:, 0]):  # a row index (tomascufaro's 0, 1, 2 ...), no clock
                notes.append("column 0 (0-based) counts samples (0, 1, 2, ...): not used as "
                             "time")
            else:
                tcol = 0
        else:
            triads = _triads_by_norm(head, tcol)
            if len(triads) == 1:
                (acc, level, unit), = triads
                notes.append(
                    f"no header: columns {', '.join(map(str, acc))} (0-based) taken as the "
                    f"accelerometer x, y, z: the only three adjacent columns whose norm stays "
                    f"near 1 g (median norm {level:.4g} in the file's units: about 1 g if "
                    f"they are {unit}) over the first {head.shape[0]} rows; give columns= to "
                    "choose others")
            else:
                used = int(np.sum(np.any(np.isfinite(head), axis=0))) if head.size else ncols
                transposed = (
                    f"; it holds {head.shape[0]} rows of {ncols} values: it looks like a "
                    f"({head.shape[0]}, N) array of x, y, z (and time) rows, which must be "
                    f"transposed: save a.T, an (N, {head.shape[0]}) array"
                    if head.shape[0] in (3, 4) and ncols > 16 else "")
                raise CalibrationError(
                    f"{path}: {used} columns and no header row: cannot tell which are the "
                    f"accelerometer x, y, z{_triads_text(triads, None)}{transposed}; give "
                    "columns=[...] (0-based indices) and, if there is one, time_column="
                )
    if tcol is not None and tcol in acc:
        tcol = None
    unsigned = bool(head.shape[0]) and _stored_unsigned(head[:, acc])
    if unsigned:
        lv = _one_g(_signed16(head[:, acc]).astype(np.float64))
        notes.append(
            f"columns {_columns_text(names, acc)} {STORED_UNSIGNED_TEXT}: read as signed"
            + ("" if lv is None else f", their norm is {lv[0]:.5g} ({lv[1]})"))
    if tcol is None and time_column is None and not no_time:
        dated = [j for j in sorted(iso or ()) if j not in acc]
        if dated:
            tcol, tscale = dated[0], 1.0
            if names is not None:
                notes.append(f"column {names[tcol]!r} holds dates and times: read as the time")
    if tcol is None and names is None and time_column is None and not no_time:
        # Without a header, a remaining strictly increasing column is the time in s.
        for i in range(ncols):
            if i not in acc and _increasing(head[:, i]):
                if _is_counter(head[:, i]):
                    notes.append(
                        f"column {i} (0-based) counts samples (0, 1, 2, ...): not used as time"
                    )
                else:
                    tcol = i
                break
    if tcol is not None and not stated and tcol not in (iso or ()) and head.shape[0]:
        epoch = _epoch_unit(float(head[0, tcol])) if np.isfinite(head[0, tcol]) else None
        rate = None if epoch is None else _fs_from_time(head[:, tcol] * epoch[1], path)
        if epoch is not None and (rate is None or 1e-3 <= rate <= 1e6):
            tscale = epoch[1]
            notes.append(f"column {_label_of(names, tcol)} holds Unix epoch times in "
                         f"{epoch[0]}: read as such")
    temp = None
    if temp_spec is not None:
        temp = _resolve_one(temp_spec, names, ncols, path, "columns (the 4th, temperature)")
        if temp in acc or temp == tcol:
            raise CalibrationError(f"{path}: the temperature column (the 4th of columns=) is "
                                   f"also an accelerometer or the time column: {temp}")
    elif names is not None:
        for i, n in enumerate(names):
            if i not in acc and i != tcol and _is_temperature(n):
                temp = i
                break
    if names is not None and any(_gravity_removed(names[i]) for i in acc):
        notes.append(f"columns {', '.join(repr(names[i]) for i in acc)} look like a linear "
                     "(user) acceleration, from which the device's sensor fusion removed "
                     "gravity: a static calibration needs the raw accelerometer output, which "
                     "sees gravity")
    meta_rate = _fs_from_meta(meta, path, meta_lines)
    fs_meta, meta_where = (None, "") if meta_rate is None else meta_rate
    fs_time = None
    # Rows of another sensor (every accelerometer field empty, NaN in the head) are left
    # out of the read, so out of the rate too.
    own = ~np.all(np.isnan(head[:, acc]), axis=1) if head.shape[1] else np.ones(0, bool)
    if tcol is not None and own.sum() >= 2:
        fs_time = _fs_from_time(head[own, tcol] * tscale, path, notes)
    fsv: float | None
    if fs is not None:
        fsv, src = positive(fs, "fs", " (sample rate in Hz)"), "given"
    elif fs_meta is not None:
        fsv, src = fs_meta, "metadata"
    elif fs_time is not None:
        fsv, src = fs_time, "time column"
    else:
        fsv, src = None, None
    if (src == "metadata" and fsv is not None and fs_time is not None and tcol is not None
            and abs(fs_time / fsv - 1.0) > 0.05):
        # Two rates from the file that disagree: either may be the wrong one (a unit the
        # reader took wrong, a time column in ms), and the dwells depend on it.
        units = {1.0: "s", 1e-3: "ms", 1e-6: "us", 1e-9: "ns"}
        unit = units.get(tscale, "s")
        tname = names[tcol] if names is not None else str(tcol)
        # The unit of the time column that gives the metadata's rate, if one does.
        other = next((u for f, u in units.items() if f != tscale
                      and abs(fs_time * tscale / f / fsv - 1.0) <= 0.05), None)
        raise CalibrationError(
            f"{path}: {meta_where} gives {fsv:.6g} Hz but the time column "
            f"{_label_of(names, tcol)} read in {unit} gives {fs_time:.6g} Hz; give the rate "
            f"with fs= (Hz), or the time column's unit with time_column= (e.g. "
            f"'{tname} [{other or 'ms'}]'"
            + (f", which gives {fsv:.6g} Hz" if other else "") + ")")
    if fsv is not None and src != "time column" and fs_time is not None:
        if abs(fs_time / fsv - 1.0) > 0.01:
            said = "fs= " if src == "given" else "the file's metadata says "
            notes.append(
                f"the time column's intervals give {fs_time:.6g} Hz but {said}"
                f"{fsv:.6g} Hz; {fsv:.6g} Hz is used (the detected dwells depend on it)"
            )
    if fsv is None:
        need = ("the dwells' times need it (the time tests of diagnose)" if dwells_known
                else "dwell detection and sample times need it")
        notes.append(f"{NO_RATE_NOTE} (no rate metadata or time column); "
                     f"give fs= (Hz){_time_hint(names, acc, head)}: {need}")
    return _Layout(
        path=path,
        ncols=ncols,
        names=names,
        acc=acc,
        time=tcol,
        time_scale=tscale,
        temp=temp,
        metadata=meta,
        fs=fsv,
        fs_source=src,
        notes=notes,
        head=head,
        signed16=unsigned,
    )


def _time_hint(names: tuple[str, ...] | None, acc: list[int], head: NDArray[Any]) -> str:
    """When the sample rate is unknown: ``", or, if column 'X' ..."`` for a named column that
    increases strictly (and is no sample counter), else ``""``."""
    if names is None:
        return ""
    for i in range(head.shape[1]):
        if i not in acc and _increasing(head[:, i]) and not _is_counter(head[:, i]):
            return (f", or, if column {names[i]!r} (it increases steadily) is the time in s, "
                    "name it with time_column=")
    return ""


#: The norm of an accelerometer at rest (1 g) in the units it is written in: m/s^2, g, mg,
#: and the counts of an int16 output at +-2, 4, 8 and 16 g full scale.
_ONE_G = ((9.80665, "m/s^2"), (1.0, "g"), (1000.0, "mg"), (16384.0, "counts at 16384/g"),
          (8192.0, "counts at 8192/g"), (4096.0, "counts at 4096/g"),
          (2048.0, "counts at 2048/g"))


def _one_g(x: NDArray[Any]) -> tuple[float, str] | None:
    """The median row norm of (n, 3) samples and the unit it suggests, when it is within 5 %
    of 1 g in some unit (:data:`_ONE_G`) and stays within 5 % of that in 75 % of the rows
    (the rest may be motion between poses); else None."""
    x = x[np.all(np.isfinite(x), axis=1)]
    if x.shape[0] < 10:
        return None
    norm = np.linalg.norm(x, axis=1)
    level = float(np.median(norm))
    unit = next((u for v, u in _ONE_G if level > 0 and abs(level / v - 1.0) < 0.05), None)
    if unit is None or float(np.quantile(np.abs(norm / level - 1.0), 0.75)) >= 0.05:
        return None
    return level, unit


#: What :func:`_stored_unsigned` found, as the notes and warnings word it.
STORED_UNSIGNED_TEXT = (
    "hold signed 16-bit values stored as unsigned (65404 for -132; read as signed they stay "
    "near zero where stored they jump between the ends of 0..65535)"
)


def _signed16(x: NDArray[Any]) -> NDArray[Any]:
    """Signed 16-bit values stored as unsigned (65404 for -132) read as signed: a view for
    uint16 arrays, ``v - 65536`` for ``v >= 32768`` otherwise."""
    if x.dtype == np.uint16:
        return x.view(np.int16)
    return np.where(x >= 32768, x - 65536, x)


def _stored_unsigned(x: NDArray[Any]) -> bool:
    """Signed 16-bit samples stored as unsigned (65404 for -132): every value a whole number
    in 0..65535, and read as signed the values of some axis spread less than half as much
    as stored (an axis that crosses zero jumps between the two ends of the range), of none
    more. A 16-bit ADC that is unsigned by design (mid-scale 32768) spreads more when read as
    signed, so it is left as it is."""
    x = x[np.all(np.isfinite(x), axis=1)]
    if x.shape[0] < 10 or np.issubdtype(x.dtype, np.signedinteger) and x.dtype.itemsize <= 2:
        return False
    lo, hi = float(x.min()), float(x.max())
    if lo < 0 or hi > 65535 or hi < 32768 or not np.all(x == np.round(x)):
        return False
    raw = np.std(x.astype(np.float64), axis=0)
    signed = np.std(_signed16(x).astype(np.float64), axis=0)
    return bool(np.any(signed < 0.5 * raw) and np.all(signed <= raw))


def _triads_by_norm(head: NDArray[Any], tcol: int | None) -> list[tuple[list[int], float, str]]:
    """Adjacent column triples of a table whose rows keep a norm of 1 g (:func:`_one_g`),
    as stored or as signed 16-bit values stored unsigned (the unit then says so): an
    accelerometer among other channels (gyroscope, magnetometer, pressure). With the triple,
    its median norm and the unit it suggests."""
    out: list[tuple[list[int], float, str]] = []
    for j in range(head.shape[1] - 2):
        cols = [j, j + 1, j + 2]
        if tcol in cols:
            continue
        found = _one_g(head[:, cols])
        if found is None and _stored_unsigned(head[:, cols]):
            wrapped = _one_g(_signed16(head[:, cols]).astype(np.float64))
            found = None if wrapped is None else (wrapped[0], f"{wrapped[1]}, stored unsigned")
        if found is not None:
            out.append((cols, *found))
    return out


#: Names of quaternion components (``qx``, ``q0``, ``quat_w``): a unit quaternion's three
#: components can keep a norm near 1 (one "g").
_QUATERNION = re.compile(r"^(?:q|quat|quaternion|orientation)_?[wxyz0-3]$")


def _triads_text(triads: list[tuple[list[int], float, str]],
                 names: tuple[str, ...] | None) -> str:
    """`` (each of the adjacent columns 1,2,3; 4,5,6 keeps a norm of about 1 g: ...)``, or
    ``""`` without candidates."""
    if not triads:
        return ""
    cols = "; ".join(",".join(map(str, c)) if names is None else ",".join(names[i] for i in c)
                     for c, _, _ in triads)
    levels = ", ".join(sorted({f"{lv:.4g} {u}" for _, lv, u in triads}))
    return f" (each of the adjacent columns {cols} keeps a norm of about 1 g: {levels})"


def _increasing(x: NDArray[Any]) -> bool:
    return bool(x.shape[0] >= 2 and np.all(np.isfinite(x)) and np.all(np.diff(x) > 0))


#: Start of the note on a time column coarser than the sample interval (dropped when the
#: rows turn out to be poses, which have no sample interval).
_COARSE_TIME_NOTE = "the time column's resolution"


def _fs_from_time(t: NDArray[Any], path: str, notes: list[str] | None = None) -> float | None:
    """Sample rate from (the first rows of) a time column.

    The intervals within half the median interval of it (no dropouts, no repeated stamps) are
    averaged: their sum telescopes, so time stamps rounded to a fixed resolution (e.g. epoch
    seconds, whose float64 spacing is 2.4e-7 s) give the rate without the rounding of each
    interval. Stamps coarser than the sample interval (a 5 kHz stream stamped in ms: most
    intervals are 0) give the rows over their span instead, with a note in ``notes``.
    """
    if t.shape[0] < 2:
        return None
    d = np.diff(t.astype(np.float64))
    d = d[np.isfinite(d)]
    if d.size == 0:
        return None
    med = float(np.median(d))
    if med == 0 and np.all(d >= 0) and d.sum() > 0:
        step = float(np.min(d[d > 0]))
        span = float(d.sum())
        if notes is not None:
            notes.append(
                f"{_COARSE_TIME_NOTE} ({step:.3g} s) is coarser than the sample "
                f"interval: the rate is from its span, {d.size} intervals in {span:.6g} s "
                f"(+-{step / span:.1%})")
        return float(d.size / span)
    if not med > 0:
        raise CalibrationError(
            f"{path}: the time column is not increasing (median interval {med!r}); "
            "name the right one with time_column=, or give fs= and time_column= none (no "
            "time column)"
        )
    regular = d[np.abs(d - med) <= 0.5 * med]
    return float(regular.size / regular.sum())


def _names_of(lay: _Layout) -> tuple[str, ...]:
    if lay.names is None:
        return tuple(str(i) for i in lay.acc)
    return tuple(lay.names[i] for i in lay.acc)


def _text_groups(lay: _Layout) -> list[list[tuple[int, float, bool]]]:
    groups = [[(j, 1.0, False) for j in lay.acc]]
    if lay.time is not None:
        groups.append([(lay.time, lay.time_scale, lay.time in lay.iso)])
    if lay.temp is not None:
        groups.append([(lay.temp, 1.0, False)])
    return groups


def _text_kwargs(lay: _Layout, src: _TextSource) -> dict[str, Any]:
    kw: dict[str, Any] = {
        "delimiter": lay.delim,
        "decimal_comma": lay.decimal_comma,
        "names": list(lay.names) if lay.names is not None else None,
        "first_line": lay.first_line,
        "t0": lay.t0,
    }
    if lay.temp is not None:
        # A temperature written on some rows only (a slow channel): empty fields read NaN,
        # then hold the last value (`_Recording._hold_temperature`).
        kw["sparse_groups"] = [1 + (lay.time is not None)]
    # Rows with every accelerometer field empty belong to another sensor of a merged log.
    kw["skip_empty_rows"] = True
    if src.stdin or src.eof:
        kw.update(prefix=src.head, stdin=src.stdin and not src.eof)
    return kw


def _split_groups(
    lay: _Layout, arrays: list[NDArray[np.float64]]
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, NDArray[np.float64] | None]:
    samples = _signed16(arrays[0]) if lay.signed16 else arrays[0]
    i = 1
    t = temp = None
    if lay.time is not None:
        t = arrays[i]
        i += 1
    if lay.temp is not None:
        temp = arrays[i]
    return samples, t, temp


# ---- numpy and HDF5 files ---------------------------------------------------------------------
def _npy_layout(
    path: str,
    arr: NDArray[Any],
    columns: Any,
    fs: float | None,
    time_column: Any,
    meta: dict[str, str],
    names: tuple[str, ...] | None = None,
) -> _Layout:
    if arr.dtype.names:
        raise CalibrationError(
            f"{path}: structured arrays are not supported; save a plain (N, 3) array"
        )
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise CalibrationError(f"{path}: array must have shape (N, 3) or (N, >=3); got {arr.shape}")
    if arr.shape[0] == 0:
        raise CalibrationError(f"{path}: array is empty (0 rows)")
    if arr.dtype.kind not in "fiu":
        raise CalibrationError(f"{path}: unsupported dtype {arr.dtype} (need numbers)")
    head = np.asarray(arr[:_SNIFF_ROWS], dtype=np.float64)
    return _decide(path, names, arr.shape[1], head, meta, columns, fs, time_column)


def _np_load(path: str, mmap: bool = False) -> Any:
    try:
        return np.load(path, allow_pickle=False, mmap_mode="r" if mmap else None)
    except FileNotFoundError:
        raise CalibrationError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise CalibrationError(f"{path}: is a directory, not a recording file") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise CalibrationError(f"{path}: cannot read as a NumPy file ({e})") from None


def _npz_arrays(path: str) -> dict[str, Any]:
    try:
        # Open the file here: np.load leaks its handle when the zip is corrupt.
        with open(path, "rb") as fh:
            z = np.load(fh, allow_pickle=False)
            if not hasattr(z, "files"):
                raise CalibrationError(f"{path}: not a .npz archive (rename it .npy?)")
            with z:
                return {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise CalibrationError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise CalibrationError(f"{path}: is a directory, not a recording file") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise CalibrationError(f"{path}: cannot read as a .npz archive ({e})") from None


class _Columns:
    """A table held as named 1-D columns (HDF5 datasets read lazily, ``.npz`` arrays, a
    DataFrame's columns) presented as one (N, c) array sliced by rows."""

    def __init__(self, path: str, cols: dict[str, Any]) -> None:
        self.path = path
        self.names = tuple(cols)
        self.cols = list(cols.values())
        lens = {int(c.shape[0]) for c in self.cols}
        if len(lens) != 1:
            sizes = {n: int(c.shape[0]) for n, c in cols.items()}
            raise CalibrationError(f"{path}: columns have different lengths {sizes}")
        self.n = lens.pop()
        kinds = {np.dtype(c.dtype).kind for c in self.cols}
        self.dtype = (
            np.result_type(*[c.dtype for c in self.cols]) if kinds <= set("iu") or kinds <= {"f"}
            else np.dtype(np.float64)
        )

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n, len(self.cols))

    def rows(self, a: int, b: int, which: Sequence[int]) -> NDArray[Any]:
        return np.column_stack([np.asarray(self.cols[j][a:b]) for j in which])


def _table_from_dict(path: str, data: dict[str, Any]) -> tuple[Any, tuple[str, ...] | None]:
    """The sample table of a ``.npz``/HDF5 mapping: a 2-D array by key, or 1-D columns."""
    key = next((k for k in _SAMPLE_KEYS if k in data and np.ndim(data[k]) == 2), None)
    if key is None:
        two = [k for k in data if np.ndim(data[k]) == 2]
        if len(two) == 1:
            key = two[0]
    if key is not None:
        return data[key], None
    ones = {k: v for k, v in data.items() if np.ndim(v) == 1}
    leaf = {k.split("/")[-1]: k for k in ones}
    if ones and _auto_acc(list(leaf), path) is not None:
        return _Columns(path, {k: ones[v] for k, v in leaf.items()}), tuple(leaf)
    raise CalibrationError(
        f"{path}: cannot tell which array holds the samples (keys {list(data)}); name it one "
        f"of {list(_SAMPLE_KEYS)}, or give separate 1-D ax, ay, az arrays"
    )


def _h5_check_storage(path: str, name: str, ds: Any) -> None:
    """Refuse a dataset that declares more values than its file holds: contiguous storage
    smaller than the declared size, or a chunked dataset with no chunk written (every value
    the fill value). A file of a few kB declaring 2e9 samples is not a recording: reading it
    through would take hours and grow the dwell statistics without bound."""
    from h5py import h5d

    if ds.ndim == 0 or ds.size == 0 or ds.dtype.kind not in "fiub":
        return
    try:
        dcpl = ds.id.get_create_plist()
        layout = dcpl.get_layout()
        if dcpl.get_external_count() > 0:
            return  # raw data in other files: not this file's storage
        stored = ds.id.get_storage_size()
        if layout == h5d.CONTIGUOUS and stored < ds.nbytes:
            held = f"only {stored} bytes of it"
        elif layout == h5d.CHUNKED and stored == 0 and ds.id.get_num_chunks() == 0:
            held = "none of it (no chunk written: every value is the fill value)"
        else:
            return
    except (AttributeError, OSError, RuntimeError, ValueError):
        return  # an older h5py / HDF5 that cannot tell: read as before
    raise CalibrationError(
        f"{path}: dataset {name!r} declares {ds.shape} values ({ds.nbytes} bytes) but the "
        f"file holds {held}: a truncated or damaged file?")


def _h5_tree(path: str) -> tuple[Any, dict[str, Any], dict[str, Any]]:
    """An open HDF5 file, its datasets by leaf name (not read) and its scalar attributes."""
    try:
        import h5py
    except ImportError:
        raise CalibrationError(
            f"{path}: reading HDF5 needs h5py: pip install 'accelcal[hdf5]'"
        ) from None
    try:
        f = h5py.File(path, "r")
    except FileNotFoundError:
        raise CalibrationError(f"{path}: file not found") from None
    except (OSError, ValueError) as e:
        raise CalibrationError(f"{path}: cannot read as an HDF5 file ({e})") from None
    data: dict[str, Any] = {}

    def visit(name: str, obj: Any) -> None:
        if isinstance(obj, h5py.Dataset):
            _h5_check_storage(path, name, obj)
            leaf = name.split("/")[-1]
            data[leaf if leaf not in data else name] = obj[()] if obj.ndim == 0 else obj

    f.visititems(visit)
    attrs = {k: np.asarray(v) for k, v in f.attrs.items() if np.ndim(v) == 0}
    return f, data, attrs


@dataclass
class _ArraySource:
    """A numeric table (memory-mapped ``.npy``, ``.npz`` arrays, HDF5 datasets, a DataFrame)."""

    path: str
    table: Any  # (N, c) array-like supporting row slices, or _Columns
    lay: _Layout
    t: Any = None  # separate (N,) time array, in units of t_scale s
    t_name: str | None = None  # its key
    t_scale: float = 1.0  # its unit, s
    temp: Any = None
    closer: Callable[[], None] | None = None
    labels: list[str] | None = None  # a text label per row (a table of pose means' names)
    sections: Any = None  # Bounds of the labelled static sections of an annotated session

    def chunk(self, a: int, b: int) -> tuple[NDArray[Any], Any, Any]:
        lay = self.lay
        if isinstance(self.table, _Columns):
            cols = self.table.cols
            samples = np.ascontiguousarray(self.table.rows(a, b, lay.acc))
            t = temp = None
            if lay.time is not None:
                t = np.asarray(cols[lay.time][a:b], dtype=np.float64) * lay.time_scale
            if lay.temp is not None:
                temp = np.asarray(cols[lay.temp][a:b], dtype=np.float64)
        else:
            raw = np.asarray(self.table[a:b])
            samples = raw if lay.acc == [0, 1, 2] and raw.shape[1] == 3 else raw[:, lay.acc]
            t = None if lay.time is None else np.asarray(raw[:, lay.time], np.float64) * (
                lay.time_scale
            )
            temp = None if lay.temp is None else np.asarray(raw[:, lay.temp], np.float64)
        if lay.signed16:
            samples = _signed16(samples)
        if t is None and self.t is not None:
            t = np.asarray(self.t[a:b], dtype=np.float64)
            if self.t_scale != 1.0:
                t = t * self.t_scale
        if temp is None and self.temp is not None:
            temp = np.asarray(self.temp[a:b], dtype=np.float64)
        return samples, t, temp


def _scalar_meta(data: dict[str, Any]) -> dict[str, str]:
    out = {}
    for k, v in data.items():
        if np.ndim(v) == 0:
            x = np.asarray(v).item()
            out[k] = x.decode() if isinstance(x, bytes) else str(x)
    return out


def _array_source(
    path: str,
    data: dict[str, Any],
    columns: Any,
    fs: float | None,
    time_column: Any,
    extra_meta: dict[str, Any] | None = None,
    closer: Callable[[], None] | None = None,
) -> _ArraySource:
    # A rate stored as a one-element array (``np.savez(..., fs=[100.0])``, MATLAB's 1 x 1):
    # a scalar.
    data = {k: (v[0] if k in _FS_NPZ_KEYS and np.ndim(v) == 1 and np.shape(v)[0] == 1
                else v) for k, v in data.items()}
    table, names = _table_from_dict(path, data)
    scalars = {**(extra_meta or {}), **{k: v for k, v in data.items() if np.ndim(v) == 0}}
    meta = _scalar_meta(scalars)
    fsv: float | None = fs
    meta_fs = None
    fk = next((k for k in _FS_NPZ_KEYS if k in scalars), None)
    if fk is not None:
        meta_fs = positive(np.asarray(scalars[fk]).item(), f"{path}: {fk}", " (Hz)")
    # time_column= naming a separate 1-D array of the container (``'t [ms]'``), not a column
    # of the sample table.
    sep_t: tuple[str, float] | None = None
    if isinstance(time_column, str) and not _no_time(time_column, names):
        spec, unit_scale = _time_spec(time_column, None)
        if (isinstance(spec, str) and (names is None or spec not in names) and spec in data
                and np.ndim(data[spec]) == 1):
            found = _time_name(spec)
            sep_t = (spec, unit_scale if unit_scale is not None
                     else found[0] if found is not None else 1.0)
            time_column = False
    if isinstance(table, _Columns):
        n = table.n
        head = table.rows(0, min(n, _SNIFF_ROWS), range(len(table.names))).astype(np.float64)
        if n == 0:
            raise CalibrationError(f"{path}: the sample arrays are empty (0 rows)")
        lay = _decide(path, names, len(table.names), head, {}, columns, fsv, time_column)
    else:
        lay = _npy_layout(path, table, columns, fsv, time_column, {})
    lay.metadata = meta
    n = table.shape[0]
    src = _ArraySource(path, table, lay, closer=closer)
    if lay.time is None and (sep_t is not None or time_column is not False):
        tk = sep_t[0] if sep_t is not None else next(
            (k for k in (*_T_KEYS, *data) if k in data and np.ndim(data[k]) == 1
             and (names is None or k not in names) and _time_name(k) is not None), None)
        if tk is not None:
            if data[tk].shape[0] != n:
                raise CalibrationError(
                    f"{path}: {tk!r} has {data[tk].shape[0]} values but samples have {n} rows"
                )
            src.t, src.t_name = data[tk], tk
            found = _time_name(tk)
            src.t_scale = sep_t[1] if sep_t is not None else found[0] if found else 1.0
            tt = np.asarray(data[tk][:_SNIFF_ROWS], dtype=np.float64) * src.t_scale
            lay.notes = [x for x in lay.notes if "not in the file" not in x]
            fs_t = _fs_from_time(tt, path, lay.notes)
            if fsv is None and meta_fs is None and fs_t is not None:
                lay.fs, lay.fs_source = fs_t, "time column"
    if fsv is None and meta_fs is not None:
        lay.fs, lay.fs_source = meta_fs, "metadata"
        lay.notes = [x for x in lay.notes if "not in the file" not in x]
    if lay.temp is None:
        mk = next((k for k in _TEMP_KEYS if k in data and np.ndim(data[k]) == 1
                   and (names is None or k not in names)), None)
        if mk is not None:
            if data[mk].shape[0] != n:
                raise CalibrationError(
                    f"{path}: {mk!r} has {data[mk].shape[0]} values but samples have {n} rows"
                )
            src.temp = data[mk]
    return src


def _table_like(obj: Any) -> bool:
    return hasattr(obj, "__dataframe__") or (
        hasattr(obj, "columns") and hasattr(obj, "__getitem__") and hasattr(obj, "__array__")
    )


def _dataframe_source(obj: Any, columns: Any, fs: float | None, time_column: Any,
                      path: str = "<table>", named: bool = True,
                      meta: dict[str, str] | None = None,
                      dwells_known: bool = False) -> _ArraySource:
    """A DataFrame (pandas, polars, or anything with the interchange protocol): columns by
    name, as with a text header. ``meta``: what the file says about itself, as a text
    file's metadata lines (a rate in it ranks as in a text file: given > metadata > time
    column). ``dwells_known``: the table's own labels give the dwells (see ``_decide``)."""
    df = obj
    if not (hasattr(df, "columns") and hasattr(df, "__getitem__")):
        try:
            import pandas as pd
        except ImportError:
            raise CalibrationError(
                "reading a DataFrame-interchange object needs pandas: pip install pandas"
            ) from None
        read = None
        if hasattr(obj, "__dataframe__") and not hasattr(obj, "__arrow_c_stream__"):
            # pandas 3 deprecates the protocol but still reads it: its reader past the
            # warning (only the process-wide warning filters, not thread-safe, could hide it).
            from pandas.core.interchange import from_dataframe as xchg

            read = getattr(xchg, "_from_dataframe", None)
        df = (pd.api.interchange.from_dataframe(obj) if read is None
              else read(obj.__dataframe__(allow_copy=True)))
    cols: dict[str, Any] = {}
    starts: dict[str, str] = {}  # the first date-time of each date-time column
    for name in df.columns:
        c = df[name]
        if getattr(getattr(c, "dt", None), "tz", None) is not None:  # pandas, with a zone
            c = c.dt.tz_convert("UTC").dt.tz_localize(None)
        a = c.to_numpy() if hasattr(c, "to_numpy") else np.asarray(c)
        if a.dtype.kind == "M":  # datetimes: seconds since the first row
            if a.size:
                starts[str(name)] = str(np.datetime_as_string(a[0]))
            a = (a - a[0]).astype("timedelta64[ns]").astype(np.int64) * 1e-9
        elif a.dtype.kind not in "fiub":
            continue  # text, categories: not a sample column
        cols[str(name)] = a
    if not cols:
        raise CalibrationError("the table has no numeric columns")
    table = _Columns(path, cols)
    head = table.rows(0, min(table.n, _SNIFF_ROWS), range(len(table.names))).astype(np.float64)
    if table.n == 0:
        raise CalibrationError("the table is empty (0 rows)")
    lay = _decide(path, table.names if named else None, len(table.names), head, meta or {},
                  columns, fs, time_column, dwells_known=dwells_known)
    if lay.time is not None:
        lay.t0_text = starts.get(table.names[lay.time])
    return _ArraySource(path, table, lay)


def _plain_array_source(
    obj: Any, columns: Any, fs: float | None, time_column: Any
) -> _ArraySource:
    a = np.asarray(obj)
    if a.dtype.kind == "c":
        raise CalibrationError("samples are complex numbers; give real x, y, z values")
    lay = _npy_layout("<array>", a, columns, fs, time_column, {})
    return _ArraySource("<array>", a, lay)


# ---- opening any recording --------------------------------------------------------------------
def _path(path: Any) -> str:
    try:
        return os.fspath(path)
    except TypeError:
        raise CalibrationError(
            f"path must be a file path, '-' (standard input), a DataFrame or an array; "
            f"got {type(path).__name__}"
        ) from None


def _refuse_pipe(p: str) -> None:
    """A named pipe or a device would block or lose data: the reader opens a file twice (its
    head for the layout, then the whole), which a pipe cannot give."""
    if p == "-":
        return
    try:
        mode = os.stat(p).st_mode
    except OSError:
        return  # missing or unreadable: the reader says which
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise CalibrationError(
            f"{p} is not a regular file (a pipe or a device), which the reader would have to "
            "read twice: write it to a file first, or send it to standard input and give '-' "
            "as the file (e.g. zcat rec.csv.gz | accelcal dwells -)")


def _kind(p: str) -> str:
    low = p.lower()
    if low.endswith(".npy"):
        return "npy"
    if low.endswith(".npz"):
        return "npz"
    if low.endswith((".h5", ".hdf5", ".hdf")):
        return "h5"
    if low.endswith(".mat"):
        return _mat_kind(p)
    if low.endswith((".xlsx", ".xlsm", ".xls", ".ods")):
        return "sheet"
    if low.endswith((".parquet", ".pq", ".feather", ".arrow")):
        return "arrow"
    if low.endswith(".tdms"):
        return "tdms"
    if low.endswith((".mseed", ".miniseed", ".msd", ".seed")):
        return "mseed"
    from ._formats import is_rosbag

    return "rosbag" if is_rosbag(p) else "text"


def _mat_kind(p: str) -> str:
    """"mat5" or "mat73" for a binary MATLAB file, "text" for an ASCII one (as MATLAB's
    ``save -ascii`` writes them)."""
    try:
        with open(p, "rb") as fh:
            head = fh.read(520)
    except OSError:
        return "text"  # the text reader names the problem
    if head.startswith(b"MATLAB 5.0 MAT-file"):
        return "mat5"
    if head[512:520] == b"\x89HDF\r\n\x1a\n":
        return "mat73"
    return "text"


def _mat_arrays(p: str, kind: str) -> dict[str, Any]:
    """The numeric variables of a binary MATLAB file as a ``.npz``-like mapping: matrices as
    MATLAB shows them (v7.3 stores them transposed), vectors 1-D, scalars 0-D."""
    out: dict[str, Any] = {}
    if kind == "mat5":
        try:
            from scipy.io import loadmat
        except ImportError:
            raise CalibrationError(
                f"{p}: a binary MATLAB (v5) file; reading it needs scipy (pip install scipy), "
                "or export the samples to CSV") from None
        try:
            raw = loadmat(p, squeeze_me=True)
        except (ValueError, TypeError, OSError, NotImplementedError) as e:
            raise CalibrationError(f"{p}: cannot read the MATLAB file: {e}") from None
        items = [(k, v) for k, v in raw.items() if not k.startswith("__")]
    else:
        try:
            import h5py
        except ImportError:
            raise CalibrationError(
                f"{p}: a MATLAB v7.3 file (HDF5); reading it needs h5py (pip install h5py), "
                "or export the samples to CSV") from None
        with h5py.File(p, "r") as f:
            items = [(k, np.asarray(v).T) for k, v in f.items()
                     if isinstance(v, h5py.Dataset) and v.dtype.kind in "fiu"]
    for k, v in items:
        a = np.asarray(v)
        if a.dtype.kind in "fiu" and a.ndim <= 2:
            out[k] = np.squeeze(a) if a.ndim == 2 and 1 in a.shape else a
    if not out:
        raise CalibrationError(f"{p}: the MATLAB file holds no numeric matrix or vector")
    return out


def _located(path: str, it: Any, fn: Callable[..., Any] | None = None, *a: Any,
             **kw: Any) -> Any:
    """Prefix the reader's errors (which name the line) with the file: either call
    ``fn(*a, **kw)`` or wrap the iterator ``it``."""
    if fn is not None:
        try:
            return fn(*a, **kw)
        except CalibrationError as e:
            raise CalibrationError(f"{path}: {e}{_bad_row_hint(path, str(e))}") from None

    def gen() -> Iterator[Any]:
        try:
            yield from it
        except CalibrationError as e:
            raise CalibrationError(f"{path}: {e}{_bad_row_hint(path, str(e))}") from None

    return gen()


def _bad_row_hint(path: str, msg: str) -> str:
    """What a row that is not a number may be: the header again (files joined), or the
    file's last line (a logger's closing text)."""
    return _repeated_header_hint(msg) or _trailer_hint(path, msg)


def _last_line(path: str) -> tuple[int, bool] | None:
    """The number of the file's last non-blank line (as the reader numbers lines: a last line
    without its newline counts) and whether the file ends in a newline; None for what is not
    a regular file, or is too big for a second pass (over 1 GB)."""
    if not os.path.isfile(path):
        return None
    try:
        if os.path.getsize(path) > 1 << 30:
            return None  # a second pass over a file this big is not worth a hint
        newlines, tail = 0, b""
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 24), b""):
                newlines += block.count(b"\n")
                tail = (tail + block)[-65536:]
    except OSError:
        return None
    lines = tail.split(b"\n")
    total = newlines + (1 if lines[-1] else 0)
    blank = 0
    for ln in reversed(lines[:-1] if not lines[-1] else lines):
        if ln.strip():
            break
        blank += 1
    return total - blank, tail.endswith(b"\n")


def _trailer_hint(path: str, msg: str) -> str:
    """For a field that is not a number on the file's last non-empty line: a trailer."""
    m = re.match(r"line (\d+): .* is not a number", msg)
    last = _last_line(path) if m else None
    if m is None or last is None or last[0] != int(m.group(1)):
        return ""
    return ("; it is the file's last line, text after the data (a logger's closing message): "
            f"delete it (e.g. sed '{m.group(1)}d' FILE > data.csv)")


def _left_out_hint(path: str, line: int, what: str) -> str:
    """What a left-out row that did not parse likely is: the header again (files joined),
    the file's last line cut off, or text after the data."""
    if _repeated_header_hint(f"line {line}: {what}"):
        return "the line repeats the header: files joined one after the other?"
    last = _last_line(path)
    if last is None or last[0] != line:
        return "lines cut short or run together, as a serial capture drops them"
    if not last[1]:
        return ("the file's last line, cut off (no line end): a file whose writing or copying "
                "stopped? The rows before it are read")
    return "the file's last line: text after the data (a logger's closing message)?"


def _repeated_header_hint(msg: str) -> str:
    """For a data field that reads its own column's name: the header again (files joined)."""
    m = re.search(r'column "([^"]*)": "([^"]*)" is not a number', msg)
    if m and m.group(1) == m.group(2):
        return ("; the line repeats the header: files joined one after the other? Remove the "
                "repeated header lines (e.g. awk 'NR == 1 || $0 != h {print} NR == 1 {h = $0}'),"
                " or read the parts separately")
    return ""


_Chunk = tuple[NDArray[Any], NDArray[np.float64] | None, NDArray[np.float64] | None]


def _take(
    pending: list[_Chunk], n: int, have: int
) -> tuple[_Chunk, list[_Chunk], int]:
    """The first ``n`` rows of the pending pieces, and what remains."""
    parts: list[_Chunk] = []
    need = n
    while need > 0:
        s, t, temp = pending[0]
        m = s.shape[0]
        if m <= need:
            parts.append(pending.pop(0))
            need -= m
        else:
            parts.append((s[:need], None if t is None else t[:need],
                          None if temp is None else temp[:need]))
            pending[0] = (s[need:], None if t is None else t[need:],
                          None if temp is None else temp[need:])
            need = 0
    if len(parts) == 1:
        out = parts[0]
    else:
        out = (
            np.concatenate([p[0] for p in parts]),
            None if parts[0][1] is None else np.concatenate([p[1] for p in parts]),
            None if parts[0][2] is None else np.concatenate([p[2] for p in parts]),
        )
    return out, pending, have - n


class _TimeUnwrap:
    """A time column read chunk by chunk, made monotonic where a counter wrapped around.

    A backward step of about ``2^w`` units of the column (w = 16, 24, 31 or 32: a 32-bit
    microsecond counter wraps every 71.6 min, a 16-bit millisecond one every 65.5 s), less one
    sample interval, is a counter wrap: every later time gets ``2^w`` units added. Another
    backward step (a clock reset, files joined) is left as it is and counted for a note.
    """

    WIDTHS = (16, 24, 31, 32)
    SLICE = 1 << 16

    def __init__(self, unit_s: float, fs: float | None) -> None:
        self.unit_s, self.fs = unit_s, fs
        self.offset = 0.0
        self.prev: float | None = None  # the last time of the previous chunk, as read
        self.wraps: list[tuple[int, int]] = []  # (row, counter width)
        self.back: list[tuple[int, float]] = []  # (row, step back in s)
        self.gaps = _TimeGaps(fs)


    def __call__(self, t: NDArray[np.float64], row0: int) -> NDArray[np.float64]:
        if t.size > self.SLICE:  # bounded temporaries for a whole file read at once
            cuts = range(0, t.size, self.SLICE)
            views = [t[a:a + self.SLICE] for a in cuts]
            parts = [self(v, row0 + a) for v, a in zip(views, cuts, strict=True)]
            unchanged = all(p is v for p, v in zip(parts, views, strict=True))
            return t if unchanged else np.concatenate(parts)
        if t.size == 0:
            return t
        first = t[0] if self.prev is None else self.prev
        self.prev = float(t[-1])
        d = np.diff(t, prepend=first)
        self.gaps.push(d, row0)
        if not (d < 0).any():  # no step back
            return t if self.offset == 0.0 else t + self.offset
        steps = np.flatnonzero(d < 0)
        add = np.full(t.shape, self.offset)
        dt = 1.0 / self.fs if self.fs else float(np.median(np.diff(t))) if t.size > 1 else 0.0
        for i in steps:
            before = t[i - 1] if i > 0 else first
            jump = float(before - t[i]) + dt
            width = next((w for w in self.WIDTHS if abs(jump - 2.0**w * self.unit_s)
                          <= max(10 * dt, 1e-6 * 2.0**w * self.unit_s)), None)
            if width is None:
                self.back.append((row0 + int(i), jump - dt))
                continue
            self.wraps.append((row0 + int(i), width))
            self.offset += 2.0**width * self.unit_s
            add[i:] = self.offset
        return t + add

    def notes(self, label: str) -> list[str]:
        out = []
        if self.wraps:
            w = self.wraps[0][1]
            unit = {1.0: "s", 1e-3: "ms", 1e-6: "us", 1e-9: "ns"}.get(self.unit_s,
                                                                      f"{self.unit_s:g} s")
            out.append(
                f"the time column {label} wraps around {len(self.wraps)} time(s) (a {w}-bit "
                f"counter of 1 {unit}: every {2.0**w * self.unit_s:.6g} s; the first at data "
                f"row {self.wraps[0][0] + 1}): unwrapped, so times keep increasing")
        if self.back:
            r, j = self.back[0]
            out.append(
                f"the time column {label} steps back {len(self.back)} time(s) (the first at "
                f"data row {r + 1}, by {j:.6g} s) by no counter width: a clock reset or joined "
                "files? The dwell times after it are on the new clock (the time and drift "
                "tests of diagnose assume one clock)")
        return out + self.gaps.notes(label)


class _TimeGaps:
    """Intervals of a time column that skip samples: longer than ``FACTOR`` sample intervals
    (``1 / fs``, the rate of the regular intervals), counted chunk by chunk.

    A logger that stamps samples in bursts (several rows with one stamp or nearly, then a long
    interval) has long intervals too, but nothing missing: its intervals shorter than
    ``1 / FACTOR`` of a sample interval are as common as the long ones, and then no gap is
    reported."""

    FACTOR = 3.0

    def __init__(self, fs: float | None) -> None:
        self.dt = 1.0 / fs if fs else None
        self.count = 0  # long intervals
        self.short = 0  # intervals shorter than dt / FACTOR (bursts)
        self.missing = 0.0  # samples the long intervals hold beyond one each
        self.largest: tuple[float, int] | None = None  # (interval s, 0-based row after it)
        self.n = 0  # intervals seen
        self.total = 0.0  # their sum, s (the ones that go forward)

    def push(self, d: NDArray[np.float64], row0: int) -> None:
        """Intervals ``d`` (s) before rows ``row0`` on (the first from the previous chunk's
        last time; the column's first row has none)."""
        if self.dt is None or d.size == 0:
            return
        d = d[1:] if row0 == 0 else d
        off = 1 if row0 == 0 else 0
        self.n += d.size
        self.total += float(d[d > 0].sum())
        self.short += int(np.count_nonzero((d >= 0) & (d < self.dt / self.FACTOR)))
        long = np.flatnonzero(d > self.FACTOR * self.dt)
        if long.size == 0:
            return
        self.count += int(long.size)
        self.missing += float(d[long].sum()) / self.dt - long.size
        i = int(long[np.argmax(d[long])])
        if self.largest is None or d[i] > self.largest[0]:
            self.largest = (float(d[i]), row0 + off + i)

    def notes(self, label: str) -> list[str]:
        if self.largest is None or self.missing < 1.0 or self.short >= 0.5 * self.count:
            return []  # none, or bursts of stamps rather than lost samples
        if self.dt is not None and self.count >= 0.9 * self.n:
            # Nearly every interval is long: not lost samples, but a clock in other units
            # than the rate given (t = 10, 20, ... ms read in s beside fs = 100 Hz said "99.9 %
            # missing").
            ratio = self.total / max(self.n, 1) / self.dt
            unit = next((u for u, f in (("ms", 1e3), ("us", 1e6), ("ns", 1e9))
                         if 0.5 * f <= ratio <= 2.0 * f), None)
            name = label[1:-1] if label.startswith("'") and label.endswith("'") else (
                label.split()[0])  # 'x' or 3 (0-based)
            why = (f"it looks like a clock in {unit} read in s: name its unit with "
                   f"time_column= (e.g. '{name} [{unit}]')" if unit else
                   "check the rate given (fs=) and the time column's unit")
            return [f"the time column {label} steps by {ratio:.4g} sample intervals of the "
                    f"rate given ({1.0 / self.dt:.6g} Hz) on average: {why}; the dwell times "
                    "are in its units as read"]
        big, row = self.largest
        longest = f"{big * 1e3:.3g} ms" if big < 1 else f"{big:.4g} s"
        return [
            f"the time column {label} skips {self.count} time(s) by more than "
            f"{self.FACTOR:g} sample intervals (the longest {longest}, between data rows "
            f"{row} and {row + 1}; about {self.missing:.0f} samples, "
            f"{self.missing / max(self.n + self.missing, 1.0):.1%} of the recording's span, "
            "are missing in all): the logger lost samples. Dwell means and times stand; a "
            "dwell holds fewer samples than its span, and the dwell detector, which counts "
            "samples, sees a move lost in a gap as a jump"]


#: The Rust core's advice in its "too few samples per window" error (``dwell.rs``,
#: ``DetectorSettings::validate``): a longer window, s.
_WINDOW_ADVICE = re.compile(r" \(is fs the sample rate in Hz\? else give window_s= "
                            r"([0-9.eE+-]+) s or more\)")


class _Recording:
    """An opened recording: its layout, and its rows as chunks (one pass)."""

    def __init__(self, path: Any, columns: Any, fs: float | None, time_column: Any) -> None:
        self.text: _TextSource | None = None
        self.arrays: _ArraySource | None = None
        if isinstance(path, (str, os.PathLike)):
            p = _path(path)
            _refuse_pipe(p)
            kind = _kind(p)
            if kind == "text":
                self.text = _read_head(p)
                if not self.text.stdin and _is_mseed(self.text.head):
                    kind, self.text = "mseed", None  # a miniSEED file named otherwise
            if kind == "text" and self.text is not None:
                comp = None if self.text.stdin else _compression(self.text.head)
                if comp is not None:  # expanded first: the parser reads files in place
                    tmp, release = _decompressed(p, comp)
                    self._tmp = weakref.finalize(self, release)
                    src = _read_head(tmp)
                    self.text = _TextSource(p, src.head, src.eof, src.size, file=tmp)
                text = self.text
                try:
                    self.lay = _sniff(text, columns, fs, time_column)
                except (_LongFormat, _LabelPairs) as e:
                    if text.stdin:
                        raise
                    self.text = None
                    read = (_label_pairs_source if isinstance(e, _LabelPairs)
                            else _long_format_source)
                    self.arrays = read(text, columns, fs, time_column)
                    self.lay = self.arrays.lay
                if comp is not None:
                    self.lay.notes.append(f"{comp}-compressed text: read through a temporary "
                                          f"file of {text.size or 0} bytes")
            elif kind == "npy":
                arr = _np_load(p, mmap=True)
                if not isinstance(arr, np.ndarray):
                    raise CalibrationError(f"{p}: not a .npy array file")
                self.arrays = _ArraySource(p, arr, _npy_layout(p, arr, columns, fs, time_column,
                                                               {}))
            elif kind == "npz":
                self.arrays = _array_source(p, _npz_arrays(p), columns, fs, time_column)
            elif kind in ("mat5", "mat73"):
                self.arrays = _array_source(p, _mat_arrays(p, kind), columns, fs, time_column)
            elif kind in ("sheet", "arrow", "tdms", "mseed", "rosbag"):
                from . import _formats

                self.arrays = _formats.SOURCES[kind](p, columns, fs, time_column)
            else:
                f, data, attrs = _h5_tree(p)
                try:
                    self.arrays = _array_source(p, data, columns, fs, time_column, attrs, f.close)
                except BaseException:
                    f.close()
                    raise
        elif _table_like(path):
            self.arrays = _dataframe_source(path, columns, fs, time_column)
        elif hasattr(path, "__array__") or isinstance(path, (list, tuple)):
            self.arrays = _plain_array_source(path, columns, fs, time_column)
        else:
            raise CalibrationError(
                "a recording must be a file path, '-' (standard input), a DataFrame or an "
                f"array; got {type(path).__name__}"
            )
        if self.arrays is not None:
            self.lay = self.arrays.lay
        self.path = self.lay.path
        self.rows = 0
        self.repeats = 0
        self.bytes = 0
        self.pose_table = False  # read as a table of dwell means (one row per pose)
        self.skipped = 0  # rows whose accelerometer fields are all empty (merged logs)
        self.bad = 0  # rows that did not parse, left out (a serial capture's broken lines)
        self.first_bad: tuple[int, str] | None = None  # (line, what was wrong)
        self._bad_hint: str | None = None  # what the first of them likely is
        self.untimed = 0  # rows whose time is NaN or infinite, left out
        # The file's last line, numeric but cut off (a file still being written): its line
        # number (None when unknown) and text, left out of the read.
        self.cut_last: tuple[int | None, str] | None = (
            self._cut_last_line() if self.text is not None else None)
        self.first_untimed: int | None = None  # the first of them, 0-based data row as read
        self._temp_last: float | None = None  # the sparse temperature's last value
        self._temp_held = 0  # its empty fields filled
        self._last: NDArray[Any] | None = None
        lay = self.lay
        iso = lay.time is not None and lay.time in lay.iso
        from_file = lay.time is not None or (self.arrays is not None and self.arrays.t is not None)
        unit_s = (lay.time_scale if lay.time is not None
                  else self.arrays.t_scale if self.arrays is not None else 1.0)
        self._unwrap = _TimeUnwrap(unit_s, lay.fs) if from_file and not iso else None

    # -- what is known before reading
    def no_rate(self) -> str:
        """The error for a recording whose sample rate is unknown."""
        lay = self.lay
        est = self.rows_estimate()
        poses = ("; or, if each row is already a pose's mean (a table of dwell means), read "
                 "it with means=True" if est is not None and est <= POSE_TABLE_ROWS else "")
        return (f"{lay.path}: the sample rate is unknown (no rate metadata or time column); "
                f"give fs= (Hz){_time_hint(lay.names, lay.acc, lay.head)}{poses}")

    def rate_hint(self) -> str:
        """For a sample rate taken from the time column: which unit of it gives a plausible
        rate (1 Hz to 100 kHz), or ``""``."""
        lay = self.lay
        if lay.fs_source != "time column" or lay.fs is None:
            return ""
        if lay.time is not None:
            scale = lay.time_scale
            name = lay.names[lay.time] if lay.names is not None else str(lay.time)
            label = _label(lay, lay.time)
        elif self.arrays is not None and self.arrays.t_name is not None:
            # The container's own time array (``t`` of a .npz, an HDF5 dataset).
            scale, name = self.arrays.t_scale, self.arrays.t_name
            label = repr(name)
        else:
            return ""
        unit = {1.0: "s", 1e-3: "ms", 1e-6: "us", 1e-9: "ns"}.get(scale, "s")
        alt = [(u, lay.fs * scale / f) for u, f in _TIME_UNITS.items()
               if u in ("s", "ms", "us", "ns") and f != scale]
        alt = [(u, r) for u, r in alt if 1.0 <= r <= 1e5]
        if not alt:
            return ""
        said = " or ".join(f"{u} ({r:.6g} Hz)" for u, r in alt)
        return (f"the rate {lay.fs:.6g} Hz comes from the time column {label} "
                f"read in {unit}: if it is in {said}, name its unit with time_column= (e.g. "
                f"'{name} [{alt[0][0]}]') or give fs=")

    def untimed_note(self) -> str:
        """For a calibrated stream of this recording written without a time column (none
        read, no rate known) while a column looks like its clock (:meth:`clock_hint`): that
        it was not written, why, and how to write it; ``""`` for a recording with no clock
        (its output lacks nothing it had)."""
        clock = self.clock_hint()
        if not clock:
            return ""
        return ("no time column (t_s) written: the sample rate is unknown (no rate metadata "
                f"or time column read); {clock} to write t_s, or give fs= (Hz)")

    def clock_hint(self) -> str:
        """For a recording read without a time column: the column that may be its clock,
        ``"column 0 (0-based) looks like a clock (...): if it is the time in ms (84.457 Hz),
        name it with time_column= (e.g. '0 [ms]')"``, or ``""``. A clock increases in nearly
        every row (one that steps back a few times: files joined) and is no accelerometer,
        temperature or sample-counter column; its mean step read in s, ms, us and ns gives
        the units whose rate is plausible (1 Hz to 100 kHz)."""
        lay = self.lay
        head = lay.head
        if lay.time is not None or head.ndim != 2:
            return ""
        for j in range(head.shape[1]):
            if j in lay.acc or j == lay.temp:
                continue
            x = head[:, j].astype(np.float64)
            if x.shape[0] < 10 or not np.all(np.isfinite(x)) or _is_counter(x):
                continue
            d = np.diff(x)
            back = int(np.count_nonzero(d < 0))
            if np.count_nonzero(d > 0) < 0.9 * d.size:
                continue
            # The mean of the steps near the median (no gaps, no repeats): stamps rounded to
            # whole ms still give the rate between them.
            med = float(np.median(d[d > 0]))
            step = float(np.mean(d[(d > 0.5 * med) & (d < 1.5 * med)]))
            said = [(u, 1.0 / (step * f)) for u, f in (("s", 1.0), ("ms", 1e-3),
                                                        ("us", 1e-6), ("ns", 1e-9))]
            said = [(u, r) for u, r in said if 1.0 <= r <= 1e5]
            if not said:
                continue
            name = lay.names[j] if lay.names is not None else str(j)
            steps = (f"; it steps back {back} time{'' if back == 1 else 's'} in the first "
                     f"{x.shape[0]} rows: joined files?" if back else "")
            units = " or ".join(f"{u} ({r:.5g} Hz)" for u, r in said)
            return (f"column {_label(lay, j)} looks like a clock (mean step {step:.4g}"
                    f"{steps}): if it is the time in {units}, name it with time_column= "
                    f"(e.g. '{name} [{said[0][0]}]')")
        return ""

    def dwell_accumulator(self, bounds: Any = None, units: str = "",
                          **detector: Any) -> Any:
        """A :class:`~accelcal.DwellAccumulator` for this recording's rate, with the error
        explained when the rate came from a time column of the wrong unit. ``bounds``: (k, 2)
        rows, or a bounds file or :class:`Bounds` (its notes join the recording's)."""
        from .dwell import DwellAccumulator

        if isinstance(bounds, (str, os.PathLike)):
            bounds = read_bounds(bounds)
        if isinstance(bounds, Bounds):
            self.lay.notes += bounds.notes
            bounds = bounds.rows(self.fs)

        if bounds is None and self.fs is None:
            raise CalibrationError(self.no_rate())
        try:
            return DwellAccumulator(bounds, fs=self.fs, units=units, check_times=False,
                                    **({} if bounds is not None else detector))
        except CalibrationError as exc:
            hint = self.rate_hint() if bounds is None else ""  # the rate sizes detection only
            # Below 1 Hz the clock read in another unit is the fix (its rate is usable: the
            # hint names it), not a window of minutes.
            msg = self._window_advice(str(exc), bool(hint) and self.fs is not None
                                      and self.fs < 1.0)
            if not hint and msg == str(exc):
                raise
            raise CalibrationError(f"{msg}; {hint}" if hint else msg) from None

    def _window_advice(self, msg: str, other_unit: bool) -> str:
        """The detector's "too few samples per window" error ``msg`` without advice that
        misleads: no longer window when the rate read from the time column is below any
        detector's reach and another unit of it gives a usable rate (``other_unit``: that is
        the fix), nor one longer than the whole recording."""
        m = _WINDOW_ADVICE.search(msg)
        if m is None:
            return msg
        if other_unit:
            return msg[:m.start()] + msg[m.end():]
        rows = self.rows_estimate()
        span = rows / self.fs if rows and self.fs else None
        try:
            need = float(m.group(1))
        except ValueError:
            return msg
        if span is None or need <= span:
            return msg
        about = "" if self.arrays is not None else "about "
        return (msg[:m.start()] + f" (is fs the sample rate in Hz? At {self.fs:.6g} Hz a "
                f"window needs {need:g} s or more, longer than the whole recording ({about}"
                f"{rows} rows, {span:.4g} s): no dwell can be detected in it)" + msg[m.end():])

    @property
    def fs(self) -> float | None:
        return self.lay.fs

    @property
    def size_bytes(self) -> int | None:
        return None if self.text is None else self.text.size

    def rows_estimate(self) -> int | None:
        """Rows expected (exact for arrays; from the file size and the head rows for text)."""
        if self.arrays is not None:
            return int(self.arrays.table.shape[0])
        assert self.text is not None
        if self.text.size is None:
            return None
        return max(int((self.text.size - self.lay.offset) / self.lay.bytes_per_row), 1)

    # -- reading
    def _add_bad(self, bad: tuple[int, int, str] | None) -> None:
        """Count the rows a block left out because they did not parse (the Rust reader
        refuses the file when they are more than 10 and 1 % of its rows)."""
        if bad is not None:
            self.bad += bad[0]
            if self.first_bad is None:
                self.first_bad = (bad[1], bad[2])

    def _drop_untimed(self, s: NDArray[Any], t: NDArray[np.float64] | None,
                      temp: NDArray[np.float64] | None, row0: int
                      ) -> tuple[NDArray[Any], NDArray[np.float64] | None,
                                 NDArray[np.float64] | None]:
        """The rows whose time read from the file is finite: a NaN or infinite time (``NaN``
        written for a missing stamp) is left out, as a row with an empty time field is."""
        if t is None:
            return s, t, temp
        ok = np.isfinite(t)
        if ok.all():
            return s, t, temp
        if self.first_untimed is None:
            self.first_untimed = row0 + int(np.argmin(ok))
        self.untimed += int(ok.size - np.count_nonzero(ok))
        return s[ok], t[ok], None if temp is None else temp[ok]

    def _untimed_line(self) -> tuple[int, str] | None:
        """The line of the text file that holds the first non-finite time, and that
        time's text; None when it cannot be read again (standard input) or found."""
        lay, src = self.lay, self.text
        if src is None or lay.time is None or src.stdin:
            return None
        try:
            with open(src.opened, "rb") as fh:
                fh.seek(lay.offset)
                for i, raw in enumerate(fh):
                    line = raw.decode("utf-8", "replace").strip("\r\n")
                    fields = _split(line, lay.delim)
                    if len(fields) <= lay.time:
                        continue
                    v = fields[lay.time].strip().strip("\"'")
                    if v.lower().lstrip("+-") in ("nan", "inf", "infinity"):
                        return lay.first_line + i, v
        except OSError:
            return None
        return None

    def _cut_last_line(self) -> tuple[int | None, str] | None:
        """The file's last line when it has no line end and, though its fields are numbers,
        its last field is shorter than in every one of the rows before it (``-4.6`` under
        ``-4.627180``): cut off while the file was written or copied. A complete last line
        without its line end is not."""
        src, lay = self.text, self.lay
        if src is None or src.stdin or lay.time in lay.iso:
            return None
        try:
            with open(src.opened, "rb") as fh:
                fh.seek(0, os.SEEK_END)
                size = fh.tell()
                if size <= lay.offset:
                    return None
                start = max(lay.offset, size - 8192)
                fh.seek(start)
                tail = fh.read()
        except OSError:
            return None
        if not tail or tail.endswith(b"\n"):
            return None
        lines = tail.decode("utf-8", "replace").split("\n")
        last = lines[-1].rstrip("\r")
        before = [ln.rstrip("\r") for ln in lines[-21:-1] if ln.strip()]
        if start > lay.offset and before:
            before = before[1:]  # the first may be cut by the 8 KB window
        fields = _split(last.strip(), lay.delim)
        if len(before) < 3 or len(fields) != lay.ncols or not _is_number(
                fields[-1].strip().replace(",", ".")):
            return None
        widths = [len(_split(ln.strip(), lay.delim)[-1].strip()) for ln in before
                  if len(_split(ln.strip(), lay.delim)) == lay.ncols]
        if len(widths) < 3 or len(fields[-1].strip()) >= min(widths):
            return None
        where = _last_line(src.opened)
        return (None if where is None else where[0]), last.strip()

    def _count_repeats(self, samples: NDArray[Any]) -> None:
        if samples.shape[0] == 0:
            return
        eq = np.all(samples[1:] == samples[:-1], axis=1)
        self.repeats += int(np.count_nonzero(eq))
        if self._last is not None and np.array_equal(self._last, samples[0]):
            self.repeats += 1
        self._last = np.array(samples[-1])

    def chunks(
        self, chunk_rows: int | None = None, progress: Callable[[int, int], None] | None = None
    ) -> Iterator[tuple[NDArray[Any], NDArray[np.float64] | None, NDArray[np.float64] | None]]:
        """(samples, t, temperature) chunks of at most ``chunk_rows`` rows, in order.

        ``progress(rows, bytes)`` is called after every chunk (bytes are 0 for arrays).
        """
        lay = self.lay
        if self.arrays is not None:
            src = self.arrays
            n = int(src.table.shape[0])
            step = chunk_rows or 262_144
            try:
                for a in range(0, n, step):
                    b = min(a + step, n)
                    s, t, temp = src.chunk(a, b)
                    s, t, temp = self._drop_untimed(s, t, temp, a)
                    temp = self._hold_temperature(temp, a)
                    if t is None and lay.fs is not None:
                        t = np.arange(a, b, dtype=np.float64) / lay.fs
                    elif self._unwrap is not None and t is not None:
                        t = self._unwrap(t, a)
                    self._count_repeats(s)
                    self.rows = b
                    if progress is not None:
                        progress(b, 0)
                    yield s, t, temp
            finally:
                if src.closer is not None:
                    src.closer()
            return
        assert self.text is not None
        src_t = self.text
        bpr = lay.bytes_per_row
        block = int(min(max((chunk_rows or 10**9) * bpr, 1 << 16), 4 << 20))
        blocks = _located(src_t.path, _core.TextBlocks(
            None if (src_t.stdin or src_t.eof) else src_t.opened,
            lay.offset,
            lay.ncols,
            _text_groups(lay),
            block_bytes=block,
            **_text_kwargs(lay, src_t),
        ))
        pending: list[tuple[Any, Any, Any]] = []
        have = 0
        parsed = 0
        it = iter(blocks)
        nxt = next(it, None)
        while nxt is not None:
            arrays, rows, nbytes, repeats, skipped, bad = nxt
            nxt = next(it, None)
            self.skipped += skipped
            self._add_bad(bad)
            if rows == 0:
                self.bytes += nbytes
                continue
            s, t, temp = _split_groups(lay, arrays)
            if nxt is None and self.cut_last is not None:  # the last block: its last row
                s, t = s[:-1], None if t is None else t[:-1]
                temp = None if temp is None else temp[:-1]
            s, t, temp = self._drop_untimed(s, t, temp, parsed)
            if s.shape[0] < rows:
                parsed += rows - s.shape[0]
                rows = s.shape[0]
                if rows == 0:
                    self.bytes += nbytes
                    continue
            temp = self._hold_temperature(temp, parsed)
            if t is None and lay.fs is not None:
                t = np.arange(parsed, parsed + rows, dtype=np.float64) / lay.fs
            elif self._unwrap is not None and t is not None:
                t = self._unwrap(t, parsed)
            parsed += rows
            if self._last is not None and np.array_equal(self._last, s[0]):
                repeats += 1
            self._last = s[-1].copy()
            self.repeats += repeats
            self.bytes += nbytes
            if chunk_rows is None:
                self.rows += rows
                yield s, t, temp
            else:
                # Exactly chunk_rows rows per chunk (the last may be shorter).
                pending.append((s, t, temp))
                have += rows
                while have >= chunk_rows:
                    out, pending, have = _take(pending, chunk_rows, have)
                    self.rows += chunk_rows
                    yield out
            if progress is not None:
                progress(self.rows, self.bytes)
        if pending:
            out, pending, have = _take(pending, have, have)
            self.rows += out[0].shape[0]
            yield out
            if progress is not None:
                progress(self.rows, self.bytes)

    def read_all(
        self, progress: Callable[[int, int], None] | None = None
    ) -> tuple[NDArray[Any], NDArray[np.float64] | None, NDArray[np.float64] | None]:
        """All rows at once (one parallel pass for text)."""
        lay = self.lay
        if self.arrays is not None:
            src = self.arrays
            n = int(src.table.shape[0])
            try:
                s, t, temp = src.chunk(0, n)
            finally:
                if src.closer is not None:
                    src.closer()
            s, t, temp = self._drop_untimed(s, t, temp, 0)
            temp = self._hold_temperature(temp, 0)
            if isinstance(src.table, np.memmap):
                s = np.array(s)
            self._count_repeats(s)
            self.rows = n = s.shape[0]
            if t is None and lay.fs is not None:
                t = np.arange(n, dtype=np.float64) / lay.fs
            elif self._unwrap is not None and t is not None:
                t = self._unwrap(t, 0)
            return s, t, temp
        assert self.text is not None
        src_t = self.text
        try:
            arrays, rows, nbytes, repeats, skipped, bad = _core.text_read_all(
                None if (src_t.stdin or src_t.eof) else src_t.opened,
                lay.offset,
                lay.ncols,
                _text_groups(lay),
                rows_hint=int(1.05 * (self.rows_estimate() or 0)),
                progress=progress,
                **_text_kwargs(lay, src_t),
            )
        except CalibrationError as e:
            raise CalibrationError(f"{src_t.path}: {e}{_repeated_header_hint(str(e))}") from None
        self.rows, self.bytes, self.repeats, self.skipped = rows, nbytes, repeats, skipped
        self._add_bad(bad)
        s, t, temp = _split_groups(lay, arrays)
        if self.cut_last is not None and s.shape[0]:
            s, t = s[:-1], None if t is None else t[:-1]
            temp = None if temp is None else temp[:-1]
        s, t, temp = self._drop_untimed(s, t, temp, 0)
        rows = self.rows = s.shape[0]
        temp = self._hold_temperature(temp, 0)
        if t is None and lay.fs is not None:
            t = np.arange(rows, dtype=np.float64) / lay.fs
        elif self._unwrap is not None and t is not None:
            t = self._unwrap(t, 0)
        return s, t, temp

    def _hold_temperature(self, temp: NDArray[np.float64] | None,
                          row0: int) -> NDArray[np.float64] | None:
        """Fill the empty (NaN) fields of a sparse temperature column, rows ``row0`` on: each
        holds the last value before it; rows before the first value take that value."""
        if temp is None:
            return None
        empty = np.isnan(temp)
        if not empty.any():
            self._temp_last = float(temp[-1])
            return temp
        have = np.flatnonzero(~empty)
        first = self._temp_last
        if first is None:
            if have.size == 0:
                raise CalibrationError(
                    f"{self.path}: the temperature column {_label(self.lay, self.lay.temp or 0)}"
                    f" is empty in data rows {row0 + 1} to {row0 + temp.size}: too sparse to "
                    "follow; remove the column or fill it in")
            first = float(temp[have[0]])
        last_at = np.maximum.accumulate(np.where(empty, -1, np.arange(temp.size)))
        out = np.where(last_at >= 0, temp[np.maximum(last_at, 0)], first)
        self._temp_held += int(empty.sum())
        self._temp_last = float(out[-1])
        return out

    # -- what is known after reading
    def output_rate(self) -> float | None:
        """The sensor's own update rate, Hz, when many rows repeat the previous one."""
        if self.rows < 100 or self.repeats < _REPEAT_FRACTION * self.rows:
            return None
        if self.lay.fs is None:
            return math.nan
        return self.lay.fs * (self.rows - self.repeats) / self.rows

    def notes(self) -> list[str]:
        out = list(self.lay.notes)
        if self.fs is not None and self.fs < 1.0:  # below any dwell detector's reach
            hint = self.rate_hint()
            if hint:
                out.append(f"{hint} (at {self.fs:.4g} Hz no dwell can be detected)")
        if self._unwrap is not None and self.lay.time is not None:
            out += self._unwrap.notes(_label(self.lay, self.lay.time))
        elif self._unwrap is not None:
            out += self._unwrap.notes("t")
        if self.skipped:
            out.append(
                f"{self.skipped} rows with every accelerometer field empty were left out (rows "
                "of another sensor in a merged log)")
        if self.bad and self.first_bad is not None:
            line, what = self.first_bad
            if self._bad_hint is None:  # a pass over the file: once
                self._bad_hint = _left_out_hint(self.path, line, what)
            out.append(
                f"{self.bad} data row(s) that do not parse were left out (the first, line "
                f"{line}: {what}): {self._bad_hint}")
        if self.cut_last is not None:
            cut_at, text = self.cut_last
            at = "the last line" if cut_at is None else f"line {cut_at}, the last"
            out.append(
                f"1 data row was left out ({at}: {text[:60]!r}): the file's last line, cut "
                "off (no line end, its last field shorter than in the rows before): a file "
                "whose writing or copying stopped? The rows before it are read")
        if self.untimed and self.first_untimed is not None:
            where = self._untimed_line()
            label = (_label(self.lay, self.lay.time) if self.lay.time is not None
                     else repr(self.arrays.t_name) if self.arrays is not None else "t")
            first = (f"line {where[0]}: column {label} is {where[1]!r}" if where is not None
                     else f"data row {self.first_untimed + 1}: column {label}")
            out.append(
                f"{self.untimed} data row(s) whose time is not a number (NaN or infinite) "
                f"were left out (the first, {first}), as rows with an empty time field are")
        if self._temp_held and self.lay.temp is not None:
            out.append(
                f"the temperature column {_label(self.lay, self.lay.temp)} is empty in "
                f"{self._temp_held} of {self.rows} rows (written on some rows only): each "
                "empty row holds the last value before it (the first value before that)")
        if self.rows >= 100 and self.repeats >= _REPEAT_FRACTION * self.rows:
            frac = self.repeats / self.rows
            rate = self.output_rate()
            per = self.rows / max(self.rows - self.repeats, 1)
            if self.lay.time is None and rate is not None and math.isfinite(rate):
                out.append(
                    f"{frac:.0%} of the rows repeat the previous sample exactly: the sensor "
                    f"updates at about {rate:.4g} Hz and was read at {self.lay.fs:g} Hz "
                    f"(each value about {per:.2g} times); dwell statistics count every row, "
                    "so the noise of a dwell mean looks smaller than it is"
                )
            else:
                out.append(
                    f"{frac:.0%} of the rows repeat the previous sample exactly (each value "
                    f"about {per:.2g} times): the sensor was read faster than it updates"
                )
        return out

    def stream(
        self, s: NDArray[Any], t: NDArray[np.float64] | None, temp: NDArray[np.float64] | None
    ) -> Stream:
        lay = self.lay
        return Stream(
            s, t, lay.fs, dict(lay.metadata), _names_of(lay), self.path, temp,
            t0=lay.t0_text, fs_source=lay.fs_source, notes=self.notes(),
            repeats=self.repeats, output_rate_hz=self.output_rate(),
            sections=None if self.arrays is None else self.arrays.sections,
        )


# ---- public API -------------------------------------------------------------------------------
def read_stream(
    path: Any,
    *,
    columns: Any = None,
    fs: float | None = None,
    time_column: Any = None,
    progress: bool | None = False,
) -> Stream:
    """Read a recording as it is.

    Parameters
    ----------
    path : str, path-like, ``"-"``, DataFrame or array
        The file: ``.npy`` holds an (N, 3) or (N, >=3) array; ``.npz`` and HDF5 hold
        ``samples`` (or ``acc``, ``a``, ``data``), or separate 1-D ``ax``, ``ay``, ``az``
        arrays, and optionally ``t``, ``fs``, ``temperature``; anything else is read as
        delimited text (see the module docstring for the layout rules); ``"-"`` reads text
        from standard input. A pandas/polars DataFrame (or any object with the DataFrame
        interchange protocol) has its columns chosen by name as a text header would; an
        array (anything with ``__array__``) is an (N, 3) or (N, >=3) table.
    columns : 3 names or 0-based indices, or "ax,ay,az", optional
        The accelerometer x, y, z columns; chosen by name when omitted. A fourth names the
        temperature column (a file without a header cannot name it "temp...").
    fs : float, optional
        Sample rate in Hz; overrides the file's metadata and time column.
    time_column : name or 0-based index, optional
        The time column (s, or ms/us/ns when the name says so, or as given: ``"stamp [ms]"``,
        ``"0 [ns]"``); recognised by name (or by its ISO-8601 times) when omitted;
        ``"none"``: use no time column (then give ``fs``).
    progress : bool or None
        Show a progress bar (True), only when stderr is a terminal (None), or never (False).

    Returns
    -------
    Stream
        ``samples`` (N, 3), ``t`` (N,) s or None, ``fs`` Hz or None, ``metadata``, ``names``,
        ``path``, ``temperature`` (N,) or None, ``t0``, ``fs_source``, ``notes``.

    Raises
    ------
    CalibrationError
        Missing, unreadable, empty or non-numeric file (bad rows are named by line), or
        columns that cannot be chosen.
    """
    rec = _Recording(path, columns, fs, time_column)
    with _progress_bar(rec, "read", progress) as cb:
        s, t, temp = rec.read_all(cb)
    if rec.rows == 0:
        raise CalibrationError(f"{rec.path}: no data rows")
    return rec.stream(s, t, temp)


def iter_stream(
    path: Any,
    *,
    chunk_rows: int = 500_000,
    columns: Any = None,
    fs: float | None = None,
    time_column: Any = None,
) -> Iterator[tuple[NDArray[Any], NDArray[np.float64] | None]]:
    """Read a recording chunk by chunk without loading it whole.

    Same layout rules and arguments as :func:`read_stream`. Text is parsed ahead on a
    background thread; ``.npy`` files are memory-mapped and HDF5 datasets read by slices;
    ``.npz`` files are loaded whole (the format cannot be streamed).

    Yields
    ------
    samples : (m, 3) array
        At most ``chunk_rows`` rows; concatenated, the chunks equal ``read_stream(path).samples``.
    t : (m,) float64 or None
        Sample times in s (time column, else from ``fs``; None when neither is known).
    """
    cr = _chunk_rows(chunk_rows)
    rec = _Recording(path, columns, fs, time_column)
    for s, t, _temp in rec.chunks(cr):
        yield s, t


def _chunk_rows(chunk_rows: Any) -> int:
    if (
        not isinstance(chunk_rows, (int, np.integer))
        or isinstance(chunk_rows, bool)
        or chunk_rows < 1
    ):
        raise CalibrationError(f"chunk_rows must be a positive integer; got {chunk_rows!r}")
    return int(chunk_rows)


class _progress_bar:  # noqa: N801 (a context manager used like a function)
    """A tqdm bar over rows with total, percentage and ETA (the total estimated from the
    file size and refined as bytes are read); ``callback(rows, bytes)`` updates it."""

    def __init__(self, rec: _Recording, desc: str, progress: bool | None) -> None:
        self.rec = rec
        self.desc = desc
        self.disable: bool | None = True if progress is False else (
            None if progress is None else False)
        self.bar: Any = None

    def __enter__(self) -> Callable[[int, int], None] | None:
        if self.disable is True:
            return None
        from tqdm import tqdm

        self.bar = tqdm(
            total=self.rec.rows_estimate(), unit=" rows", unit_scale=True,
            desc=f"{self.desc} {os.path.basename(self.rec.path)}", disable=self.disable,
            leave=False, dynamic_ncols=True,
        )
        return self.update

    def update(self, rows: int, nbytes: int) -> None:
        bar = self.bar
        size = self.rec.size_bytes
        if size and nbytes:
            est = int(rows * (size - self.rec.lay.offset) / nbytes)
            if bar.total != est:
                bar.total = max(est, rows)
        bar.update(rows - bar.n)

    def __exit__(self, *exc: Any) -> None:
        if self.bar is not None:
            if exc[0] is None:
                self.bar.total = self.bar.n
                self.bar.refresh()
            self.bar.close()


def stream_dwells(
    path: Any,
    *,
    fs: float | None = None,
    bounds: Any = None,
    columns: Any = None,
    time_column: Any = None,
    chunk_rows: int = 500_000,
    units: str = "",
    progress: bool | None = False,
    means: bool | None = False,
    count: int | None = None,
    **detector_kw: Any,
) -> Any:
    """Dwell statistics of a (large) recording, streamed chunk by chunk in one pass.

    ``progress``: show a progress bar of rows read (True), only when stderr is a terminal
    (None), or never (False, the default for library use).

    With ``bounds`` (k, 2), or the path of a bounds file (:func:`read_bounds`: JSON or CSV,
    imucal's session list too), the given ``[start, stop)`` dwells are accumulated; otherwise the
    static intervals are detected (needs ``fs`` from the argument, the file's metadata or its
    time column; ``detector_kw`` are :class:`~accelcal.DetectorSettings` fields). Memory use is
    a few blocks of text plus compressed block statistics. The result equals
    :func:`~accelcal.dwell_stats` / :func:`~accelcal.detect_dwells` on ``read_stream(path)``
    with the same ``t`` and ``temperature`` channels.

    ``means=True`` reads a table of dwell means instead (:func:`read_means`: one pose per
    row); ``means=None`` does so only when the rate is unknown and the rows look like poses
    (what the command line does, with a note), and reads samples otherwise. ``count``: the
    samples behind each mean, for a table with per-pose std columns but no count column.

    Returns
    -------
    DwellSet
    """
    d, _rec = _stream_dwells(path, fs=fs, bounds=bounds, columns=columns,
                             time_column=time_column, chunk_rows=chunk_rows, units=units,
                             progress=progress, means=means, count=count, **detector_kw)
    return d


def read_means(path: Any, *, columns: Any = None, units: str = "",
               count: int | None = None) -> Any:
    """A table of dwell means, one pose per row, as a :class:`~accelcal.DwellSet` (what a
    logger or firmware that averages each pose writes, or a spreadsheet of pose means): any
    format :func:`read_stream` reads, columns by name as for samples, or ``x_mean`` /
    ``mean_x`` / ``acc_x_avg``... (a column of the reference attitude, ``x_true``, is not
    taken). Per-pose sample std columns (``x_std``...) with a count column (``n``,
    ``count``) give each mean its noise (std / sqrt(count)); otherwise the fit estimates
    the noise level from the residuals. A time column, if any, gives each dwell's time and a
    ``temp...`` column its temperature. Rows with NaN are refused, naming them.

    ``count``: the samples averaged into each mean, for a table whose std columns come without
    a count column (a logger that averages a fixed number of samples per pose).
    """
    rec = _Recording(path, columns, None, None)
    d = pose_table(rec, units, forced=True, count=count)
    assert d is not None
    return d


# ---- known dwells ------------------------------------------------------------------------------
#: Section names that are not static (imucal's x_rot ...; moves between poses).
_MOVING = re.compile(r"(?:^|[^a-z])(?:rot|rotation|rotations|move|moving|transition)(?:$|[^a-z])")
_START_KEYS = ("start", "begin", "from", "first")
_STOP_KEYS = ("stop", "end", "to", "last")


@dataclass
class Bounds:
    """Known dwells read by :func:`read_bounds`: ``values`` (k, 2) ``[start, stop)`` in rows
    of the stream, or in seconds from its first sample when ``seconds``; ``names`` of the
    sections when the file names them; ``notes`` on what was left out."""

    values: NDArray[np.float64]
    seconds: bool = False
    names: list[str] | None = None
    notes: list[str] = field(default_factory=list)
    path: str = ""

    def rows(self, fs: float | None) -> NDArray[np.int64]:
        """``[start, stop)`` as rows (seconds times the sample rate, rounded)."""
        if not self.seconds:
            return self.values.astype(np.int64)
        if fs is None:
            raise CalibrationError(f"{self.path}: the dwell bounds are in seconds, so the "
                                   "sample rate is needed: give fs= (Hz)")
        return np.rint(self.values * fs).astype(np.int64)


def read_bounds(path: str | os.PathLike[str]) -> Bounds:
    """Known dwells from a file, for when a test sequencer or a marker log says where the
    static poses are (instead of detecting them).

    - JSON: a list of ``[start, stop]`` pairs, or of objects; or an object whose entries are
      named sections ``{"x_p": {"start": 540, "end": 1271}, ...}`` (imucal's session list) or
      pairs. ``start``/``stop`` (or ``end``) are rows of the stream (``[start, stop)``);
      ``start_s``/``stop_s`` are seconds from its first sample.
    - CSV (comma, semicolon, tab or spaces; ``#`` comments): columns named ``start`` and
      ``stop``/``end`` (rows) or ``start_s`` and ``stop_s``/``end_s`` (seconds), and any
      text column as the section name; without a header, the first two columns are rows.

    Sections named as motions (``x_rot``, ``rotation``, ``move``, ``transition``) are left
    out, with a note: they are not static.
    """
    import json

    from ._files import read_small_text

    p = os.fspath(path)
    try:
        # a device (/dev/urandom) or a file of more than 64 MB refused, not read without end
        text = read_small_text(p, "the bounds file")
    except FileNotFoundError:
        raise CalibrationError(f"bounds file not found: {p}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise CalibrationError(f"cannot read the bounds file {p}: {e}") from None
    if text.lstrip().startswith(("{", "[")):
        try:
            obj = json.loads(text)
        except ValueError as e:
            raise CalibrationError(f"{p}: not valid JSON: {e}") from None
        entries = _bounds_json_entries(obj, p)
    else:
        entries = _bounds_csv_entries(text, p)
    return _bounds_from_entries(entries, p)


def _pair(d: dict[str, Any], p: str, where: str) -> tuple[Any, Any, bool]:
    """``(start, stop, seconds)`` of one JSON object."""
    low = {str(k).strip().lower(): v for k, v in d.items()}
    for suffix, seconds in (("", False), ("_s", True)):
        a = next((low[k + suffix] for k in _START_KEYS if k + suffix in low), None)
        b = next((low[k + suffix] for k in _STOP_KEYS if k + suffix in low), None)
        if a is not None and b is not None:
            return a, b, seconds
    raise CalibrationError(f"{p}: {where} has no start and stop (or end): keys {sorted(low)}")


def _bounds_json_entries(obj: Any, p: str) -> list[tuple[str | None, Any, Any, bool]]:
    if isinstance(obj, dict) and isinstance(obj.get("bounds"), (list, dict)):
        obj = obj["bounds"]
    items = list(obj.items()) if isinstance(obj, dict) else (
        [(None, v) for v in obj] if isinstance(obj, list) else None)
    if items is None:
        raise CalibrationError(f"{p}: dwell bounds must be a list or an object of sections")
    out: list[tuple[str | None, Any, Any, bool]] = []
    for i, (name, v) in enumerate(items):
        where = f"section {name!r}" if name is not None else f"entry {i}"
        if isinstance(v, dict):
            a, b, sec = _pair(v, p, where)
            out.append((name if name is not None else v.get("name"), a, b, sec))
        elif isinstance(v, (list, tuple)) and len(v) == 2:
            out.append((name, v[0], v[1], False))
        else:
            raise CalibrationError(f"{p}: {where} is not a [start, stop] pair or an object "
                                   f"with start and stop: {v!r}")
    return out


def _bounds_csv_entries(text: str, p: str) -> list[tuple[str | None, Any, Any, bool]]:
    import csv

    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise CalibrationError(f"{p}: no dwell bounds in the file")
    delim = _guess_delim(lines[0])
    rows = ([r for r in csv.reader(lines, delimiter=delim)] if delim else
            [ln.split() for ln in lines])
    rows = [[f.strip() for f in r] for r in rows]
    head = [f.lower() for f in rows[0]]
    if all(_is_number(f) for f in rows[0] if f):
        ia, ib, iname, sec, body = 0, 1, None, False, rows
        if len(rows) == 2 and len(rows[0]) >= 3 and len(rows[1]) == len(rows[0]):
            # Two rows of k >= 3 numbers: the starts, then the stops (a (2, k) array saved
            # as it is, as numpy's savetxt writes it), one dwell per column.
            body = [list(c) for c in zip(rows[0], rows[1], strict=True)]
    else:
        body = rows[1:]
        found = None
        for suffix, unit_s in (("", False), ("_s", True)):
            a = next((head.index(k + suffix) for k in _START_KEYS if k + suffix in head), None)
            b = next((head.index(k + suffix) for k in _STOP_KEYS if k + suffix in head), None)
            if a is not None and b is not None:
                found = (a, b, unit_s)
                break
        if found is None:
            raise CalibrationError(f"{p}: the header {rows[0]} names no start and stop (or "
                                   "end) columns (rows), nor start_s and stop_s (seconds)")
        ia, ib, sec = found
        iname = next((j for j, f in enumerate(body[0] if body else []) if j not in (ia, ib)
                      and f and not _is_number(f)), None)
    out: list[tuple[str | None, Any, Any, bool]] = []
    for r in body:
        if max(ia, ib) >= len(r):
            raise CalibrationError(f"{p}: the row {r} has no start and stop")
        out.append((r[iname] if iname is not None and iname < len(r) else None,
                    r[ia], r[ib], sec))
    return out


def _bounds_from_entries(entries: list[tuple[str | None, Any, Any, bool]], p: str) -> Bounds:
    kept, names, moving = [], [], []
    secs = {e[3] for e in entries}
    if len(secs) > 1:
        raise CalibrationError(f"{p}: some bounds are in rows and some in seconds")
    for name, a, b, sec in entries:
        if name is not None and _MOVING.search(str(name).lower()):
            moving.append(str(name))
            continue
        try:
            va, vb = float(a), float(b)
        except (TypeError, ValueError):
            raise CalibrationError(f"{p}: section {name!r}: start and stop must be numbers; "
                                   f"got {a!r}, {b!r}") from None
        if not sec and not (va.is_integer() and vb.is_integer()):
            raise CalibrationError(f"{p}: section {name!r}: rows must be whole numbers; got "
                                   f"{a!r}, {b!r} (for seconds, name them start_s and stop_s)")
        kept.append((va, vb))
        names.append(None if name is None else str(name))
    if not kept:
        raise CalibrationError(f"{p}: no static sections in the bounds file"
                               + (f" (left out as motions: {', '.join(moving)})" if moving else ""))
    notes = [f"dwell bounds from {os.path.basename(p)}: {len(kept)} sections"
             + (f"; left out as motions, not static: {', '.join(moving)}" if moving else "")]
    named = [n or "" for n in names] if any(n is not None for n in names) else None
    return Bounds(np.array(kept, dtype=np.float64), seconds=secs == {True}, names=named,
                  notes=notes, path=p)


def _stream_dwells(
    path: Any,
    *,
    fs: float | None = None,
    bounds: Any = None,
    columns: Any = None,
    time_column: Any = None,
    chunk_rows: int | None = None,
    units: str = "",
    progress: bool | None = False,
    desc: str = "dwells",
    means: bool | None = False,
    count: int | None = None,
    **detector_kw: Any,
) -> tuple[Any, _Recording]:
    """:func:`stream_dwells` that also returns the opened recording (rows, notes)."""
    cr = None if chunk_rows is None else _chunk_rows(chunk_rows)
    if means and bounds is not None:
        raise CalibrationError("give dwell bounds or read the file as a table of dwell means "
                               "(one pose per row), not both")
    rec = _Recording(path, columns, fs, time_column)
    if count is not None and means is False:
        raise CalibrationError("count= (samples per pose's mean) is for a table of dwell "
                               "means: give means=True too")
    slow = too_slow_for_detection(rec.fs, detector_kw.get("window_s"))
    annotated = rec.arrays is not None and rec.arrays.sections is not None
    if bounds is None and not annotated and not means and count is None and _rests_only(rec):
        # A log that holds only the rests (a block of samples per pose): its runs between
        # jumps are the dwells, whatever the window and the rate (read whole: such logs are
        # small).
        with _progress_bar(rec, desc, progress) as cb:
            s, t, temp = rec.read_all(cb)
        got = step_log_dwells(s, t, temp, rec.fs, units)
        if got is not None:
            d, note = got
            rec.lay.notes[:] = [n for n in rec.lay.notes if not n.startswith(NO_RATE_NOTE)]
            rec.lay.notes.append(note)
            rec.lay.notes += uneven_runs_note(d)
            if rec.fs is None:
                clock = rec.clock_hint()
                rec.lay.notes.append(f"{NO_RATE_NOTE}: the dwells do not need it here, their "
                                     "times do (the time tests of diagnose): give fs= (Hz)"
                                     + (f"; or, {clock}" if clock else ""))
            return d, rec
        rec = _Recording(path, columns, fs, time_column)  # its head only: detect as ever
    if means or (means is None and bounds is None and not annotated
                 and (rec.fs is None or slow)):

        d = pose_table(rec, units, forced=bool(means), count=count)
        if d is not None:
            rec.pose_table = True
            rec.lay.notes[:] = [n for n in rec.lay.notes if not n.startswith(_COARSE_TIME_NOTE)]
            return d, rec
        if rec.rows and not slow:  # read, and not poses: the rate is unknown
            raise CalibrationError(rec.no_rate())
        if rec.rows:  # read, and not poses: the detector's own error, from a fresh reader
            rec = _Recording(path, columns, fs, time_column)
    if count is not None:
        raise CalibrationError(f"{rec.path}: count= is for a table of dwell means, and this "
                               "file is read as samples (give means=True to read it as one)")
    if isinstance(bounds, (str, os.PathLike)):
        bounds = read_bounds(bounds)
    if bounds is None and rec.arrays is not None and rec.arrays.sections is not None:
        bounds = rec.arrays.sections  # an annotated session's labelled static sections
    known = bounds.path if isinstance(bounds, Bounds) else None  # named in its errors
    if rec.text is not None:
        # Text arrives in blocks of a few MB already: pushed as they come (the result does
        # not depend on the chunking), with no copy into chunks of exactly chunk_rows rows.
        cr = None
    try:
        acc = rec.dwell_accumulator(bounds, units, **detector_kw)
        with _progress_bar(rec, desc, progress) as cb:
            for s, t, temp in rec.chunks(cr, cb):
                acc.push(s, t, temp)
        if rec.rows == 0:
            raise CalibrationError(f"{rec.path}: no data rows")
        d = _named_dwells(acc.finish(), bounds)
        if bounds is not None:
            rec.lay.notes += _short_dwells(d)
        return d, rec
    except CalibrationError as e:
        if known is None or str(e).startswith(rec.path):
            raise  # not about the bounds
        raise type(e)(f"{known} (dwell bounds of {rec.path}): {e}") from None


#: Largest recording read whole to test it as a log of rests (rows; the test's scratch
#: memory is about 40 bytes a row).
_STEP_LOG_MAX_ROWS = 5_000_000


def _rests_only(rec: _Recording) -> bool:
    """Whether the head of ``rec`` reads as a log that holds only the rests (see
    :func:`step_log_dwells`), and the recording is small enough to read whole and can be
    read again (not standard input) should the whole not read so."""
    lay = rec.lay
    if rec.text is not None and rec.text.stdin:
        return False  # read once only: a head that misleads could not be read again
    est = rec.rows_estimate()
    if len(lay.acc) != 3 or lay.head.shape[0] == 0 or (est or 0) > _STEP_LOG_MAX_ROWS:
        return False
    h = lay.head[:, list(lay.acc)]
    h = _signed16(h) if lay.signed16 else h
    return _core.dwell_step_log(np.ascontiguousarray(h, dtype=np.float64)) is not None


def step_log_dwells(samples: Any, t: Any, temperature: Any, fs: float | None, units: str = ""
                    ) -> tuple[Any, str] | None:
    """A recording that holds only the rests - a logger that stores a block of samples per
    pose and nothing while the sensor is turned, so consecutive poses meet in a jump between
    two samples - as dwells: the runs between its jumps (``_core.dwell_step_log``), with the
    note that says so. None when it does not read as such a log (its moves are recorded, or
    it has fewer than 5 jumps; a recording longer than 5 million rows is not tested)."""
    from .dwell import dwell_stats

    n = len(samples)
    if n > _STEP_LOG_MAX_ROWS or (
            n > _SNIFF_ROWS and _core.dwell_step_log(samples[:_SNIFF_ROWS]) is None):
        return None  # its head says no (or too long for such a log): no pass over it all
    log = _core.dwell_step_log(samples)
    if log is None:
        return None
    # The reader noted what the clock did (steps back, gaps): not checked again here.
    d = dwell_stats(samples, log.runs, t=t, temperature=temperature, fs=fs, units=units,
                    check_times=False)
    k = len(log.runs)
    block = "a block of" if log.period is None else f"{log.period}"
    cut = k - log.jumps - 1
    note = (f"the recording holds only the rests: {log.jumps} jumps between runs of still "
            f"samples, with no motion recorded between them (a logger that stores {block} "
            f"samples per pose); its {k} runs are the dwells")
    if cut > 0:
        note += (f", {cut} of them cut on the logger's grid of blocks (poses too close for a "
                 "jump between them)")
    return d, note


#: A run of a log of rests whose sample variance on an axis is more than this many times
#: the median of the other runs' on that axis is named in a note (std 3x the others').
_UNEVEN_RUN_VAR = 9.0


def uneven_runs_note(d: Any) -> list[str]:
    """For dwells taken whole (the runs of a log that holds only the rests, see
    :func:`step_log_dwells`): a note on the run whose sample variance on some axis is more
    than ``_UNEVEN_RUN_VAR`` (9) times the median of the other runs' on that axis (a bump or
    a turn begun within the run, which is in its mean), naming the run and the axis, and how
    many other runs are so; ``[]`` otherwise (and for fewer than 3 runs). It only says so:
    the samples used stay the same."""
    var = None if d.var is None else np.asarray(d.var, dtype=np.float64)
    if var is None or var.ndim != 2 or var.shape[0] < 3:
        return []
    found: list[tuple[float, int, int, float]] = []  # (ratio, run, axis, others' median)
    for ax in range(var.shape[1]):
        v = var[:, ax]
        for i in range(v.size):
            rest = np.delete(v, i)
            rest = rest[np.isfinite(rest)]
            med = float(np.median(rest)) if rest.size else math.nan
            if med > 0 and math.isfinite(v[i]) and v[i] > _UNEVEN_RUN_VAR * med:
                found.append((float(v[i]) / med, i, ax, med))
    if not found:
        return []
    r, i, ax, med = max(found)
    units = getattr(d, "units", "")
    unit, of = (f" {units}", "") if units else ("", ", std in the file's units")
    rows = ""
    if d.start is not None and d.stop is not None:
        rows = f" (start {int(d.start[i])}, stop {int(d.stop[i])})"
    more = len({run for _, run, _, _ in found} - {i})
    also = f" ({more} other run(s) too)" if more else ""
    return [f"dwell {d.label(i)}{rows} varies far more than the other runs on {'xyz'[ax]}"
            f"{also}: sample std {math.sqrt(float(var[i, ax])):.3g}{unit} against a median "
            f"{math.sqrt(med):.3g}{unit} over the others ({r:.3g}x the variance{of}); each "
            "run is taken whole, so a bump or a turn within it is in its mean: look at the "
            "dwells plot and, if so, give the rows to keep as dwell bounds (bounds=)"]


def _short_dwells(d: Any) -> list[str]:
    """A note on given dwells of fewer than ``FAULT_MIN_SAMPLES`` (30, the Rust core's
    fewest for a variance the output-fault checks trust): their variances say little about
    the noise (a variance from 2 samples is off by a factor of 10 one time in 6)."""
    least = _core.FAULT_MIN_SAMPLES
    short = [i for i, c in enumerate(np.asarray(d.count)) if c < least]
    if not short:
        return []
    which = ", ".join(f"dwell {d.label(i)}: {int(d.count[i])} samples" for i in short[:6])
    return [f"{len(short)} of the given dwells hold fewer than {least} samples ({which}"
            f"{' ...' if len(short) > 6 else ''}): their variances say little about the "
            "noise, so a chi2 against them says little either"]


def _named_dwells(d: Any, bounds: Any) -> Any:
    """``d`` with the names of a bounds file's sections (one per dwell, in its order)."""
    if isinstance(bounds, Bounds) and bounds.names is not None and len(bounds.names) == len(d):
        d.names = list(bounds.names)
    return d


def open_recording(
    path: Any, *, columns: Any = None, fs: float | None = None, time_column: Any = None
) -> Any:
    """Open a recording for one streaming pass (internal: used by the command line).

    Returns an object with ``fs``, ``path``, ``chunks(chunk_rows, progress)``, ``read_all``,
    ``rows``, ``notes()`` and ``rows_estimate()``.
    """
    return _Recording(path, columns, fs, time_column)

