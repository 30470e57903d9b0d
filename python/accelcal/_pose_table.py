"""Tables of dwell means: one row per pose, as written by a logger or a firmware that averages
each pose itself (an Arduino sketch printing the mean of each pose, a lab's spreadsheet of
pose means). Such a file has no sample rate and no stream to detect dwells in: each row is a
dwell. :func:`~accelcal.io.read_means` reads one on purpose; the command line also takes a
file for one when its rate is unknown and its rows look like poses (:func:`looks_like_poses`),
and says so.
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ._core import CalibrationError

if TYPE_CHECKING:
    from .dwell import DwellSet
    from .io import _Recording

#: The most rows a file may have to be taken for a table of dwell means without being asked
#: (a session of more poses than this is not hand-placed).
POSE_TABLE_ROWS = 2000
#: Consecutive rows of a pose table differ by about the radius of the sphere the poses lie
#: on; consecutive samples of a stream mostly differ by the noise. A file is taken for poses
#: when the median step between consecutive rows is above this fraction of the rows' median
#: distance from their median point.
POSE_STEP = 0.5
#: At least this many rows make a pose table.
POSE_MIN_ROWS = 6
#: The rows' median distance from their median point must exceed this fraction of that
#: point's distance from zero (poses spread by about g; a raw ADC's offset is a few g at most, while
#: the noise of one pose is a per cent of g or less).
POSE_SPREAD = 0.03

_AXIS = r"(?:a|ac|acc|accl|accel|acceleration|accelerometer)?([xyz])"
_MEAN = r"(?:mean|avg|average|mu)"
_STD = r"(?:std|sd|sigma|stdev|stddev|stdv)"
_UNIT = r"(?:g|mg|ms2|mps2|mss|si|raw|counts|lsb|adc)?"
#: A dwell mean's column after ``io._norm`` (``x_mean (g)``, ``mean_x``, ``acc_x_avg``).
MEAN_NAME = re.compile(rf"^(?:{_MEAN}{_AXIS}|{_AXIS}{_MEAN}){_UNIT}$")
#: A per-dwell sample std's column (``x_std``, ``std_ax``, ``sigma_z``).
STD_NAME = re.compile(rf"^(?:{_STD}{_AXIS}|{_AXIS}{_STD}){_UNIT}$")
#: A per-dwell sample count's column.
COUNT_NAMES = {"n", "count", "nsamples", "numsamples", "samplecount", "samples", "npoints",
               "npts", "nsample", "num"}


def too_slow_for_detection(fs: float | None, window_s: float | None = None) -> bool:
    """Whether a rate ``fs`` (Hz) gives the dwell detector's window (``window_s``, default
    :class:`~accelcal.DetectorSettings`'s) fewer than the 8 samples the detector needs
    (``MIN_WINDOW_SAMPLES`` of the Rust core): a time column with one row per pose, at
    best."""
    from . import _core
    from .dwell import DetectorSettings

    w = DetectorSettings().window_s if window_s is None else float(window_s)
    return fs is not None and fs * w < _core.MIN_WINDOW_SAMPLES


def looks_like_poses(s: NDArray[np.float64]) -> bool:
    """Whether the rows ``s`` (n, 3) read as one mean per pose rather than as samples: a
    few (``POSE_MIN_ROWS`` to ``POSE_TABLE_ROWS``) finite rows, nearly every one a step to
    another attitude (median step between consecutive rows above ``POSE_STEP`` times the
    median distance from the median point), spread over three directions by about g
    (``POSE_SPREAD``)."""
    n = s.shape[0]
    if not POSE_MIN_ROWS <= n <= POSE_TABLE_ROWS or not np.all(np.isfinite(s)):
        return False
    centred = s - np.median(s, axis=0)
    radius = float(np.median(np.linalg.norm(centred, axis=1)))
    steps = np.linalg.norm(np.diff(s, axis=0), axis=1)
    if not radius > 0 or not float(np.median(steps)) > POSE_STEP * radius:
        return False
    # Poses span the sphere (an ellipsoid): the centred rows have three clear directions,
    # and their spread is of the order of gravity. A stream of one pose is noise round one
    # point: its spread is tiny against that point's distance from zero.
    sv = np.linalg.svd(centred - centred.mean(axis=0), compute_uv=False)
    offset = float(np.linalg.norm(np.median(s, axis=0)))
    return bool(sv[2] > 0.05 * sv[0] and radius > POSE_SPREAD * offset)


def _named(names: tuple[str, ...] | None, pattern: re.Pattern[str]) -> list[int] | None:
    """The x, y, z columns whose names match ``pattern`` (axis in a group), or None."""
    from .io import _norm

    if names is None:
        return None
    found: dict[str, list[int]] = {"x": [], "y": [], "z": []}
    for i, n in enumerate(names):
        m = pattern.match(_norm(n))
        if m:
            found[next(g for g in m.groups() if g)].append(i)
    if all(len(v) == 1 for v in found.values()):
        return [found["x"][0], found["y"][0], found["z"][0]]
    return None


def _whole_columns(rec: _Recording, idx: list[int]) -> NDArray[np.float64] | None:
    """Columns ``idx`` of the whole table, when the reader holds them already (a text file
    read in its head, an array source), else None."""
    from .io import _Columns

    if rec.arrays is not None:
        tab = rec.arrays.table
        n = int(tab.shape[0])
        if isinstance(tab, _Columns):
            return np.asarray(tab.rows(0, n, idx), dtype=np.float64)
        return np.asarray(np.asarray(tab[0:n])[:, idx], dtype=np.float64)
    head = rec.lay.head
    if rec.text is not None and rec.text.eof and head.shape[0] == rec.rows:
        return np.asarray(head[:, idx], dtype=np.float64)
    return None


def pose_table(rec: _Recording, units: str = "", forced: bool = True,
               count: int | None = None) -> DwellSet | None:
    """The rows of ``rec`` as dwell means (a :class:`~accelcal.DwellSet` with one dwell per
    row), with a note saying so. Unless ``forced``, only when the rows look like poses
    (:func:`looks_like_poses`); None otherwise (the recording is then read).

    Per-pose std columns (``x_std`` ...) with a sample-count column (``n``, ``count``) give
    each mean its white-noise variance; std columns alone are left out with a note (they
    give no standard error without the count), unless ``count`` gives the samples behind
    every mean.
    """
    from .dwell import DwellSet
    from .io import NO_RATE_NOTE, _norm

    if not forced:
        est = rec.rows_estimate()
        if est is None or est > 2 * POSE_TABLE_ROWS:
            return None
    names = rec.lay.names
    std_cols = _named(names, STD_NAME)
    count_col = None if names is None else next(
        (i for i, n in enumerate(names) if _norm(n) in COUNT_NAMES), None)
    given = count
    if given is not None:
        if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
            raise CalibrationError(f"count must be a whole number of samples >= 1; got "
                                   f"{count!r}")
        if not std_cols:
            raise CalibrationError(
                f"{rec.path}: count= gives the samples behind each mean's std, but the table "
                "has no per-pose std columns (x_std, y_std, z_std): the noise of a mean needs "
                "the samples' std as well as their number. Add those columns (the logger's "
                "std of each pose's samples), or read the table without count= (the noise is "
                "then estimated from the residuals, and the gap is judged by F tests only); "
                "from Python, DwellSet(mean, var=std**2, count=n) gives it directly")
        if count_col is not None:
            raise CalibrationError(f"{rec.path}: count= conflicts with the table's own count "
                                   f"column {names[count_col]!r}")  # type: ignore[index]
    extra_idx = (std_cols or []) + ([count_col] if count_col is not None else [])
    extra = _whole_columns(rec, extra_idx) if extra_idx and rec.arrays is not None else None
    s, t, temp = rec.read_all()
    s = np.asarray(s, dtype=np.float64)
    n = s.shape[0]
    if not forced and not looks_like_poses(s):
        return None
    if n == 0:
        raise CalibrationError(f"{rec.path}: no data rows")
    bad = np.flatnonzero(~np.all(np.isfinite(s), axis=1))
    if bad.size:
        rows = ", ".join(str(int(r) + 1) for r in bad[:5]) + (" ..." if bad.size > 5 else "")
        raise CalibrationError(
            f"{rec.path}: read as a table of dwell means, but data row(s) {rows} (1-based) "
            "hold NaN or inf: a pose's mean must be a number on every axis")
    if extra_idx and extra is None:
        extra = _whole_columns(rec, extra_idx)
    notes = rec.lay.notes
    # Each row is a dwell: no rate is needed, so the reader's note asking for one goes.
    notes[:] = [n for n in notes if not n.startswith(NO_RATE_NOTE)]
    fs = rec.fs
    how = "as asked" if forced else (
        ("its rate is unknown" if fs is None else
         f"its rate, {fs:.4g} Hz, is too low for a stream of samples")
        + " and its rows step from attitude to attitude; give the sample rate (fs) to read "
        "it as samples instead")
    notes.append(f"read as a table of dwell means, one pose per row ({n} rows; {how})")
    var = counts = None
    label = [names[j] for j in std_cols] if names is not None and std_cols else []
    if std_cols and given is not None and extra is not None:
        extra = np.column_stack([extra[:, :3], np.full(n, float(given))])
    if std_cols and (count_col is not None or given is not None) and extra is not None:
        std, cnt = extra[:, :3], extra[:, 3]
        said = (f"count ({names[count_col]!r})" if count_col is not None  # type: ignore[index]
                else f"the {given} samples per pose given by count=")
        if np.all(np.isfinite(std)) and np.all(std >= 0) and np.all(cnt >= 1) and np.all(
                cnt == np.round(cnt)):
            var, counts = std * std, cnt.astype(np.int64)
            notes.append(f"each mean's noise from its sample std ({', '.join(label)}) and "
                         f"{said}: std / sqrt(count)")
        else:
            notes.append(f"the std columns ({', '.join(label)}) with {said} are not all valid "
                         "(std >= 0, whole counts >= 1): not used; the noise is estimated "
                         "from the fit")
    elif std_cols:
        notes.append(f"the per-pose std columns ({', '.join(label)}) are not used: without a "
                     "sample count (a column n or count, or count= for all poses) they give "
                     "no standard error of the means; the noise level is estimated from the "
                     "fit")
    unused = _unused_columns(rec, std_cols or [], count_col)
    if unused:
        notes.append(
            f"column(s) {', '.join(repr(c) for c in unused)} of the table are not used: a "
            "per-pose std is read from columns named like x_std, std_x or sigma_z (with a "
            "count column n or count), a temperature from one whose name starts with temp")
    labels = None if rec.arrays is None else rec.arrays.labels
    if labels is not None and len(labels) != n:
        labels = None
    return DwellSet(s, var, counts, t=t, temperature=temp, units=units, names=labels)


def _unused_columns(rec: _Recording, std_cols: list[int], count_col: int | None) -> list[str]:
    """Names of a pose table's columns that nothing reads (not the means, the time, the
    temperature, a per-pose std or the count), other sensors' (gyroscope, magnetometer,
    pressure) aside."""
    lay = rec.lay
    if lay.names is None:
        return []
    used = set(lay.acc) | set(std_cols)
    used |= {c for c in (lay.time, lay.temp, count_col) if c is not None}
    other_sensor = re.compile(r"gyr|mag|baro|press|rate")  # another sensor's: not ours to read
    return [str(lay.names[i]) for i in range(len(lay.names))
            if i not in used and not other_sensor.search(str(lay.names[i]).lower())]
