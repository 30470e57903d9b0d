"""Per-dwell statistics of high-rate accelerometer streams (numerics in Rust).

Non-finite samples (NaN or inf)
    With explicit bounds (:func:`dwell_stats`, ``DwellAccumulator(bounds)``) a dwell that
    contains one is refused: the error names the dwell, how many rows are bad and the first
    one. Automatic detection (:func:`detect_dwells`, ``DwellAccumulator(fs=...)``) treats a
    row with one as a dropout: the row is left out of the stream the detector and the dwell
    statistics see (a dropout inside a dwell neither splits it nor enters its mean; a logger
    that writes NaN for each missed sample still gives whole dwells), ``DwellSet.start`` and
    ``stop`` still count the rows of the stream as given, and ``DwellSet.dropped`` counts the
    rows left out. The time and temperature channels of the rows kept must be finite.

Sample times ``t`` (s)
    Checked against the sample rate where both are given (:func:`detect_dwells`,
    :func:`dwell_stats` with ``fs``, :meth:`DwellAccumulator.push` with ``fs``): when most
    intervals between the times are over :data:`CLOCK_RATIO` sample intervals ``1 / fs`` and
    so is their mean (or both under ``1 / CLOCK_RATIO`` of one), a CalibrationError names
    both and the likely unit (t in ms, us or ns read as s). Times that never advance (all
    equal), or step back more often than forward, are refused with or without ``fs``; float16
    or float32 times too coarse for ``fs`` at their magnitude (epoch seconds in float32 step
    by 128 s) are refused saying so. A time that steps back now and then (a clock reset, files
    joined), or jumps forward by over 100 sample intervals and 1 s (a clock step, samples
    missing), is kept as given with a :class:`TimeStepWarning`, as
    :func:`accelcal.io.read_stream` keeps it with a note; a second one names the dwells that
    span such a step (their time is on neither clock). The
    checks wait for 16 intervals, and those of a clock that does not advance (or runs slow)
    for rows spanning 10 s at ``fs`` (stamps in whole seconds, jittered bursts: a stream
    pushed a row at a time is judged as one call); a :class:`~accelcal.io.Stream`'s own
    ``t`` is not checked again (read_stream notes what it found), and ``check_times=False``
    takes ``t`` as given.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import statistics
import threading
import warnings
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._core import CalibrationError
from ._files import atomic_write
from ._validate import (
    _to_float,
    bounds_array,
    channel,
    number,
    numeric_array,
    positive,
    samples_array,
    signed16_samples,
    signed16_text,
    stored_signed16,
)

__all__ = [
    "DetectorSettings",
    "DwellAccumulator",
    "DwellSet",
    "TimeStepWarning",
    "detect_dwells",
    "dwell_stats",
]

_CSV_MAGIC = "# accelcal dwell table v1"


def _csv_text(v: str) -> str:
    """A text cell of the dwell table, quoted as CSV quotes text when it needs it."""
    if any(c in v for c in ',"\n\r') or v != v.strip():
        return '"' + v.replace('"', '""') + '"'
    return v
_AXES = ("x", "y", "z")
_STATE_MAGIC = b"ACCELCAL-DWELL-ACCUMULATOR\n"
_STATE_VERSION = 3  # 3: a CRC-32 of the rest; 2: the dropout runs of detection (1, 2 read)


#: Sample times are refused when their intervals are this many times ``1 / fs`` (or this
#: many times smaller): most of them and their mean.
CLOCK_RATIO = 3.0
#: Intervals between sample times needed before they are judged (a stream pushed in chunks
#: is judged on the times pushed so far).
_CLOCK_MIN_STEPS = 16
#: With ``fs`` known, times that have not advanced (or went back) are refused only once the
#: rows span this long at ``fs``, s: a logger that stamps in whole seconds repeats a stamp for
#: a second's rows, jittered stamps of one burst step back and forth, and a stream pushed a
#: row at a time must not be refused before its clock ticks.
_CLOCK_FLAT_S = 10.0


class TimeStepWarning(UserWarning):
    """Sample times ``t`` step back (a clock reset, recordings joined) or jump forward (a
    clock step, samples missing): they are kept as given, so the dwell times after the step
    are on the new clock, and a dwell that spans it has a time on neither."""


class _Clock:
    """The running check of per-sample times ``t`` (s) against ``fs``: counts of the
    intervals, so that a stream pushed in chunks is judged on the same numbers as in one
    call, with the first and last time (the interval across a chunk boundary counts).

    :meth:`check` returns the state with a chunk added (or raises) without changing this one;
    the caller keeps it once the chunk is accepted."""

    FIELDS = ("first", "last", "steps", "pos", "long", "short", "back", "warned")
    __slots__ = FIELDS

    def __init__(self, state: list[Any] | None = None) -> None:
        self.first: float | None = None
        self.last: float | None = None
        self.steps = self.pos = self.long = self.short = self.back = 0
        self.warned = False
        if state is not None:
            (self.first, self.last, self.steps, self.pos, self.long, self.short, self.back,
             self.warned) = state

    def state(self) -> list[Any]:
        return [getattr(self, k) for k in self.FIELDS]

    @staticmethod
    def valid_state(v: Any) -> bool:
        return isinstance(v, list) and len(v) == len(_Clock.FIELDS) and all(
            (x is None or isinstance(x, float)) for x in v[:2]) and all(
            type(x) is int and x >= 0 for x in v[2:7]) and isinstance(v[7], bool)

    def check(self, t: NDArray[np.float64] | None, fs: float | None, row0: int = 0,
              whole: bool = False) -> tuple[_Clock, str | None]:
        """``(state with t added, warning text or None)``; a CalibrationError when the times
        cannot be sample times at ``fs``. ``row0`` is the stream row of ``t[0]``;
        non-finite times are left to the core. ``whole``: ``t`` is the whole stream, so the
        warning can count every step back (a stream pushed in chunks warns at its first)."""
        if t is None or t.size == 0:
            return self, None
        if t.size == 1 and self.last is not None:  # a row at a time: no array work
            x = float(t[0])
            if math.isfinite(x):
                return self._one(x, fs, row0)
        rows = None
        if not math.isfinite(float(np.add.reduce(t))):  # one sum when every time is finite
            rows = np.flatnonzero(np.isfinite(t))
        v = t if rows is None else t[rows]
        new = _Clock(self.state())
        if v.size == 0:
            return new, None
        d = v[1:] - v[:-1]
        if self.last is None:
            new.first = float(v[0])
            lo = hi = math.nan
        else:  # the interval across the chunk boundary
            lo = hi = float(v[0]) - self.last
        new.last = float(v[-1])
        n = d.size + (self.last is not None)
        new.steps += n
        dt = None if fs is None else 1.0 / fs
        nback = njump = 0
        if d.size:
            lo, hi = float(np.fmin(d.min(), lo)), float(np.fmax(d.max(), hi))
        if n and lo > 0 and (dt is None or (lo >= dt / CLOCK_RATIO and hi <= CLOCK_RATIO * dt)):
            new.pos += n  # the common case: every interval about 1 / fs
        elif n:
            if self.last is not None:
                d = np.concatenate(([float(v[0]) - self.last], d))
            new.pos += int(np.count_nonzero(d > 0))
            nback = int(np.count_nonzero(d < 0))
            new.back += nback
            if dt is not None:
                new.long += int(np.count_nonzero(d > CLOCK_RATIO * dt))
                new.short += int(np.count_nonzero((d > 0) & (d < dt / CLOCK_RATIO)))
                njump = int(np.count_nonzero(d > _clock_step_s(dt)))
        if njump and not new.judges_jumps():
            njump = 0
        warn = None
        if (nback or njump) and not self.warned:
            big = math.inf if dt is None else _clock_step_s(dt)
            i = int(np.flatnonzero((d < 0) | (d > big))[0])
            at = i + (0 if self.last is not None else 1)  # index in v of the row after it
            row = row0 + (at if rows is None else int(rows[at]))
            new.warned = True
            warn = self._step_text(float(d[i]), row, dt, (nback, njump) if whole else None)
        return new._judged(warn, fs, dt)

    def _one(self, x: float, fs: float | None, row: int) -> tuple[_Clock, str | None]:
        """:meth:`check` of one finite time ``x`` after others, in plain floats."""
        assert self.last is not None
        new = _Clock.__new__(_Clock)
        d = x - self.last
        dt = None if fs is None else 1.0 / fs
        new.first, new.last, new.steps, new.warned = self.first, x, self.steps + 1, self.warned
        new.pos, new.back = self.pos + (d > 0), self.back + (d < 0)
        new.long, new.short = self.long, self.short
        if dt is not None:
            new.long += d > CLOCK_RATIO * dt
            new.short += 0 < d < dt / CLOCK_RATIO
        warn = None
        if (d < 0 or (dt is not None and d > CLOCK_RATIO * dt and d > _clock_step_s(dt)
                      and new.judges_jumps())) and not self.warned:
            new.warned = True
            warn = self._step_text(d, row, dt, None)
        return new._judged(warn, fs, dt)

    def judges_jumps(self) -> bool:
        """Whether a forward jump is a step of the clock: once the clock can be judged (16
        intervals) and most of its intervals are about ``1 / fs`` (not a clock in other
        units, which :meth:`_judged` refuses instead)."""
        return self.steps >= _CLOCK_MIN_STEPS and 2 * self.long <= self.pos

    @staticmethod
    def _step_text(step: float, row: int, dt: float | None,
                   counts: tuple[int, int] | None) -> str:
        """The warning of a clock that steps back (``step`` < 0, s) or jumps forward, first
        at ``row``; ``counts``: the steps back and jumps of the whole stream (None: a stream
        pushed in chunks, whose first step is warned once)."""
        by = abs(step)
        if step > 0:
            assert dt is not None
            why = (f"{by / dt:.4g} sample intervals at fs = {1.0 / dt:g} Hz: a clock step, or "
                   "samples missing from the stream? Kept as given: the dwell times after it "
                   "are on the stepped clock")
        else:
            why = ("under one sample interval: jittered time stamps? Kept as given"
                   if dt is not None and by < dt else
                   "a clock reset or recordings joined? Kept as given: the dwell times after "
                   "a step back are on the new clock")
        what = "steps back" if step < 0 else "jumps forward"
        if counts is None:  # a stream pushed in chunks: its first step, warned once
            return (f"t {what} at row {row}, by {by:.6g} s (further steps of this stream, "
                    f"back or forward, are not warned again): {why}")
        nback, njump = counts
        many = [f"steps back {nback} time(s)"] if nback else []
        many += [f"jumps forward {njump} time(s)"] if njump else []
        first = "" if len(many) == 1 else ("back " if step < 0 else "forward ")
        return (f"t {' and '.join(many)} (the first at row {row}, {first}by {by:.6g} s): "
                f"{why}")

    def _judged(self, warn: str | None, fs: float | None, dt: float | None
                ) -> tuple[_Clock, str | None]:
        """This state (the chunk added) and its warning, or a CalibrationError when the times
        so far cannot be sample times at ``fs``."""
        new = self
        if new.steps < _CLOCK_MIN_STEPS:
            return new, warn
        # Whether the clock advances is judged once the rows span _CLOCK_FLAT_S at fs.
        judged = dt is None or new.steps * dt > _CLOCK_FLAT_S
        if new.pos == 0 and new.back == 0 and judged:
            raise CalibrationError(
                f"t holds the same time ({new.first:g}) in every one of the {new.steps + 1} "
                "rows: not a clock (a logger's clock never set?); give the sample times in s, "
                "or no t" + (" (fs gives the dwell times)" if fs is not None else "")
            )
        # Jittered stamps of a logger that stamps in bursts step back about as often as
        # forward, but advance overall: only a clock that went back overall is refused.
        assert new.first is not None and new.last is not None
        if new.back >= new.pos and new.back and new.last < new.first and judged:
            raise CalibrationError(
                f"t steps back in {new.back} of its {new.steps} intervals and forward in "
                f"{new.pos}: sample times must increase (reversed or shuffled rows?)"
            )
        if dt is not None:
            mean = (new.last - new.first) / new.steps
            ratio = mean / dt
            if 2 * new.long > new.pos and ratio > CLOCK_RATIO:
                unit = next(((u, f) for u, f in (("ms", 1e3), ("us", 1e6), ("ns", 1e9))
                             if 0.5 * f <= ratio <= 2.0 * f), None)
                why = (f"t looks like a clock in {unit[0]}, not s: give t / {unit[1]:g}"
                       if unit else "check the unit of t (s) and the rate fs (Hz)")
                raise CalibrationError(
                    f"t advances {mean:.4g} per sample on average ({new.long} of {new.pos} "
                    f"intervals over {CLOCK_RATIO:g} sample intervals) where fs = {fs:g} Hz "
                    f"means {dt:.4g} s: {ratio:.4g} sample intervals; {why}. Dwell times "
                    "and durations would disagree by that factor"
                )
            if 2 * new.short > new.pos and ratio < 1.0 / CLOCK_RATIO and judged:
                raise CalibrationError(
                    f"t advances {mean:.4g} per sample on average ({new.short} of {new.pos} "
                    f"intervals under 1/{CLOCK_RATIO:g} of a sample interval) where fs = "
                    f"{fs:g} Hz means {dt:.4g} s: {ratio:.4g} sample intervals; check the "
                    "unit of t (s; in minutes or hours?) and the rate fs (Hz). Dwell times "
                    "and durations would disagree by that factor"
                )
        return new, warn


#: A time step of at least this many sample intervals (and at least _CLOCK_STEP_MIN_S) is a
#: step of the clock, not a missed sample or jitter: a forward jump warns (a
#: :class:`TimeStepWarning`, as a step back does), and a dwell that spans one is named.
_CLOCK_STEP_INTERVALS = 100.0
_CLOCK_STEP_MIN_S = 1.0
#: Clock steps whose rows a DwellAccumulator keeps (to name the dwells that span them).
_CLOCK_STEPS_KEPT = 1000


def _clock_step_s(dt: float | None) -> float:
    """The smallest time step (s) taken as a step of the clock at sample interval ``dt``."""
    return _CLOCK_STEP_MIN_S if dt is None else max(_CLOCK_STEP_INTERVALS * dt,
                                                    _CLOCK_STEP_MIN_S)


def _clock_steps(t: NDArray[np.float64], dt: float | None, last: float | None = None,
                 row0: int = 0, kept: NDArray[np.intp] | None = None) -> list[int]:
    """Stream rows (of the time after the step) where ``t`` steps back or forward by at least
    :func:`_clock_step_s` (back only without ``dt``). ``last``: the time before ``t[0]``;
    ``row0``: the stream row of the chunk's first row; ``kept``: the chunk rows ``t`` holds
    (dropouts left out); non-finite times are skipped."""
    rows = np.flatnonzero(np.isfinite(t))
    v = t[rows]
    if last is not None:
        v, rows = np.concatenate(([last], v)), np.concatenate(([-1], rows))
    d = v[1:] - v[:-1]
    big = _clock_step_s(dt)
    step = d < -big
    if dt is not None:
        step |= d > big
    hit = rows[1:][step]
    if kept is not None:
        hit = kept[hit]
    return [row0 + int(r) for r in hit]


def _check_times(t: NDArray[np.float64] | None, fs: float | None, given: Any = None
                 ) -> list[int]:
    """:class:`_Clock`'s check of a whole stream's times (a warning for steps back and
    forward jumps); ``given``: ``t`` as the caller gave it (its dtype explains a clock that
    does not tick). The rows of its clock steps (:func:`_clock_steps`)."""
    try:
        _, warn = _Clock().check(t, fs, whole=True)
    except CalibrationError as e:
        raise _coarse_times(e, given, fs) from None
    if warn is None:
        return []
    warnings.warn(warn, TimeStepWarning, stacklevel=3)
    assert t is not None
    return _clock_steps(t, None if fs is None else 1.0 / fs)


def _spanned(d: DwellSet, steps: Sequence[int], stacklevel: int = 3) -> DwellSet:
    """``d``, with a :class:`TimeStepWarning` naming the dwells that span a clock step (rows
    ``steps``, each the row after its step): their time, the mid time of their first and last
    sample, lies between two clocks."""
    if not steps or d.start is None or d.stop is None:
        return d
    r = np.asarray(sorted(steps), dtype=np.int64)
    k = np.searchsorted(r, d.start, side="right")  # the first step after each dwell's start
    inside = np.flatnonzero((k < r.size) & (r[np.minimum(k, r.size - 1)] < d.stop))
    if inside.size == 0:
        return d
    words = [f"{d.label(int(i))} [{int(d.start[i])}, {int(d.stop[i])}) at row "
             f"{int(r[k[i]])}" + ("" if d.t is None else f" (t = {float(d.t[i]):.6g} s)")
             for i in inside[:4]]
    more = f" and {inside.size - 4} more" if inside.size > 4 else ""
    warnings.warn(
        f"dwell(s) {', '.join(words)}{more} span a step of the clock t: a dwell's t, the mid "
        "time of its first and last sample, is then on neither clock; cut the dwell at the "
        "step (give bounds), or correct t", TimeStepWarning, stacklevel=stacklevel)
    return d


def _coarse_times(e: CalibrationError, t: Any, fs: float | None) -> CalibrationError:
    """``e`` (times refused by :class:`_Clock`) or, when ``t`` was given as float16 or float32
    whose resolution at the times' magnitude is coarser than the sample interval ``1 / fs``
    (any resolution above 0 without ``fs``), the error that says so: epoch seconds
    (1.8e9) in float32 step by 128 s, so that every row of a stream holds the same time."""
    dtype = getattr(t, "dtype", None)
    if dtype is None or dtype not in (np.float16, np.float32):
        return e
    v = np.asarray(t)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return e
    mag = float(np.abs(v).max())
    res = float(np.spacing(v.dtype.type(mag)))
    dt = None if fs is None else 1.0 / fs
    if dt is not None and res <= dt:
        return e
    than = ("" if dt is None else
            f", coarser than the sample interval {dt:.4g} s (fs = {fs:g} Hz)")
    return CalibrationError(
        f"t is {v.dtype}, whose resolution at its magnitude ({mag:.4g} s) is {res:.4g} s"
        f"{than}: the times were rounded when stored as {v.dtype} and no longer tell the "
        "samples apart. Pass float64 times (as read or computed: converting these back does "
        "not restore them), or times relative to the start of the recording (t - t0, "
        f"computed in float64). The check of t found: {e}"
    )


def _arr(a: Any, name: str, shape: tuple[int, ...], *, finite: bool = True) -> NDArray[np.float64]:
    """``a`` as float64 of exactly ``shape`` (no silent reshape), finite unless told."""
    v = numeric_array(a, name).astype(np.float64, copy=True)
    if v.shape != shape:
        raise CalibrationError(f"{name} must have shape {shape}; got {v.shape}")
    if finite and not np.all(np.isfinite(v)):
        raise CalibrationError(f"{name} contains NaN or inf")
    return v


def _ints(a: Any, name: str, k: int, lo: int) -> NDArray[np.int64]:
    """``a`` as (k,) int64 of whole numbers >= ``lo`` (NaN and fractions refused)."""
    v = numeric_array(a, name)
    if v.shape != (k,):
        raise CalibrationError(f"{name} must have shape ({k},); got {v.shape}")
    if v.dtype.kind == "f":
        if not np.all(np.isfinite(v)) or np.any(v != np.round(v)) or np.any(np.abs(v) >= 2.0**62):
            raise CalibrationError(f"{name} must hold whole numbers; got {v[:5].tolist()}...")
    out = v.astype(np.int64)
    if np.any(out < lo):
        raise CalibrationError(f"{name} must be >= {lo} for every dwell")
    return out


def _version() -> str:
    from ._triad_model import accelcal_version

    return accelcal_version()


def _provenance_lines(source: dict[str, Any] | None, detector: dict[str, Any] | None
                      ) -> list[tuple[str, str]]:
    """The dwell table's header lines of where its dwells come from: ``source`` (absolute
    path), ``source_sha256``, ``source_bytes`` and ``detector`` (JSON), those known."""
    out: list[tuple[str, str]] = []
    if source:
        for key, name in (("path", "source"), ("sha256", "source_sha256"),
                          ("bytes", "source_bytes")):
            if source.get(key) is not None:
                out.append((name, " ".join(str(source[key]).splitlines())))
    if detector:
        out.append(("detector", json.dumps(detector, sort_keys=True)))
    return out


def _provenance_of(meta: dict[str, str]) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """``(source, detector)`` from a dwell table's header lines (:func:`_provenance_lines`)."""
    source = None
    if "source" in meta:
        size = meta.get("source_bytes")
        source = {"path": meta["source"], "sha256": meta.get("source_sha256"),
                  "bytes": int(size) if size and size.isdigit() else None}
    detector = None
    if "detector" in meta:
        try:
            detector = json.loads(meta["detector"])
        except ValueError:
            raise CalibrationError(f"dwell table: the detector line is not JSON: "
                                   f"{meta['detector']!r}") from None
        if not isinstance(detector, dict):
            raise CalibrationError("dwell table: the detector line must name the settings "
                                   f"(a JSON object); got {meta['detector']!r}")
    return source, detector


class DwellSet:
    """Statistics of k static dwells.

    Attributes
    ----------
    mean : (k, 3) float64
        Mean output per dwell and axis, in the input's units (raw counts or m/s^2).
    var : (k, 3) float64 or None
        Sample variance per dwell and axis (ddof = 1), squared input units.
    count : (k,) int64 or None
        Samples per dwell.
    start, stop : (k,) int64 or None
        ``[start, stop)`` sample indices in the stream.
    t : (k,) float64 or None
        Mid time of each dwell, s.
    temperature : (k,) float64 or None
        Mean temperature per dwell (the recording's unit, usually deg C).
    half_mean : (k, 2, 3) float64 or None
        Mean of the first and of the second half of each dwell's samples (input units). With
        bounds the halves split at ``start + count // 2``; detected dwells split at the
        detector block nearest the middle (within ``block_s``).
    inflation : (k, 3) float64 or None
        Allan noise inflation: the factor by which the noise of each dwell mean exceeds white noise
        of the same sample-to-sample deviation (about 1 for white noise, larger for flicker or
        random-walk noise). One dwell's value scatters widely and is skewed: on white noise (12
        dwells of 4800 samples) its median is 0.92 and its mean 1.22, so pool it before use, as
        :func:`accelcal.diagnose` does (the median over dwells, at least 1, or a power law in the
        dwell length). Per dwell and axis, from the overlapping Allan deviation at cluster sizes of
        about L/16 and L/4 samples (L = dwell length) referred to the one-sample Allan deviation,
        extrapolated to tau = L along the log-log slope between them (clipped to [0, 1]). Clusters
        start at sub-block boundaries (64 per dwell with bounds, the detector blocks for detected
        dwells) rather than at every sample: the same expectation as the sample-stride estimator, a
        slightly larger scatter. Not pooled over dwells and not floored at 1. NaN where it cannot be
        estimated: dwells under 64 samples, or an axis without sample-to-sample variation.
    lsb : (3,) float64 or None
        Output resolution per axis, input units: for integer samples the common divisor of the
        spacings between distinct values (1 count for ordinary data); for float samples the
        spacing of which every gap between distinct values is a whole multiple, or None when
        the values are not quantised. Estimated from a bounded subsample (at most 4096 rows at
        a power-of-two stride) of the whole stream.
    dropped : int
        Rows with NaN or inf left out of the dwell statistics (automatic detection; 0
        otherwise). A dwell's ``[start, stop)`` may span some: ``count`` is the rows used.
    threshold, noise_std : (3,) float64 or None
        For detected dwells: the per-axis variance threshold and the noise std the detector
        estimated from the data (input units).
    vibrating : (m, 2) int64 or None
        For detected dwells: ``[start, stop)`` of the stretches (at least ``min_dwell_s``)
        left out although the sensor looks still in them: their variance is above the
        threshold, but the means of each window's two halves agree within 4 standard errors
        (vibration, not motion). ``vibrating_std`` (m, 3) is their sample std per axis. Raise
        the detector's ``k`` above (std / noise_std)^2 to use them as dwells. Not kept by
        :meth:`to_csv`.
    shorter : tuple or None
        For detected dwells, when fewer than 9 were found and they cover under a quarter of
        the stream: shorter detector settings ``(window_s, min_dwell_s, trim_s, dwells)``
        that find more dwells, every one steady (the means of its halves agree within 4
        standard errors of the noise): brief rests the window missed. Only a suggestion (a
        short window also takes the slow ends of moves); None otherwise.
    clipped : (k, 3, 2) int64 or None
        Samples of each dwell on each axis's low and high rail: for integer samples, the
        smallest and largest values of their dtype (-32768 and 32767 for int16), where the
        output clips. Counted only where the dwell's mean and variance allow enough of them
        to bias the mean (0 elsewhere: a dwell far from the rail needs no search, so the
        check costs nothing in a session that stays within range); None when no dwell has
        any (and for float samples, whose rail is not known). :meth:`faults` flags the
        dwells with enough of them to bias the mean.
    rail : (3, 2) float64 or None
        The low and high rail per axis (NaN where no dwell reached it), with ``clipped``.
    fs : float or None
        Sample rate of the stream, Hz.
    names : list of str or None
        A name per dwell, when the dwells come from a file that names them (a bounds file's
        sections, imucal's ``x_p``, ``y_a`` ...): shown in :meth:`table`, kept by
        :meth:`to_csv` and used in the gap report's list of flagged dwells.
    source : dict or None
        The recording the dwells come from, when known (``accelcal dwells`` sets it): its
        ``path`` (absolute), ``sha256`` and ``bytes``. Kept by :meth:`to_csv`.
    detector : dict or None
        The detector settings that found the dwells, when known (``window_s``, ``k``,
        ``min_dwell_s``, ``trim_s``; ``accelcal dwells`` sets them for detected dwells).
        Kept by :meth:`to_csv`.
    """

    def __init__(
        self,
        mean: ArrayLike,
        var: ArrayLike | None = None,
        count: ArrayLike | None = None,
        t: ArrayLike | None = None,
        temperature: ArrayLike | None = None,
        *,
        start: ArrayLike | None = None,
        stop: ArrayLike | None = None,
        fs: float | None = None,
        threshold: ArrayLike | None = None,
        noise_std: ArrayLike | None = None,
        units: str = "",
        half_mean: ArrayLike | None = None,
        inflation: ArrayLike | None = None,
        lsb: ArrayLike | None = None,
        dropped: int = 0,
        vibrating: ArrayLike | None = None,
        vibrating_std: ArrayLike | None = None,
        names: Sequence[str] | None = None,
        clipped: ArrayLike | None = None,
        rail: ArrayLike | None = None,
    ) -> None:
        m = numeric_array(mean, "mean").astype(np.float64, copy=True)
        if m.ndim == 1 and m.size == 3:
            m = m.reshape(1, 3)
        if m.ndim != 2 or m.shape[1] != 3:
            raise CalibrationError(f"mean must have shape (k, 3); got {m.shape}")
        k = m.shape[0]
        if k == 0:
            raise CalibrationError("a DwellSet needs at least one dwell; got 0")
        if not np.all(np.isfinite(m)):
            bad = np.where(~np.all(np.isfinite(m), axis=1))[0]
            raise CalibrationError(f"mean contains NaN or inf in dwell(s) {bad.tolist()}")
        self.mean: NDArray[np.float64] = m
        self.var: NDArray[np.float64] | None = None
        if var is not None:
            v = _arr(var, "var", (k, 3))
            if np.any(v < 0):
                raise CalibrationError("var must be non-negative")
            self.var = v
        self.count: NDArray[np.int64] | None = (
            None if count is None else _ints(count, "count", k, 1)
        )
        self.t = None if t is None else _arr(t, "t", (k,))
        self.temperature = None if temperature is None else _arr(temperature, "temperature", (k,))
        self.start = None if start is None else _ints(start, "start", k, 0)
        self.stop = None if stop is None else _ints(stop, "stop", k, 1)
        if self.start is not None and self.stop is not None and np.any(self.start >= self.stop):
            raise CalibrationError("start must be < stop for every dwell")
        self.fs = None if fs is None else positive(fs, "fs", " (Hz)")
        self.threshold = None if threshold is None else _arr(threshold, "threshold", (3,))
        self.noise_std = None if noise_std is None else _arr(noise_std, "noise_std", (3,))
        self.half_mean = None if half_mean is None else _arr(half_mean, "half_mean", (k, 2, 3))
        self.inflation = None
        if inflation is not None:
            f = _arr(inflation, "inflation", (k, 3), finite=False)
            if np.any(np.isinf(f)) or np.any(f < 0):
                raise CalibrationError("inflation must be >= 0 and finite (NaN: not estimable)")
            self.inflation = f
        self.lsb = None
        if lsb is not None:
            q = _arr(lsb, "lsb", (3,))
            if np.any(q <= 0):
                raise CalibrationError(f"lsb must be positive; got {q.tolist()}")
            self.lsb = q
        self.dropped = int(number(dropped, "dropped", lo=0))
        self.vibrating: NDArray[np.int64] | None = None
        self.vibrating_std: NDArray[np.float64] | None = None
        if vibrating is not None:
            vb = np.asarray(vibrating, dtype=np.int64).reshape(-1, 2)
            vs = _arr(np.asarray(vibrating_std, dtype=np.float64).reshape(-1, 3),
                      "vibrating_std", (vb.shape[0], 3))
            self.vibrating, self.vibrating_std = vb, vs
        if not isinstance(units, str):
            raise CalibrationError(f"units must be a string; got {units!r}")
        self.units = units
        #: Detected dwells, when few were found: shorter detector settings that find more
        #: steady dwells (brief rests), ``(window_s, min_dwell_s, trim_s, dwells)``; else None.
        self.shorter: tuple[float, float, float, int] | None = None
        #: Where the dwells come from, when known (see the class doc): kept by to_csv.
        self.source: dict[str, Any] | None = None
        self.detector: dict[str, Any] | None = None
        self.names: list[str] | None = None
        if names is not None:
            nm = list(names)
            if len(nm) != k or not all(isinstance(x, str) for x in nm):
                raise CalibrationError(f"names must be {k} strings (one per dwell); got {nm!r}")
            self.names = nm
        self.clipped: NDArray[np.int64] | None = None
        self.rail: NDArray[np.float64] | None = None
        if (clipped is None) != (rail is None):
            raise CalibrationError("clipped and rail go together: give both or neither")
        if clipped is not None:
            c = numeric_array(clipped, "clipped")
            if c.shape != (k, 3, 2) or c.dtype.kind not in "iu" or np.any(c < 0):
                raise CalibrationError(f"clipped must be ({k}, 3, 2) counts >= 0; got "
                                       f"{c.dtype} {c.shape}")
            if self.count is not None and np.any(c > self.count[:, None, None]):
                raise CalibrationError("clipped must not exceed count")
            self.clipped = c.astype(np.int64)
            self.rail = _arr(rail, "rail", (3, 2), finite=False)

    def __len__(self) -> int:
        return int(self.mean.shape[0])

    def __repr__(self) -> str:
        extra = [
            n
            for n in ("var", "t", "temperature", "half_mean", "inflation", "lsb")
            if getattr(self, n) is not None
        ]
        return f"DwellSet({len(self)} dwells; {', '.join(['mean', *extra])})"

    def __getitem__(self, idx: Any) -> DwellSet:
        """A subset of dwells (index, slice, boolean mask or index array)."""
        sel = np.arange(len(self))[idx]
        sel = np.atleast_1d(sel)

        def take(a: NDArray[Any] | None) -> Any:
            return None if a is None else a[sel]

        out = DwellSet(
            self.mean[sel],
            take(self.var),
            take(self.count),
            take(self.t),
            take(self.temperature),
            start=take(self.start),
            stop=take(self.stop),
            fs=self.fs,
            threshold=self.threshold,
            noise_std=self.noise_std,
            units=self.units,
            half_mean=take(self.half_mean),
            inflation=take(self.inflation),
            lsb=self.lsb,
            dropped=self.dropped,
            vibrating=self.vibrating,
            vibrating_std=self.vibrating_std,
            names=None if self.names is None else [self.names[i] for i in sel],
            clipped=take(self.clipped),
            rail=self.rail,
        )
        out.source, out.detector = self.source, self.detector  # a subset: the same origin
        return out

    def label(self, k: int) -> str:
        """``"3"``, or ``"3 (y_a)"`` when the dwells are named."""
        return str(k) if self.names is None else f"{k} ({self.names[k]})"

    @property
    def duration(self) -> NDArray[np.float64] | None:
        """Dwell lengths in s (needs count and fs)."""
        if self.count is None or self.fs is None:
            return None
        return self.count / self.fs

    @property
    def sem(self) -> NDArray[np.float64] | None:
        """White-noise standard error of each mean, sqrt(var / count) (input units)."""
        if self.var is None or self.count is None:
            return None
        return np.sqrt(self.var / self.count[:, None])

    # ---- output faults ---------------------------------------------------------------------
    def faults(self) -> list[Fault]:
        """Dwells whose output did not follow the sensor: an axis exactly constant over a
        dwell of at least 30 samples, where that axis's noise is otherwise resolvable (its
        typical dwell std at least one LSB, or positive when the output is not quantised:
        below one LSB, constant dwells are the sensor's resolution, not a fault).

        ``kind`` says what the constancy means: ``"saturated_high"`` / ``"saturated_low"``
        (the value is the largest / smallest of that axis in the session: the output is
        clipped at the sensor's range, and the dwell mean is the rail, not the pose),
        ``"stuck"`` (constant elsewhere) or ``"frozen"`` (all three axes constant: the
        logger repeated one sample). Once a saturated dwell shows an axis's rail, a dwell whose
        mean lies within reach of it is ``"partly_saturated_high"`` / ``"_low"``: with the
        axis's typical noise std s, a pose delta s inside the rail reads a mean short by
        s (phi(delta) - delta Q(delta)), flagged above half the mean's standard error. Empty
        without ``var`` and ``count``.

        Integer samples show the rail themselves (:attr:`clipped`: the dtype's extremes): a
        dwell with some samples on it is ``"partly_saturated_high"`` / ``"_low"`` too (a
        :class:`RailFault`, which counts them) when the fraction p on the rail means a
        shortfall s (phi(delta) - delta Q(delta)) with Q(delta) = p above half the mean's
        standard error, whether or not a dwell is saturated throughout. Float samples have
        no known rail: there, in a session where no dwell is saturated throughout, a partly
        clipped dwell is not found.
        """
        if self.var is None or self.count is None:
            return []
        found: list[Fault] = list(_core.dwell_output_faults(
            self.mean, self.var, self.count, None if self.lsb is None else self.lsb.tolist()
        ))
        more = self._rail_faults(found)
        if not more:
            return found
        return sorted(found + more, key=lambda f: (f.dwell, 0 if f.axis is None else f.axis + 1))

    def _rail_faults(self, found: list[Fault]) -> list[Fault]:
        """The dwells with enough samples on an integer rail to bias their mean (those
        ``found`` already flagged on that axis left out)."""
        if self.clipped is None or self.rail is None or self.count is None or self.var is None:
            return []
        taken = {(f.dwell, f.axis) for f in found} | {(f.dwell, a) for f in found
                                                      if f.axis is None for a in range(3)}
        out: list[Fault] = []
        for k, a, side in np.argwhere(self.clipped > 0).tolist():
            n, c = int(self.count[k]), int(self.clipped[k, a, side])
            if (k, a) in taken or not _clip_biases(c / max(n, 1), n):
                continue
            v = sorted(float(x) for x, m in zip(self.var[:, a], self.count, strict=True)
                       if m >= _FAULT_MIN_SAMPLES and math.isfinite(x))
            q = v[-(-3 * (len(v) - 1) // 4)] if v else float(self.var[k, a])
            out.append(RailFault(k, a, "partly_saturated_" + ("high" if side else "low"),
                                 float(self.mean[k, a]), float(self.rail[a, side]), q, c, n))
            taken.add((k, a))
        return out

    def drop_faults(self, faults: list[Fault] | None = None) -> DwellSet:
        """The dwells without those :meth:`faults` lists (all of them when there are none);
        ``faults`` is that list when the caller already has it."""
        faults = self.faults() if faults is None else faults
        bad = {f.dwell for f in faults}
        if not bad:
            return self
        if len(bad) == len(self):
            raise CalibrationError(
                "every dwell has a constant (saturated, stuck or frozen) output: "
                + fault_text(self, faults, limit=3)
            )
        return self[np.array([k not in bad for k in range(len(self))])]

    # ---- CSV round trip -------------------------------------------------------------------
    def to_csv(self, path: str | os.PathLike[str] | None = None) -> str:
        """Write the table as CSV (atomically when ``path`` is given); return the text.

        Full float64 precision (``%.17g``), so :meth:`from_csv` gives back identical numbers.
        The header names the accelcal version that wrote it and, when known, the recording
        (:attr:`source`: ``# source:``, ``# source_sha256:``, ``# source_bytes:``) and the
        detector settings (:attr:`detector`, ``# detector:`` as JSON), read back by
        :meth:`from_csv`.
        """
        k = len(self)
        cols: list[tuple[str, NDArray[Any]]] = []
        if self.names is not None:
            cols.append(("name", np.array(self.names, dtype=object)))
        if self.start is not None and self.stop is not None:
            cols += [("start", self.start), ("stop", self.stop)]
        if self.count is not None:
            cols.append(("count", self.count))
        if self.t is not None:
            cols.append(("t_s", self.t))
        if self.temperature is not None:
            cols.append(("temperature", self.temperature))
        cols += [(f"mean_{a}", self.mean[:, i]) for i, a in enumerate(_AXES)]
        if self.var is not None:
            cols += [(f"var_{a}", self.var[:, i]) for i, a in enumerate(_AXES)]
        if self.half_mean is not None:
            for h in (0, 1):
                cols += [(f"half{h + 1}_{a}", self.half_mean[:, h, i]) for i, a in enumerate(_AXES)]
        if self.inflation is not None:
            cols += [(f"inflation_{a}", self.inflation[:, i]) for i, a in enumerate(_AXES)]
        if self.clipped is not None:
            for h, side in enumerate(("low", "high")):
                cols += [(f"clipped_{side}_{a}", self.clipped[:, i, h])
                         for i, a in enumerate(_AXES)]
        buf = io.StringIO()
        buf.write(_CSV_MAGIC + "\n")
        buf.write(f"# accelcal_version: {_version()}\n")
        for key, v in _provenance_lines(self.source, self.detector):
            buf.write(f"# {key}: {v}\n")
        if self.units:
            buf.write(f"# units: {self.units}\n")
        if self.fs is not None:
            buf.write(f"# fs_hz: {self.fs!r}\n")
        for key in ("threshold", "noise_std", "lsb"):
            v = getattr(self, key)
            if v is not None:
                buf.write(f"# {key}: " + " ".join(repr(float(x)) for x in v) + "\n")
        if self.dropped:
            buf.write(f"# dropped: {self.dropped}\n")
        if self.rail is not None:
            for h, side in enumerate(("low", "high")):
                buf.write(f"# rail_{side}: " + " ".join(repr(float(x)) for x in self.rail[:, h])
                          + "\n")
        buf.write(",".join(n for n, _ in cols) + "\n")
        for r in range(k):
            cells = []
            for _, c in cols:
                v = c[r]
                if c.dtype.kind == "O":  # a name: quoted as CSV quotes text
                    cells.append(_csv_text(str(v)))
                else:
                    cells.append(str(int(v)) if c.dtype.kind in "iu" else f"{float(v):.17g}")
            buf.write(",".join(cells) + "\n")
        text = buf.getvalue()
        if path is not None:
            atomic_write(path, text)
        return text

    @classmethod
    def from_csv(cls, path_or_text: str | os.PathLike[str]) -> DwellSet:
        """Read a table written by :meth:`to_csv` (a path, or the CSV text itself)."""
        s = str(path_or_text)
        if "\n" in s:
            text = s
        else:
            try:
                with open(s, encoding="utf-8") as fh:
                    text = fh.read()
            except OSError as e:
                raise CalibrationError(f"cannot read dwell table {s!r}: {e.strerror}") from None
            except UnicodeDecodeError:
                raise CalibrationError(f"dwell table {s!r} is not UTF-8 text") from None
        lines = [ln for ln in text.splitlines() if ln.strip()]
        meta: dict[str, str] = {}
        body = []
        for ln in lines:
            if ln.startswith("#"):
                if ":" in ln:
                    key, val = ln[1:].split(":", 1)
                    meta[key.strip()] = val.strip()
            else:
                body.append(ln)
        if not body:
            raise CalibrationError("dwell table has no header row")
        parsed = list(csv.reader(body))
        names = [c.strip() for c in parsed[0]]
        if not all(f"mean_{a}" in names for a in _AXES):
            raise CalibrationError(f"dwell table needs columns mean_x, mean_y, mean_z; got {names}")
        rows = parsed[1:]
        if any(len(r) != len(names) for r in rows):
            raise CalibrationError("dwell table rows do not all have the header's column count")
        data = {n: [r[i] for r in rows] for i, n in enumerate(names)}

        def num(vals: list[str], n: str, dtype: Any) -> NDArray[Any]:
            try:
                return np.array(vals, dtype=dtype)
            except ValueError:
                raise CalibrationError(f"dwell table column {n!r} is not numeric") from None

        def f(n: str) -> NDArray[np.float64] | None:
            return num(data[n], n, np.float64) if n in data else None

        def i(n: str) -> NDArray[np.int64] | None:
            return num(data[n], n, np.int64) if n in data else None

        def cols(prefix: str) -> NDArray[np.float64] | None:
            if not all(f"{prefix}_{a}" in data for a in _AXES):
                return None
            return np.column_stack([num(data[f"{prefix}_{a}"], prefix, np.float64) for a in _AXES])

        def vec(key: str) -> NDArray[np.float64] | None:
            return num(meta[key].split(), key, np.float64) if key in meta else None

        source, detector = _provenance_of(meta)
        h1, h2 = cols("half1"), cols("half2")
        c_lo, c_hi = cols("clipped_low"), cols("clipped_high")
        r_lo, r_hi = vec("rail_low"), vec("rail_high")
        clipped = rail = None
        if c_lo is not None and c_hi is not None and r_lo is not None and r_hi is not None:
            clipped = np.stack([c_lo, c_hi], axis=2).astype(np.int64)
            rail = np.stack([r_lo, r_hi], axis=1)
        out = cls(
            cols("mean"),  # type: ignore[arg-type]
            cols("var"),
            i("count"),
            f("t_s"),
            f("temperature"),
            start=i("start"),
            stop=i("stop"),
            fs=float(meta["fs_hz"]) if "fs_hz" in meta else None,
            threshold=vec("threshold"),
            noise_std=vec("noise_std"),
            units=meta.get("units", ""),
            half_mean=None if h1 is None or h2 is None else np.stack([h1, h2], axis=1),
            inflation=cols("inflation"),
            lsb=vec("lsb"),
            dropped=int(meta.get("dropped", "0")),
            names=data.get("name"),
            clipped=clipped,
            rail=rail,
        )
        out.source, out.detector = source, detector
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict of lists (a NaN inflation becomes None), with the :meth:`faults` and
        the ``vibrating`` stretches."""
        out: dict[str, Any] = {"n_dwells": len(self), "units": self.units, "fs_hz": self.fs,
                               "names": self.names}
        for name in (
            "start", "stop", "count", "t", "temperature", "mean", "var", "half_mean",
            "threshold", "noise_std", "lsb", "clipped",
        ):
            v = getattr(self, name)
            out[name] = None if v is None else v.tolist()
        out["inflation"] = (
            None
            if self.inflation is None
            else [[None if math.isnan(x) else x for x in r] for r in self.inflation.tolist()]
        )
        out["dropped"] = self.dropped
        out["vibrating"] = None if self.vibrating is None or self.vibrating_std is None else [
            {"start": int(a), "stop": int(b), "std": sd.tolist()}
            for (a, b), sd in zip(self.vibrating, self.vibrating_std, strict=True)
        ]
        out["rail"] = None if self.rail is None else [
            [None if math.isnan(x) else x for x in r] for r in self.rail.tolist()]
        out["faults"] = [
            {"dwell": f.dwell, "axis": None if f.axis is None else _AXES[f.axis],
             "kind": f.kind, "value": f.value, "rail": None if math.isnan(f.rail) else f.rail,
             **({"clipped": f.clipped} if isinstance(f, RailFault) else {})}
            for f in self.faults()
        ]
        return out

    def table(self, max_rows: int | None = None) -> str:
        """A readable fixed-width table."""
        wn = 0 if self.names is None else max(4, *(len(x) for x in self.names))
        hdr = f"{'#':>3} " + (f"{'name':<{wn}} " if wn else "")
        hdr += f"{'start':>9} {'stop':>9} {'dur_s':>7} "
        hdr += " ".join(f"{'mean_' + a:>14}" for a in _AXES) + " "
        hdr += " ".join(f"{'std_' + a:>10}" for a in _AXES)
        if self.temperature is not None:
            hdr += f" {'temp':>8}"
        lines = [hdr]
        k = len(self)
        rows = range(k) if max_rows is None else range(min(k, max_rows))
        for r in rows:
            st = "" if self.start is None else str(int(self.start[r]))
            sp = "" if self.stop is None else str(int(self.stop[r]))
            dur = ""
            if self.count is not None and self.fs:
                dur = f"{self.count[r] / self.fs:.2f}"
            ln = f"{r:>3} " + (f"{self.names[r]:<{wn}} " if self.names is not None else "")
            ln += f"{st:>9} {sp:>9} {dur:>7} "
            ln += " ".join(f"{v:>14.6f}" for v in self.mean[r]) + " "
            if self.var is not None:
                ln += " ".join(f"{np.sqrt(v):>10.3g}" for v in self.var[r])
            if self.temperature is not None:
                ln += f" {self.temperature[r]:>8.3f}"
            lines.append(ln)
        if max_rows is not None and k > max_rows:
            lines.append(f"... {k - max_rows} more")
        if self.dropped:
            lines.append(f"{self.dropped} row(s) with NaN or inf left out of the statistics")
        return "\n".join(lines)


_FAULT_MEANING = {
    "saturated_high": "the largest {a} of the session: saturated (clipped at the sensor's range)",
    "saturated_low": "the smallest {a} of the session: saturated (clipped at the sensor's range)",
    "stuck": "not an extreme of {a}: a stuck channel",
}


def _partly_text(f: Fault, a: str, std: float, unit: str, faults: list[Fault]) -> str:
    if isinstance(f, RailFault):
        return (f"{f.clipped} of {f.count} {a} samples ({100.0 * f.clipped / f.count:.2g} %) "
                f"at {f.rail:.10g}{unit}, the {'largest' if f.rail > f.value else 'smallest'} "
                "value the integer samples can hold: clipped at the sensor's range, so its "
                f"{a} mean {f.value:.10g}{unit} is biased inside the rail")
    rail_dwells = [g.dwell for g in faults if g.axis == f.axis and g.rail == f.rail
                   and g.kind.startswith("saturated")]
    delta = abs(f.rail - f.value) / std
    return (f"{a} mean {f.value:.10g}{unit}, {delta:.2g} noise std ({std:.3g}{unit}) inside the "
            f"rail {f.rail:.10g} at which {a} saturates in dwell(s) "
            f"{', '.join(map(str, rail_dwells[:5]))}{' ...' if len(rail_dwells) > 5 else ''}: "
            "part of its samples are clipped, so its mean is biased")


def fault_text(d: DwellSet, faults: list[Fault], limit: int | None = 8) -> str:
    """The faults in words, one line per dwell axis (``limit`` lines, then a count)."""
    unit = f" {d.units}" if d.units else ""
    lines = []
    for f in faults[: len(faults) if limit is None else limit]:
        n = "" if d.count is None else f"all {int(d.count[f.dwell])} samples"
        when = "" if d.t is None else f" (t = {d.t[f.dwell]:.1f} s)"
        std = f"{math.sqrt(f.typical_var):.3g}{unit}"
        if f.axis is None:
            lines.append(f"dwell {f.dwell}{when}: x, y and z each the same in {n or 'every sample'}"
                         f" (elsewhere their std within a dwell is up to {std}): a frozen output, "
                         "the logger repeated one sample while the sensor sent nothing new")
            continue
        a = _AXES[f.axis]
        if f.kind.startswith("partly"):
            lines.append(f"dwell {f.dwell}{when}: "
                         + _partly_text(f, a, math.sqrt(f.typical_var), unit, faults))
            continue
        lines.append(f"dwell {f.dwell}{when}: {a} = {f.value:.10g}{unit} in {n or 'every sample'} "
                     f"(elsewhere its std within a dwell is {std}), "
                     + _FAULT_MEANING[f.kind].format(a=a))
    if limit is not None and len(faults) > limit:
        lines.append(f"... {len(faults) - limit} more")
    return "\n  ".join(lines)


def shorter_text(d: DwellSet) -> list[str]:
    """A note when shorter detector settings find more steady dwells than were found
    (:attr:`DwellSet.shorter`: brief rests that the window missed), with the settings."""
    if d.shorter is None:
        return []
    w, m, tr, k = d.shorter
    return [f"only {len(d)} dwell(s) found; shorter settings, window_s = {w:g} s with "
            f"min_dwell_s = {m:g} s and trim_s = {tr:g} s, find {k} steady dwells (brief "
            "rests, the means of each dwell's halves agreeing): check them (the dwells plot, "
            "the fit's chi2/dof) before use, since a short window also takes the slow ends of "
            "moves"]


def vibrating_text(d: DwellSet, option: str = "k=") -> list[str]:
    """A note on the stretches the detector left out although they look still (vibration
    above its threshold), with the detector ``k`` that would take them (``option`` names it:
    ``"k="`` for Python, ``"--k "`` for the command line)."""
    vb, vs = d.vibrating, d.vibrating_std
    if vb is None or vs is None or len(vb) == 0 or d.noise_std is None or d.threshold is None:
        return []
    noise = np.asarray(d.noise_std)
    k_now = float(np.max(np.asarray(d.threshold) / noise**2))
    ratio = float(np.max(vs / noise))
    # Above the threshold now: at least the next whole k (a ratio of about sqrt(k) gave
    # "--k 6 would take them (... k = 6 now)").
    k_need = max(math.ceil(1.1 * ratio**2), math.floor(k_now) + 1)
    span = int((vb[:, 1] - vb[:, 0]).sum())
    when = "" if not d.fs else (f" ({span / d.fs:.3g} s in all, the first at "
                                f"{vb[0, 0] / d.fs:.1f} s)")
    take = (f"{option}{k_need} would take them (the threshold is k x the noise variance; k = "
            f"{k_now:.3g} now)")
    if k_need > 4 * k_now:
        # A threshold that high also takes slow motion (a turntable, a low sample rate):
        # the halves of a window agree while the attitude creeps.
        take = (f"a threshold that takes them ({option}{k_need}, against k = {k_now:.3g} now) "
                "would also take slow motion, so look at them first (the dwells plot)")
    return [f"{len(vb)} stretch(es){when} look still (their mean stays put) but vibrate above "
            f"the detector's threshold (std up to {ratio:.2g}x the noise): not used as dwells; "
            f"{take}"]


#: A dwell's sample std on an axis above this fraction of its mean's norm is not a rest.
UNSTEADY_STD = 0.1


def unsteady_text(d: DwellSet) -> list[str]:
    """A note on dwells whose sample std on some axis exceeds ``UNSTEADY_STD`` (10 %) of the
    norm of their mean: far above any accelerometer's noise at rest, so the sensor was likely
    moving throughout (a recording turned continuously, read at a rate that made its slow
    turns look still)."""
    if d.var is None or len(d) == 0:
        return []
    sd = np.sqrt(np.max(np.asarray(d.var), axis=1))
    nrm = np.linalg.norm(d.mean, axis=1)
    bad = np.flatnonzero(sd > UNSTEADY_STD * nrm)
    if bad.size == 0:
        return []
    worst = float(np.max(sd[bad] / nrm[bad]))
    which = ", ".join(f"#{k}" for k in bad[:8]) + (" ..." if bad.size > 8 else "")
    return [f"{bad.size} of {len(d)} dwells ({which}) have a sample std of up to "
            f"{100 * worst:.0f} % of their mean's norm on some axis: far above an "
            "accelerometer's noise at rest, so the sensor was likely moving (a recording "
            "turned continuously has no rests to find); look at the dwells plot before "
            "trusting a fit"]


def check_faults(d: DwellSet, what: str, detected: bool = False) -> None:
    """Refuse dwells whose output did not follow the sensor, naming them and the remedy
    (``detected``: the caller detected ``d`` from raw samples it was given)."""
    faults = d.faults()
    if faults:
        k = len({f.dwell for f in faults})
        how = (f"{what}(d.drop_faults(), ...)" if not detected else
               f"d = accelcal.detect_dwells(samples, fs).drop_faults(); {what}(d, ...)")
        raise CalibrationError(
            f"{k} of {len(d)} dwells have an output that did not follow the sensor, so their "
            f"means are not the pose's:\n  {fault_text(d, faults)}\n"
            f"Leave them out: {how} (the command line does so and says which), or repeat "
            "those poses within the sensor's range."
        )


class _Dropouts:
    """Rows with NaN or inf that automatic detection leaves out of the statistics, as runs
    ``[first row, length]`` of the stream as given, so that the dwell bounds can refer to it.

    The detector then sees the stream without those rows: a dropout inside a dwell no longer
    splits it (nor, when dropouts are frequent, leaves no window free of them)."""

    def __init__(self, runs: list[list[int]] | None = None) -> None:
        self.runs: list[list[int]] = runs if runs is not None else []
        self.n = sum(r[1] for r in self.runs)

    @staticmethod
    def finite_rows(a: NDArray[Any]) -> NDArray[np.bool_] | None:
        """Mask of the rows without NaN or inf, or None when every row is finite (checked
        with one sum when the values are floats; integers are always finite)."""
        if a.dtype.kind != "f" or math.isfinite(float(np.add.reduce(a, axis=None))):
            return None
        ok = np.isfinite(a).all(axis=1)
        return None if bool(ok.all()) else ok

    def add(self, ok: NDArray[np.bool_], offset: int) -> None:
        """Record the rows of a chunk starting at stream row ``offset`` that ``ok`` leaves out."""
        self.commit(self.plan(ok, offset))

    def plan(self, ok: NDArray[np.bool_], offset: int) -> tuple[int, list[list[int]], int] | None:
        """What :meth:`add` would do, without doing it: ``(k, runs, n)``, the runs from index
        ``k`` on and the new count (None when ``ok`` leaves nothing out)."""
        bad = np.flatnonzero(~ok) + offset
        if bad.size == 0:
            return None
        cut = np.flatnonzero(np.diff(bad) != 1) + 1
        new = [[int(r[0]), int(r.size)] for r in np.split(bad, cut)]
        k = len(self.runs)
        if self.runs and sum(self.runs[-1]) == new[0][0]:  # continues the last run
            k -= 1
            new[0] = [self.runs[-1][0], self.runs[-1][1] + new[0][1]]
        return k, new, self.n + int(bad.size)

    def commit(self, plan: tuple[int, list[list[int]], int] | None) -> None:
        """Apply a :meth:`plan` (assignments only: applying it again changes nothing, so an
        interrupted commit can be completed)."""
        if plan is None:
            return
        k, new, n = plan
        self.runs[k:] = new
        self.n = n

    def explain(self, e: CalibrationError, n: int,
                samples: NDArray[Any] | None = None) -> CalibrationError:
        """``e`` (detection found nothing, or nothing was left) with what the dropouts did;
        ``samples`` (the stream as given) names the axes that are never finite."""
        if not self.n:
            return e
        if self.n >= n:
            dead = [] if samples is None else [
                "xyz"[a] for a in range(3) if not np.isfinite(samples[:, a]).any()]
            which = (f"axis {dead[0]} is NaN or inf in every row: a dead or unconnected "
                     "channel" if len(dead) == 1 else
                     f"axes {', '.join(dead)} are NaN or inf in every row" if dead else
                     "a dead or unconnected channel, or a logger that wrote no data")
            return type(e)(
                f"every one of the {n} rows holds NaN or inf samples ({which}): nothing is "
                "left to detect dwells in"
            )
        return type(e)(
            f"{e}. Note: {self.n} of {n} rows ({100.0 * self.n / n:.3g} %) held NaN or inf "
            "samples (dropouts) and were left out; the detector counts the rows that remain "
            "at fs, so every dwell is shorter in samples by about that fraction: with many "
            "dropouts, lower window_s= and min_dwell_s="
        )

    def to_stream(self, i: NDArray[np.int64]) -> NDArray[np.int64]:
        """Row indices of the compacted stream (without the dropouts) as rows of the stream."""
        if not self.runs:
            return i
        r = np.asarray(self.runs, dtype=np.int64)
        lengths = np.cumsum(r[:, 1])
        at = r[:, 0] - (lengths - r[:, 1])  # where each run sits in the compacted stream
        k = np.searchsorted(at, i, side="right")
        return i + np.where(k > 0, lengths[np.maximum(k - 1, 0)], 0)


#: Fewest samples of a dwell for clipping to be judged (as for a constant axis).
_FAULT_MIN_SAMPLES = 30
#: A dwell with samples on a rail is flagged when the clipping shifts its mean by more than
#: this many standard errors of the mean (the partly saturated test of ``DwellSet.faults``).
_PARTLY_CLIPPED_SE = 0.5


def _clip_shortfall(delta: float) -> float:
    """Mean shortfall, in noise std, of a Gaussian sample clipped ``delta`` std from its mean:
    ``phi(delta) - delta Q(delta)``."""
    d = max(0.0, delta)
    return math.exp(-0.5 * d * d) / math.sqrt(2.0 * math.pi) - d * 0.5 * math.erfc(d / math.sqrt(2))


@dataclass(frozen=True)
class RailFault:
    """A dwell with part of its samples on an integer output's rail (the largest or smallest
    value its dtype holds, where the ADC clips): ``kind`` is ``"partly_saturated_high"`` or
    ``"partly_saturated_low"``, with the fields of :class:`accelcal._core.OutputFault` and
    ``clipped`` of the dwell's ``count`` samples on the rail."""

    dwell: int
    axis: int
    kind: str
    value: float
    rail: float
    typical_var: float
    clipped: int
    count: int


Fault = _core.OutputFault | RailFault


_INT_RAILS: dict[np.dtype[Any], tuple[int, int]] = {}


def _int_rails(dtype: np.dtype[Any]) -> tuple[int, int]:
    """The smallest and largest value of an integer dtype (cached: np.iinfo is slow for a
    push of a few rows)."""
    r = _INT_RAILS.get(dtype)
    if r is None:
        info = np.iinfo(dtype)
        r = _INT_RAILS[dtype] = (int(info.min), int(info.max))
    return r


class _Rails:
    """Samples of an integer stream at its dtype's extremes (the ADC's rails: the output
    clips there), as runs ``[first row, length]`` per axis and side (0 low, 1 high) of the
    stream as given, and the rail values; for the samples each dwell holds on a rail.

    A chunk is searched only when one check of its extremes finds a sample on a rail (the
    streaming path; a whole array is instead searched dwell by dwell, only in the dwells
    that :func:`_rail_candidates` names). Float samples are not checked (their rail is not
    known)."""

    def __init__(self, runs: list[list[list[list[int]]]] | None = None,
                 value: list[list[float | None]] | None = None) -> None:
        # runs[axis][side]: (m, 2) int64 arrays [first row, length], in stream order
        self.runs: list[list[list[NDArray[np.int64]]]] = [[[], []] for _ in range(3)]
        if runs is not None:
            for ax in range(3):
                for side in (0, 1):
                    if runs[ax][side]:
                        self.runs[ax][side].append(
                            np.asarray(runs[ax][side], dtype=np.int64).reshape(-1, 2))
        self.value: list[list[float | None]] = (
            value if value is not None else [[None, None] for _ in range(3)])

    def copy(self) -> _Rails:
        out = _Rails(value=[list(v) for v in self.value])
        out.runs = [[list(side) for side in ax] for ax in self.runs]
        return out

    @staticmethod
    def valid_state(v: Any) -> bool:
        return (isinstance(v, dict) and isinstance(v.get("runs"), list) and len(v["runs"]) == 3
                and all(isinstance(ax, list) and len(ax) == 2 and all(
                    isinstance(side, list) and all(
                        isinstance(r, list) and len(r) == 2 and all(
                            type(x) is int and x >= 0 for x in r) for r in side)
                    for side in ax) for ax in v["runs"])
                and isinstance(v.get("value"), list) and len(v["value"]) == 3 and all(
                    isinstance(ax, list) and len(ax) == 2 and all(
                        x is None or isinstance(x, (int, float)) for x in ax)
                    for ax in v["value"]))

    def state(self) -> dict[str, Any]:
        return {"runs": [[self._all(side).tolist() for side in ax] for ax in self.runs],
                "value": self.value}

    @staticmethod
    def _all(parts: list[NDArray[np.int64]]) -> NDArray[np.int64]:
        return np.concatenate(parts) if parts else np.zeros((0, 2), dtype=np.int64)

    def add(self, a: NDArray[Any], offset: int, dtype: np.dtype[Any]) -> None:
        """Record the rail samples of a chunk ``a`` (values of ``dtype``, the input's dtype
        before any widening) that starts at stream row ``offset``."""
        self.commit(self.plan(a, offset, dtype))

    def plan(self, a: NDArray[Any], offset: int, dtype: np.dtype[Any]
             ) -> list[tuple[int, int, float, int, list[NDArray[np.int64]]]]:
        """What :meth:`add` would do, without doing it: per axis and side with rail samples,
        ``(axis, side, value, k, parts)``, the parts of its runs from index ``k`` on."""
        if dtype.kind not in "iu" or a.shape[0] == 0:
            return []
        lo, hi = _int_rails(dtype)
        rails = [(s, v) for s, v, hit in ((0, lo, np.minimum.reduce(a, axis=None) <= lo),
                                          (1, hi, np.maximum.reduce(a, axis=None) >= hi)) if hit]
        out: list[tuple[int, int, float, int, list[NDArray[np.int64]]]] = []
        for side, v in rails:
            if a.flags.c_contiguous:  # one comparison of the flat array, then split by axis
                hit = np.flatnonzero(a.reshape(-1) == v)
                where = [hit[hit % 3 == ax] // 3 for ax in range(3)]
            else:
                where = [np.flatnonzero(a[:, ax] == v) for ax in range(3)]
            for ax, at in enumerate(where):
                if at.size == 0:
                    continue
                at = at.astype(np.int64) + offset
                cut = np.flatnonzero(np.diff(at) != 1) + 1
                first = at[np.concatenate([[0], cut])]
                last = at[np.concatenate([cut - 1, [at.size - 1]])]
                new = np.column_stack([first, last - first + 1])
                parts = self.runs[ax][side]
                k, put = len(parts), []
                if parts and int(parts[-1][-1].sum()) == int(new[0, 0]):  # continues a run
                    prev = parts[-1].copy()
                    prev[-1, 1] += new[0, 1]
                    k, put = k - 1, [prev]
                    new = new[1:]
                if new.shape[0]:
                    put.append(new)
                out.append((ax, side, float(v), k, put))
        return out

    def commit(self, plan: list[tuple[int, int, float, int, list[NDArray[np.int64]]]]) -> None:
        """Apply a :meth:`plan` (assignments only: applying it again changes nothing)."""
        for ax, side, v, k, put in plan:
            self.value[ax][side] = v
            self.runs[ax][side][k:] = put

    def attach(self, d: DwellSet) -> None:
        """Set ``d.clipped`` and ``d.rail`` from the rail samples recorded, as
        :func:`_attach_rails` sets them from the samples."""
        if d.start is None or d.stop is None or not any(s for ax in self.runs for s in ax):
            return
        rail = np.array([[np.nan if v is None else v for v in ax] for ax in self.value])
        counts = np.zeros((len(d), 3, 2), dtype=np.int64)
        for k, ax, side in _rail_candidates(d, rail):
            r = self._all(self.runs[ax][side])
            at = np.array([d.start[k], d.stop[k]], dtype=np.int64)
            lo, hi = self._below(r, at)
            counts[k, ax, side] = hi - lo
        _set_clipped(d, counts, rail)

    @staticmethod
    def _below(r: NDArray[np.int64], x: NDArray[np.int64]) -> NDArray[np.int64]:
        """Rail rows before each row ``x`` (runs ``r`` sorted and apart)."""
        ends = r[:, 0] + r[:, 1]
        done = np.concatenate([[0], np.cumsum(r[:, 1])])
        j = np.searchsorted(r[:, 0], x, side="left")  # runs starting before x
        last = np.maximum(j - 1, 0)
        over = np.where(j > 0, np.maximum(ends[last] - x, 0), 0)
        return done[j] - over


def _clip_biases(p: float, n: int) -> bool:
    """Whether a fraction ``p`` of ``n`` Gaussian samples clipped at a rail shifts their mean
    by more than ``_PARTLY_CLIPPED_SE`` standard errors (the clip ``Q^-1(p)`` std away)."""
    if n < _FAULT_MIN_SAMPLES or p <= 0.0:
        return False
    delta = 0.0 if p >= 0.5 else statistics.NormalDist().inv_cdf(1.0 - p)
    return _clip_shortfall(delta) * math.sqrt(n) > _PARTLY_CLIPPED_SE


def _rail_candidates(d: DwellSet, rail: NDArray[np.float64]) -> list[tuple[int, int, int]]:
    """``(dwell, axis, side)`` whose samples could hold enough on the rail ``rail[axis,
    side]`` to bias the mean: c samples a distance D from the mean add c D^2 to the sum of
    squared deviations, so at most a fraction var (n - 1) / (n D^2) of them can be on it.
    Dwells far from every rail (nearly always all of them) need no search."""
    if d.var is None or d.count is None:
        return []
    n = d.count.astype(np.float64)[:, None]
    out = []
    for side in (0, 1):
        dist = np.abs(rail[None, :, side] - d.mean)  # NaN where no rail
        with np.errstate(divide="ignore", invalid="ignore"):
            pmax = np.where(dist > 0, d.var * (n - 1) / (n * dist**2), 1.0)
        # Below 1e-7 no dwell of under 1e10 samples can be biased by half a standard error.
        for k, ax in np.argwhere(np.isfinite(dist) & (pmax > 1e-7)).tolist():
            if _clip_biases(min(1.0, float(pmax[k, ax])), int(d.count[k])):
                out.append((k, ax, side))
    return out


def _set_clipped(d: DwellSet, counts: NDArray[np.int64], rail: NDArray[np.float64]) -> None:
    """``d.clipped`` and ``d.rail`` (the rails some dwell reached) when a count is > 0."""
    if not counts.any():
        return
    d.clipped = counts
    d.rail = np.where(counts.any(axis=0), rail, np.nan)


def _attach_rails(d: DwellSet, s: NDArray[Any], dtype: np.dtype[Any]) -> None:
    """Count the samples of ``s`` (values of ``dtype``, before any widening; rows of the
    stream as ``d.start`` / ``d.stop`` count them) on an integer dtype's rails, in the dwells
    where they could bias the mean (:func:`_rail_candidates`), into ``d.clipped`` /
    ``d.rail``."""
    if dtype.kind not in "iu" or d.start is None or d.stop is None:
        return
    lo, hi = _int_rails(dtype)
    rail = np.tile(np.array([float(lo), float(hi)]), (3, 1))
    cands = _rail_candidates(d, rail)
    if not cands:
        return
    counts = np.zeros((len(d), 3, 2), dtype=np.int64)
    for k, ax, side in cands:
        col = s[int(d.start[k]):int(d.stop[k]), ax]
        counts[k, ax, side] = np.count_nonzero(col == (hi if side else lo))
    _set_clipped(d, counts, rail)


def _from_raw(d: _core.DwellTableRaw, fs: float | None, units: str,
              drops: _Dropouts | None = None, rails: _Rails | None = None) -> DwellSet:
    start, stop, dropped = d.start, d.stop, int(d.dropped)
    vib = d.vibrating_bounds
    if drops is not None and drops.n:
        start, stop = drops.to_stream(start), drops.to_stream(stop - 1) + 1
        vib = np.stack([drops.to_stream(vib[:, 0]), drops.to_stream(vib[:, 1] - 1) + 1], axis=1)
        dropped += drops.n
    t: NDArray[Any] | None = d.t
    if t is None and fs is not None:
        t = 0.5 * (start + stop - 1) / fs
    nv = d.noise_var
    out = DwellSet(
        d.mean,
        d.var,
        d.count,
        t,
        d.temperature,
        start=start,
        stop=stop,
        fs=fs,
        threshold=d.threshold,
        noise_std=None if nv is None else np.sqrt(nv),
        units=units,
        half_mean=d.half_mean,
        inflation=d.inflation,
        lsb=d.lsb,
        dropped=dropped,
        vibrating=vib if d.threshold is not None else None,
        vibrating_std=d.vibrating_std if d.threshold is not None else None,
    )
    if rails is not None:
        rails.attach(out)
    if d.shorter is not None:
        w, m, tr, k = d.shorter
        out.shorter = (float(w), float(m), float(tr), int(k))
    return out


def dwell_stats(
    samples: ArrayLike,
    bounds: ArrayLike,
    *,
    t: ArrayLike | None = None,
    temperature: ArrayLike | None = None,
    fs: float | None = None,
    units: str = "",
    check_times: bool = True,
) -> DwellSet:
    """Per-dwell mean, variance (ddof = 1), count, half-dwell means and Allan noise inflation
    over ``[start, stop)`` bounds, in one pass.

    Parameters
    ----------
    samples : (N, 3) array
        Raw counts or physical units, any real dtype, memory layout or byte order (float64,
        float32, int16 and int32 are read in place; a DataFrame works too, its x, y, z
        columns taken by name as :func:`accelcal.io.read_stream` takes them). uint16 words
        that hold signed 16-bit values stored as unsigned (judged on the first rows as
        read_stream judges a file) are read as signed, with a warning.
    bounds : (k, 2) int
        ``[start, stop)`` sample indices, non-overlapping, at least 2 samples each.
    t : (N,) float, optional
        Sample times in s; each dwell's ``t`` is the mid time ``(t[start] + t[stop-1]) / 2``.
    temperature : (N,) float, optional
        Temperature per sample; each dwell gets its mean.
    fs : float, optional
        Sample rate in Hz (gives dwell times when ``t`` is absent; with ``t``, checked
        against it).

    check_times : bool
        Check ``t`` (module notes); False takes it as given (a clock in other units on
        purpose).

    A dwell containing NaN or inf samples is refused (see the module notes), and so are
    times ``t`` that do not advance or disagree with ``fs`` (module notes: a CalibrationError
    naming both and the likely unit of ``t``); times that step back now and then give a
    :class:`TimeStepWarning`.
    """
    given = signed16_samples(numeric_array(samples, "samples"))
    s = samples_array(given)
    b = bounds_array(bounds)
    n = s.shape[0]
    fsv = None if fs is None else positive(fs, "fs", " (Hz)")
    tc = channel(t, n, "t")
    steps = _check_times(tc, fsv, t) if check_times else []
    d = _core.dwell_stats_raw(s, b, tc, channel(temperature, n, "temperature"))
    out = _from_raw(d, fsv, units)
    _attach_rails(out, s, given.dtype)
    return _spanned(out, steps)


_SETTING_RANGES: dict[str, tuple[float, float, bool, str]] = {
    # name: (lo, hi, lo_open, unit)
    "window_s": (0.0, 1e6, True, "s"),
    "k": (0.0, 1e6, True, "(threshold factor)"),
    "min_dwell_s": (0.0, 1e6, False, "s"),
    "trim_s": (0.0, 1e6, False, "s"),
    "noise_quantile": (0.0, 1.0, True, ""),
    "block_s": (0.0, 1e6, True, "s"),
}


@dataclass(frozen=True)
class DetectorSettings:
    """Static-interval detector settings (defaults need no tuning on the real sessions).

    window_s : moving-window length, s, in (0, 1e6] (and at least 8 samples).
    k : a window is static when every axis's variance is below ``k`` x its noise variance;
        in (0, 1e6].
    min_dwell_s : shortest dwell kept after trimming, s, in [0, 1e6] (dwells always have at
        least 2 samples).
    trim_s : settling removed at both ends of each static run, s, in [0, 1e6].
    noise_quantile : quantile of the window variances taken as the noise level, in (0, 1).
    block_s : granularity of the compressed statistics, s, in (0, window_s]. A detecting
        accumulator keeps one block's statistics (about 150 bytes) per ``block_s`` of the
        stream until ``finish()``: about 27 MB per hour at 0.02 s, whatever the rate.
    noise_std : per-axis noise std (input units) to use instead of the data's own estimate.
    """

    window_s: float = 1.0
    k: float = 6.0
    min_dwell_s: float = 1.0
    trim_s: float = 0.1
    noise_quantile: float = 0.2
    block_s: float = 0.02
    noise_std: tuple[float, float, float] | None = field(default=None)

    def raw_kwargs(self) -> dict[str, Any]:
        """The settings for the Rust core, each checked (name, value and valid range)."""
        out: dict[str, Any] = {}
        for name, (lo, hi, lo_open, unit) in _SETTING_RANGES.items():
            out[name] = number(getattr(self, name), name, lo=lo, hi=hi, lo_open=lo_open, unit=unit)
        if out["noise_quantile"] >= 1.0:
            raise CalibrationError(
                f"noise_quantile must be a number in (0, 1); got {self.noise_quantile!r}"
            )
        nv = None
        if self.noise_std is not None:
            try:
                ns = numeric_array(self.noise_std, "noise_std").astype(np.float64).reshape(-1)
            except CalibrationError:
                ns = np.array([np.nan])
            if ns.shape != (3,) or not np.all(np.isfinite(ns)) or np.any(ns <= 0):
                raise CalibrationError(
                    f"noise_std must be three positive finite numbers (x, y, z); "
                    f"got {self.noise_std!r}"
                )
            nv = [float(v) ** 2 for v in ns]
        out["noise_var"] = nv
        return out

    @classmethod
    def merged(cls, base: DetectorSettings | None, kw: dict[str, Any]) -> DetectorSettings:
        """``base`` (or the defaults) with the fields in ``kw`` replaced (names checked)."""
        st = base if base is not None else cls()
        if not isinstance(st, DetectorSettings):
            raise CalibrationError(f"settings must be a DetectorSettings; got {st!r}")
        names = {f.name for f in fields(cls)}
        bad = sorted(set(kw) - names)
        if bad:
            raise CalibrationError(
                f"unknown detector setting(s) {bad}; valid: {sorted(names)}"
            )
        return cls(**{**st.__dict__, **kw}) if kw else st


def detect_dwells(
    samples: ArrayLike,
    fs: float | None = None,
    *,
    t: ArrayLike | None = None,
    temperature: ArrayLike | None = None,
    settings: DetectorSettings | None = None,
    units: str = "",
    check_times: bool = True,
    **kw: Any,
) -> DwellSet:
    """Find the static intervals of a stream and return their statistics.

    A window of ``window_s`` seconds slides over the stream; it is static when each axis's
    variance is below ``k`` times that axis's noise variance, which is estimated from the data
    itself (a low quantile of all window variances, i.e. the quiet parts of the recording).
    Static runs are trimmed by ``trim_s`` at both ends (settling) and kept when at least
    ``min_dwell_s`` long. The threshold used is returned as ``DwellSet.threshold`` (variance,
    squared input units) with the noise estimate ``DwellSet.noise_std``. Rows with NaN or inf
    samples are dropouts, left out of the stream the detector and the statistics see (counted
    in ``DwellSet.dropped``; a dwell may span them).

    ``samples`` is an (N, 3) array (then ``fs``, Hz, is required) or a
    :class:`~accelcal.io.Stream` from :func:`accelcal.io.read_stream`, whose ``fs``, ``t``,
    ``temperature`` and units are used unless given here. A DataFrame's x, y, z columns are
    taken by name, and uint16 words read as signed when they hold signed 16-bit values
    stored as unsigned, as :func:`dwell_stats` reads them.

    Keyword arguments override :class:`DetectorSettings` fields (``window_s=0.5`` ...).

    ``t`` (N,) gives the sample times in s, checked against ``fs`` (see the module notes): a
    clock in other units (ms, us, ns) or one that never advances is refused, one that steps
    back now and then warns (:class:`TimeStepWarning`). A Stream's own ``t`` is not checked
    again (:func:`accelcal.io.read_stream` notes what it found); ``check_times=False`` takes
    ``t`` as given.

    Raises
    ------
    DegenerateDataError
        When no static dwell is found (the message gives the noise level and the settings).
    CalibrationError
        Bad input, or sample times ``t`` that disagree with ``fs`` or do not advance.
    """
    t_given = t is not None
    samples, fs, t, temperature, units = stream_fields(samples, fs, t, temperature, units)
    given = signed16_samples(numeric_array(samples, "samples"))
    s = samples_array(given)
    if fs is None:
        raise CalibrationError("fs (the sample rate, Hz) is needed for an array of samples; "
                               "or pass the Stream that accelcal.io.read_stream returns")
    fsv = positive(fs, "fs", " (Hz)")
    st = DetectorSettings.merged(settings, kw)
    n = s.shape[0]
    tc, temp = channel(t, n, "t"), channel(temperature, n, "temperature")
    steps = _check_times(tc, fsv, t) if t_given and check_times else []
    drops = _Dropouts()
    if s.dtype.kind == "f":
        # The core counts the rows with NaN or inf as it goes (no extra pass over clean data);
        # when there are some, detect again on the stream without them.
        with contextlib.suppress(CalibrationError):
            d = _core.detect_dwells_raw(s, fsv, t=tc, temperature=temp, **st.raw_kwargs())
            if d.dropped == 0:
                return _spanned(_from_raw(d, fsv, units), steps)
        ok = _Dropouts.finite_rows(s)
        if ok is not None:
            drops.add(ok, 0)
            s = s[ok]
            tc = None if tc is None else tc[ok]
            temp = None if temp is None else temp[ok]
    try:
        d = _core.detect_dwells_raw(s, fsv, t=tc, temperature=temp, **st.raw_kwargs())
    except CalibrationError as e:
        e = drops.explain(e, n, samples_array(given))
        if "no static dwell found" in str(e) and _core.dwell_step_log(s) is not None:
            e = type(e)(f"{e}. Note: the stream reads as a log that holds only the rests (a "
                        "block of samples per pose, jumps between them, no motion recorded): "
                        "accelcal.io.step_log_dwells(samples, t, temperature, fs) takes its "
                        "blocks as the dwells")
        raise e from None
    out = _from_raw(d, fsv, units, drops)
    _attach_rails(out, s, given.dtype)  # integer samples: no dropouts, rows of the stream
    return _spanned(out, steps)


def stream_fields(data: Any, fs: float | None, t: Any, temperature: Any, units: str = ""
                  ) -> tuple[Any, float | None, Any, Any, str]:
    """``(samples, fs, t, temperature, units)`` of ``data``: a :class:`~accelcal.io.Stream`'s
    own where not given (a Stream without a rate keeps ``fs`` None), else ``data`` and the
    arguments as they are."""
    from .io import Stream

    if not isinstance(data, Stream):
        return data, fs, t, temperature, units
    return (data.samples, data.fs if fs is None else fs, data.t if t is None else t,
            data.temperature if temperature is None else temperature, units)


def _refuse_nonfinite_channel(v: NDArray[np.float64] | None, what: str, at: int,
                              kept: NDArray[np.intp] | None) -> None:
    """A CalibrationError, as the core words it but with the row of the stream, when the
    chunk's channel ``v`` (time, temperature) holds NaN or inf. ``at``: the stream row of
    the chunk's first row; ``kept``: the chunk rows ``v`` holds (dropouts left out)."""
    if v is None or v.size == 0 or math.isfinite(float(np.add.reduce(v))):
        return
    bad = np.flatnonzero(~np.isfinite(v))
    if bad.size == 0:  # finite values whose sum overflows
        return
    i = int(bad[0])
    row = i if kept is None else int(kept[i])
    x = float(v[i])
    shown = "NaN" if math.isnan(x) else ("inf" if x > 0 else "-inf")
    raise CalibrationError(
        f"{what} contains NaN or inf: {bad.size} value(s) in this chunk, the first at row "
        f"{at + row} of the stream (row {row} of the chunk) ({shown}); {what} must be finite "
        "everywhere"
    )


def _bounds_settings_error(settings: Any, kw: dict[str, Any]) -> CalibrationError:
    """The error of a ``DwellAccumulator(bounds, ...)`` given detector settings (which do
    not apply: the dwells are known) or unknown keywords."""
    names = sorted(f.name for f in fields(DetectorSettings))
    bad = sorted(set(kw) - set(names))
    if bad:
        return CalibrationError(
            f"unknown keyword argument(s) {bad} of DwellAccumulator; it takes bounds or fs, "
            f"settings, units, check_times and, with fs (detection), the detector settings "
            f"{names}"
        )
    given = sorted(kw) + (["settings"] if settings is not None else [])
    return CalibrationError(
        f"detector settings {given} do not apply with known bounds: the dwells are given, "
        "nothing is detected; drop them, or give fs= without bounds to detect the dwells"
    )


class _SignedWords:
    """The first uint16 rows pushed to a :class:`DwellAccumulator`, judged as
    :func:`accelcal.io.read_stream` judges a file's head (:func:`stored_signed16`, on up to
    its first 10 000 rows) each time they double: when they hold signed 16-bit values
    stored as unsigned, the warning text, once. The accumulator cannot read them as signed
    (the rows pushed before the finding were read as given, whatever the chunking)."""

    def __init__(self) -> None:
        self.rows: list[NDArray[Any]] = []
        self.n = 0
        self.next = 16
        self.done = False

    def plan(self, a: NDArray[Any]) -> tuple[_SignedWords, str | None]:
        """``(state with a added, warning text or None)``, this state unchanged."""
        if self.done or a.dtype != np.uint16:
            return self, None
        new = _SignedWords.__new__(_SignedWords)
        new.rows, new.n, new.next, new.done = list(self.rows), self.n, self.next, self.done
        return new, new.add(a)

    def add(self, a: NDArray[Any]) -> str | None:
        if self.done or a.dtype != np.uint16:
            return None
        from .io import _SNIFF_ROWS

        take = a[:_SNIFF_ROWS - self.n]
        self.rows.append(np.array(take))  # a copy: a DAQ reuses its buffer
        self.n += take.shape[0]
        if self.n < min(self.next, _SNIFF_ROWS):
            return None
        self.next = 2 * self.n
        head = np.concatenate(self.rows)
        self.rows = [head]
        found = stored_signed16(head)
        if found or self.n >= _SNIFF_ROWS:
            self.done, self.rows = True, []
        if not found:
            return None
        return (
            f"{signed16_text('chunk')} over the first {self.n} rows pushed, as "
            "accelcal.io.read_stream and detect_dwells read them; the accumulator reads "
            "uint16 as unsigned (it cannot judge a stream chunk by chunk), so its dwells "
            "come out wrong: push chunk.view(np.int16) (or chunk.astype(np.int32) to keep "
            "them unsigned and silence this)"
        )


def _state_crc(meta: dict[str, Any], raw: bytes) -> int:
    """CRC-32 of a state's header fields (sorted, without the CRC itself) and core bytes."""
    return zlib.crc32(json.dumps(meta, sort_keys=True).encode() + b"\n" + raw)


@dataclass(slots=True)
class _Commit:
    """What a :meth:`DwellAccumulator.push` changes, computed before anything changes: the
    core's position before and after the chunk, and the Python-side state with it added."""

    before: int
    after: int
    clock: _Clock
    drops: tuple[int, list[list[int]], int] | None
    rails: list[tuple[int, int, float, int, list[NDArray[np.int64]]]]
    words: _SignedWords
    steps: list[int]


class DwellAccumulator:
    """Streaming per-dwell statistics for acquisition scripts.

    ``DwellAccumulator(bounds)`` accumulates known ``[start, stop)`` dwells;
    ``DwellAccumulator(fs=...)`` (optionally with detector settings) keeps compressed block
    statistics and detects dwells at :meth:`finish`. Push chunks of any size; dwells may span
    chunks. :meth:`finish` returns exactly what :func:`dwell_stats` / :func:`detect_dwells`
    return on the concatenated stream (bit for bit, whatever the chunking).

    Safe to share between threads (e.g. a GUI thread reading :attr:`position` while another
    pushes). A push that fails (bad shape, NaN time, NaN or inf samples inside a dwell of
    the bounds, ...) keeps nothing of its chunk: the accumulator stays usable with what it
    held before. It pickles, and :meth:`to_state` / :meth:`from_state` checkpoint a stream
    mid-dwell so that another process resumes it with bit-identical results.

    Sample times ``t`` are checked as :func:`detect_dwells` checks them (module notes), on
    the times pushed so far: the interval from the last time of one chunk to the first of
    the next counts, so chunks are judged as the stream in one push would be (a
    disagreement with ``fs`` is refused at the push that shows it, once 16 intervals are
    in). A step back or forward jump of the clock warns once per accumulator, and
    :meth:`finish` names the dwells that span one. ``check_times=False`` takes the times as
    given (times already checked, as :func:`accelcal.io.read_stream` checks and notes them).

    Interrupts: a push interrupted by an exception that a signal handler raises (Ctrl-C's
    KeyboardInterrupt, a SIGTERM handler's SystemExit) keeps its chunk whole or not at all,
    and :attr:`position` says which (resume from it). A signal handler may call
    :attr:`position`, :meth:`to_state` and :meth:`finish` during a push of the same thread
    (they see the chunk whole or not at all); a push from there is refused (RuntimeError).

    uint16 chunks are read as given (unsigned): whether a stream's words are signed 16-bit
    values stored as unsigned cannot be judged chunk by chunk. When the first rows pushed
    look so, a warning says to push ``chunk.view(np.int16)`` (:func:`detect_dwells` on the
    whole stream reads them as signed). With bounds, detector settings and unknown keywords
    are refused. Errors name rows of the stream, not of the chunk.
    """

    def __init__(
        self,
        bounds: ArrayLike | None = None,
        *,
        fs: float | None = None,
        settings: DetectorSettings | None = None,
        units: str = "",
        check_times: bool = True,
        **kw: Any,
    ) -> None:
        self.fs = None if fs is None else positive(fs, "fs", " (sample rate in Hz)")
        self.check_times = bool(check_times)
        if not isinstance(units, str):
            raise CalibrationError(f"units must be a string; got {units!r}")
        self.units = units
        self._drops = _Dropouts()
        self._rails = _Rails()
        self._clock = _Clock()
        self._words = _SignedWords()
        self._bounds: NDArray[np.int64] | None = None
        self._steps: list[int] = []  # rows of the clock steps seen (_clock_steps)
        self._lock = threading.RLock()
        self._pending: _Commit | None = None
        self._pushing = False
        if bounds is not None:
            if settings is not None or kw:
                raise _bounds_settings_error(settings, kw)
            rate = _to_float(bounds) if np.ndim(bounds) == 0 else None
            if rate is not None:
                raise CalibrationError(
                    f"bounds must have shape (k, 2) [start, stop); got the single number "
                    f"{bounds!r}: to detect the dwells at a sample rate, give it as fs= "
                    f"(DwellAccumulator(fs={rate:g}))"
                )
            self._bounds = bounds_array(bounds)
            self._raw = _core.RawDwellAccumulator(bounds=self._bounds)
            self.mode = "bounds"
        elif self.fs is not None:
            st = DetectorSettings.merged(settings, kw)
            self._raw = _core.RawDwellAccumulator(fs=self.fs, **st.raw_kwargs())
            self.mode = "detect"
        else:
            raise CalibrationError("give bounds (k, 2) or fs (Hz) for automatic detection")

    @property
    def position(self) -> int:
        """Samples pushed so far (with the dropouts that detection leaves out)."""
        with self._lock:
            self._settle()
            return int(self._raw.position) + self._drops.n

    def _settle(self) -> None:
        """Complete a push whose chunk the core took but whose commit of the Python-side
        state was cut short (an exception raised by a signal handler, e.g. KeyboardInterrupt,
        as the core returned), so that every reader sees the chunk whole or not at all. Call
        with the lock held."""
        rec = self._pending
        if rec is not None and int(self._raw.position) == rec.after:
            self._apply(rec)

    def _apply(self, rec: _Commit) -> None:
        """Commit the Python-side state of a push (assignments only: an interrupted commit is
        completed by applying it again)."""
        self._clock = rec.clock
        if rec.drops is not None:
            self._drops.commit(rec.drops)
        if rec.rails:
            self._rails.commit(rec.rails)
        self._words = rec.words
        self._steps = rec.steps
        self._pending = None

    def push(
        self,
        chunk: ArrayLike,
        t: ArrayLike | None = None,
        temperature: ArrayLike | None = None,
    ) -> None:
        """Add a chunk (m, 3) of samples (and optional per-sample t in s, temperature).

        On error nothing of the chunk is kept: the accumulator holds what it held before the
        call, stays usable, and the message says so. With bounds, a chunk with NaN or inf
        samples inside a dwell is refused here (outside every dwell they are harmless);
        with detection they are dropouts (module notes). Times ``t`` that disagree with
        ``fs`` or do not advance are refused; a step back or forward jump warns
        (:class:`TimeStepWarning`). Warnings come before anything is kept: one turned into
        an error (``warnings.simplefilter("error")``) keeps nothing of the chunk either. An
        interrupt (KeyboardInterrupt) keeps the chunk whole or not at all (class notes).
        An empty chunk keeps nothing, but its ``t`` and ``temperature`` must be empty too.
        """
        try:
            a = numeric_array(chunk, "chunk")
            if a.ndim == 2 and a.shape[0] == 0 and a.shape[1] == 3:
                channel(t, 0, "t")  # nothing to keep, but the channels must match it
                channel(temperature, 0, "temperature")
                return
            c = samples_array(a, "chunk")
            m = c.shape[0]
            tc, temp = channel(t, m, "t"), channel(temperature, m, "temperature")
            ok = _Dropouts.finite_rows(c)
            if self.mode == "detect" and ok is not None:
                # dropouts: left out of the stream the detector sees
                c = c[ok]
                tc = None if tc is None else tc[ok]
                temp = None if temp is None else temp[ok]
            with self._lock:
                if self._pushing:
                    raise RuntimeError(
                        "DwellAccumulator.push called while a push of this accumulator is under "
                        "way in the same thread (from a signal handler or a warnings hook): "
                        "nothing of this chunk was kept; push it after that push returns "
                        "(position, to_state and finish may be called there)"
                    )
                self._pushing = True
                try:
                    if self._pending is not None:
                        self._settle()
                    before = int(self._raw.position)
                    at = before + self._drops.n
                    kept = (np.flatnonzero(ok) if self.mode == "detect" and ok is not None
                            else None)
                    _refuse_nonfinite_channel(tc, "t", at, kept)
                    _refuse_nonfinite_channel(temp, "temperature", at, kept)
                    if self.mode == "bounds" and ok is not None:
                        self._refuse_nonfinite_in_dwells(ok, at)
                    clock, warn, steps = self._clock, None, self._steps
                    if self.check_times:
                        try:
                            clock, warn = self._clock.check(tc, self.fs, at)
                        except CalibrationError as e:
                            raise _coarse_times(e, t, self.fs) from None
                        if tc is not None and len(steps) < _CLOCK_STEPS_KEPT and (
                                clock.back > self._clock.back or (
                                    clock.long > self._clock.long and clock.judges_jumps())):
                            steps = steps + _clock_steps(
                                tc, None if self.fs is None else 1.0 / self.fs,
                                self._clock.last, at, kept)[:_CLOCK_STEPS_KEPT - len(steps)]
                    words, words_warn = self._words.plan(a)
                    drops = (self._drops.plan(ok, at) if self.mode == "detect" and ok is not None
                             else None)
                    rails = (self._rails.plan(c, at, a.dtype) if a.dtype.kind in "iu"
                             else [])  # integers: no dropouts
                    rec = _Commit(before, before + c.shape[0], clock, drops, rails, words, steps)
                    # Warnings before the commit: one turned into an error keeps nothing.
                    for text, cat in (() if warn is None and words_warn is None else
                                      ((warn, TimeStepWarning), (words_warn, UserWarning))):
                        if text is None:
                            continue
                        try:
                            warnings.warn(text, cat, stacklevel=2)
                        except Warning as w:
                            raise type(w)(
                                f"{w} (raised as an error: nothing of this chunk was kept, the "
                                f"accumulator still holds the {at} samples pushed before)"
                            ) from None
                    # The commit: the core's push is one call, and whatever interrupts this
                    # (a KeyboardInterrupt as the core returns, say) finds the Python-side
                    # state in _pending, completed here or by the next reader (_settle).
                    self._pending = rec
                    if rec.after == rec.before:  # every row a dropout: nothing for the core
                        self._apply(rec)
                    else:
                        try:
                            self._raw.push(c, tc, temp)
                        except BaseException:  # the core's refusal, or an interrupt
                            if int(self._raw.position) == rec.after:
                                self._apply(rec)  # the core took it: complete the commit
                            self._pending = None
                            raise
                        self._apply(rec)
                finally:
                    self._pushing = False
        except CalibrationError as e:
            raise type(e)(
                f"{e} (nothing of this chunk was kept: the accumulator still holds the "
                f"{self.position} samples pushed before and stays usable)"
            ) from None

    def _refuse_nonfinite_in_dwells(self, ok: NDArray[np.bool_], at: int) -> None:
        """A CalibrationError, as :func:`dwell_stats` words it, when a row of the chunk
        starting at stream row ``at`` that ``ok`` leaves out lies inside a dwell of the
        bounds (a state written before the bounds were kept cannot tell: the dwell is then
        refused at :meth:`finish`)."""
        if self._bounds is None:
            return
        bad = np.flatnonzero(~ok) + at
        lo = np.searchsorted(bad, self._bounds[:, 0], side="left")
        hi = np.searchsorted(bad, self._bounds[:, 1], side="left")
        hit = np.flatnonzero(hi > lo)
        if hit.size:
            k = int(hit[0])
            b0, b1 = (int(v) for v in self._bounds[k])
            raise CalibrationError(
                f"samples contain NaN or inf in dwell {k} [{b0}, {b1}): "
                f"{int(hi[k] - lo[k])} row(s) in this chunk, the first at sample "
                f"{int(bad[lo[k]])}; a dwell given by bounds must be complete (cut it out of "
                "the bounds, or use DwellAccumulator(fs=...), whose detection treats "
                "non-finite samples as dropouts)"
            )

    def finish(self) -> DwellSet:
        """The dwell table of everything pushed so far (the accumulator stays usable).

        With bounds, every dwell must be complete (its ``stop`` pushed): before that a
        CalibrationError names the dwells complete and those still waiting for samples
        (push the rest and call again). Detection takes what has been pushed.
        """
        with self._lock:
            self._settle()
            drops = _Dropouts([list(r) for r in self._drops.runs])
            rails = self._rails.copy()
            steps = list(self._steps)
            n = int(self._raw.position) + drops.n
            try:
                raw = self._raw.finish()
            except CalibrationError as e:
                raise self._incomplete(n) or drops.explain(e, n) from None
        return _spanned(_from_raw(raw, self.fs, self.units, drops, rails), steps, stacklevel=2)

    def _incomplete(self, n: int) -> CalibrationError | None:
        """With bounds beyond the ``n`` samples pushed: the error naming the dwells complete
        and those that are not; None otherwise."""
        b = self._bounds
        if b is None or int(b[:, 1].max()) <= n:
            return None
        done = np.flatnonzero(b[:, 1] <= n)
        wait = np.flatnonzero(b[:, 1] > n)

        def some(ix: NDArray[np.intp]) -> str:
            words = [f"{int(i)} [{int(b[i, 0])}, {int(b[i, 1])})" for i in ix[:4]]
            return ", ".join(words) + (f" and {ix.size - 4} more" if ix.size > 4 else "")

        have = (f"dwell(s) {some(done)} complete" if done.size else "no dwell complete yet")
        return CalibrationError(
            f"with bounds, finish needs every dwell complete: dwell(s) {some(wait)} out of "
            f"range of the {n} samples pushed so far (the bounds reach sample "
            f"{int(b[:, 1].max())}), {have}; push the rest of the stream and call finish "
            "again (the accumulator is unchanged)"
        )

    # ---- checkpoints ----------------------------------------------------------------------
    def to_state(self) -> bytes:
        """The complete state as bytes (versioned; the core's state plus ``fs`` and units)."""
        with self._lock:
            self._settle()
            meta = {"version": _STATE_VERSION, "fs": self.fs, "units": self.units,
                    "mode": self.mode, "dropouts": self._drops.runs,
                    "clock": self._clock.state(), "check_times": self.check_times,
                    "rails": self._rails.state(),
                    "bounds": None if self._bounds is None else self._bounds.tolist()}
            if self._steps:  # absent when there are none (and from older states)
                meta["steps"] = self._steps
            raw = self._raw.to_state()
            meta["crc32"] = _state_crc(meta, raw)
            return _STATE_MAGIC + json.dumps(meta).encode() + b"\n" + raw

    @classmethod
    def from_state(cls, state: bytes) -> DwellAccumulator:
        """Rebuild an accumulator from :meth:`to_state` bytes (checked: corrupted or
        truncated bytes give a CalibrationError)."""
        if not isinstance(state, (bytes, bytearray, memoryview)):
            raise CalibrationError(f"state must be bytes; got {type(state).__name__}")
        b = bytes(state)
        if not b.startswith(_STATE_MAGIC) or b"\n" not in b[len(_STATE_MAGIC):]:
            raise CalibrationError("not a DwellAccumulator state (bad header)")
        head, raw = b[len(_STATE_MAGIC):].split(b"\n", 1)
        try:
            meta = json.loads(head)
            version, fs, units, mode = meta["version"], meta["fs"], meta["units"], meta["mode"]
            runs = meta.get("dropouts", []) if version >= 2 else []
            clock, bounds = meta.get("clock"), meta.get("bounds")  # absent from older states
            check_times = meta.get("check_times", True)
            rails = meta.get("rails")  # absent from older states
            steps = meta.get("steps", [])
        except (ValueError, KeyError, TypeError, AttributeError):
            raise CalibrationError("not a DwellAccumulator state (bad header)") from None
        if version not in (1, 2, _STATE_VERSION):
            raise CalibrationError(
                f"DwellAccumulator state version {version!r} is not supported "
                f"(this version reads 1 to {_STATE_VERSION})"
            )
        if version >= 3 and meta.get("crc32") != _state_crc(
                {k: v for k, v in meta.items() if k != "crc32"}, raw):
            raise CalibrationError("DwellAccumulator state is corrupted (its CRC-32 does not "
                                   "match: bytes changed since to_state wrote them)")
        if mode not in ("bounds", "detect") or not isinstance(units, str) or not (
            isinstance(runs, list) and all(
                isinstance(r, list) and len(r) == 2 and all(
                    type(v) is int and v >= 0 for v in r) for r in runs)
        ) or not (clock is None or _Clock.valid_state(clock)) or not (
            rails is None or _Rails.valid_state(rails)) or not (
            isinstance(steps, list) and all(type(v) is int and v >= 0 for v in steps)
        ) or not isinstance(
            check_times, bool) or not (
            bounds is None or (mode == "bounds" and isinstance(bounds, list) and bounds and all(
                isinstance(r, list) and len(r) == 2 and all(type(v) is int for v in r)
                for r in bounds))
        ):
            raise CalibrationError("not a DwellAccumulator state (bad header)")
        self = cls.__new__(cls)
        self.fs = None if fs is None else positive(fs, "fs", " (Hz)")
        self.units = units
        self.mode = mode
        self._drops = _Dropouts(runs)
        self._rails = _Rails() if rails is None else _Rails(rails["runs"], rails["value"])
        self._clock = _Clock(clock)
        self._words = _SignedWords()
        self._steps = steps
        self.check_times = check_times
        self._bounds = None if bounds is None else np.asarray(bounds, dtype=np.int64)
        self._lock = threading.RLock()
        self._pending = None
        self._pushing = False
        self._raw = _core.RawDwellAccumulator.from_state(raw)
        return self

    def __reduce__(self) -> tuple[Any, ...]:
        return (DwellAccumulator.from_state, (self.to_state(),))

