"""Per-dwell statistics of high-rate accelerometer streams (numerics in Rust)."""

from __future__ import annotations

import io
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._core import CalibrationError
from ._files import atomic_write
from ._validate import bounds_array, channel, positive, samples_array

__all__ = [
    "DetectorSettings",
    "DwellAccumulator",
    "DwellSet",
    "detect_dwells",
    "dwell_stats",
]

_CSV_MAGIC = "# accelcal dwell table v1"
_AXES = ("x", "y", "z")


def _opt(a: Any, k: int, name: str) -> NDArray[np.float64] | None:
    if a is None:
        return None
    v = np.asarray(a, dtype=np.float64).reshape(-1)
    if v.shape != (k,):
        raise CalibrationError(f"{name} must have shape ({k},); got {np.shape(a)}")
    return v


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
    threshold, noise_std : (3,) float64 or None
        For detected dwells: the per-axis variance threshold and the noise std the detector
        estimated from the data (input units).
    fs : float or None
        Sample rate of the stream, Hz.
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
    ) -> None:
        m = np.array(mean, dtype=np.float64, copy=True)
        if m.ndim == 1 and m.size == 3:
            m = m.reshape(1, 3)
        if m.ndim != 2 or m.shape[1] != 3:
            raise CalibrationError(f"mean must have shape (k, 3); got {np.shape(mean)}")
        if not np.all(np.isfinite(m)):
            bad = np.where(~np.all(np.isfinite(m), axis=1))[0]
            raise CalibrationError(f"mean contains NaN or inf in dwell(s) {bad.tolist()}")
        k = m.shape[0]
        self.mean: NDArray[np.float64] = m
        self.var: NDArray[np.float64] | None = None
        if var is not None:
            v = np.array(var, dtype=np.float64, copy=True).reshape(-1, 3) if np.size(var) else None
            if v is None or v.shape != (k, 3):
                raise CalibrationError(f"var must have shape ({k}, 3); got {np.shape(var)}")
            if np.any(v < 0):
                raise CalibrationError("var must be non-negative")
            self.var = v
        self.count: NDArray[np.int64] | None = None
        if count is not None:
            c = np.asarray(count).reshape(-1)
            if c.shape != (k,):
                raise CalibrationError(f"count must have shape ({k},); got {np.shape(count)}")
            if np.any(c < 1):
                raise CalibrationError("count must be >= 1 for every dwell")
            self.count = c.astype(np.int64)
        self.t = _opt(t, k, "t")
        self.temperature = _opt(temperature, k, "temperature")
        self.start = None if start is None else np.asarray(start, dtype=np.int64).reshape(-1)
        self.stop = None if stop is None else np.asarray(stop, dtype=np.int64).reshape(-1)
        for nm, arr in (("start", self.start), ("stop", self.stop)):
            if arr is not None and arr.shape != (k,):
                raise CalibrationError(f"{nm} must have shape ({k},)")
        self.fs = None if fs is None else float(fs)
        self.threshold = None if threshold is None else np.asarray(threshold, dtype=np.float64)
        self.noise_std = None if noise_std is None else np.asarray(noise_std, dtype=np.float64)
        self.units = units

    def __len__(self) -> int:
        return int(self.mean.shape[0])

    def __repr__(self) -> str:
        extra = []
        if self.var is not None:
            extra.append("var")
        if self.t is not None:
            extra.append("t")
        if self.temperature is not None:
            extra.append("temperature")
        return f"DwellSet({len(self)} dwells; {', '.join(['mean', *extra])})"

    def __getitem__(self, idx: Any) -> DwellSet:
        """A subset of dwells (index, slice, boolean mask or index array)."""
        sel = np.arange(len(self))[idx]
        sel = np.atleast_1d(sel)

        def take(a: NDArray[Any] | None) -> Any:
            return None if a is None else a[sel]

        return DwellSet(
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
        )

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

    # ---- CSV round trip -------------------------------------------------------------------
    def to_csv(self, path: str | os.PathLike[str] | None = None) -> str:
        """Write the table as CSV (atomically when ``path`` is given); return the text.

        Full float64 precision (``%.17g``), so :meth:`from_csv` gives back identical numbers.
        """
        k = len(self)
        cols: list[tuple[str, NDArray[Any]]] = []
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
        buf = io.StringIO()
        buf.write(_CSV_MAGIC + "\n")
        if self.units:
            buf.write(f"# units: {self.units}\n")
        if self.fs is not None:
            buf.write(f"# fs_hz: {self.fs!r}\n")
        if self.threshold is not None:
            buf.write("# threshold: " + " ".join(repr(float(v)) for v in self.threshold) + "\n")
        if self.noise_std is not None:
            buf.write("# noise_std: " + " ".join(repr(float(v)) for v in self.noise_std) + "\n")
        buf.write(",".join(n for n, _ in cols) + "\n")
        for r in range(k):
            cells = []
            for _, c in cols:
                v = c[r]
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
        names = [c.strip() for c in body[0].split(",")]
        if not all(f"mean_{a}" in names for a in _AXES):
            raise CalibrationError(f"dwell table needs columns mean_x, mean_y, mean_z; got {names}")
        rows = [r.split(",") for r in body[1:]]
        if any(len(r) != len(names) for r in rows):
            raise CalibrationError("dwell table rows do not all have the header's column count")
        data = {n: [r[i] for r in rows] for i, n in enumerate(names)}

        def f(n: str) -> NDArray[np.float64] | None:
            return np.array(data[n], dtype=np.float64) if n in data else None

        def i(n: str) -> NDArray[np.int64] | None:
            return np.array(data[n], dtype=np.int64) if n in data else None

        def cols(prefix: str) -> NDArray[np.float64]:
            return np.column_stack(
                [np.array(data[f"{prefix}_{a}"], dtype=np.float64) for a in _AXES]
            )

        mean = cols("mean")
        var = cols("var") if all(f"var_{a}" in data for a in _AXES) else None

        def vec(key: str) -> NDArray[np.float64] | None:
            return np.array(meta[key].split(), dtype=np.float64) if key in meta else None

        return cls(
            mean,
            var,
            i("count"),
            f("t_s"),
            f("temperature"),
            start=i("start"),
            stop=i("stop"),
            fs=float(meta["fs_hz"]) if "fs_hz" in meta else None,
            threshold=vec("threshold"),
            noise_std=vec("noise_std"),
            units=meta.get("units", ""),
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict of lists."""
        out: dict[str, Any] = {"n_dwells": len(self), "units": self.units, "fs_hz": self.fs}
        for name in ("start", "stop", "count", "t", "temperature", "mean", "var"):
            v = getattr(self, name)
            out[name] = None if v is None else v.tolist()
        out["threshold"] = None if self.threshold is None else self.threshold.tolist()
        out["noise_std"] = None if self.noise_std is None else self.noise_std.tolist()
        return out

    def table(self, max_rows: int | None = None) -> str:
        """A readable fixed-width table."""
        hdr = f"{'#':>3} {'start':>9} {'stop':>9} {'dur_s':>7} "
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
            ln = f"{r:>3} {st:>9} {sp:>9} {dur:>7} "
            ln += " ".join(f"{v:>14.6f}" for v in self.mean[r]) + " "
            if self.var is not None:
                ln += " ".join(f"{np.sqrt(v):>10.3g}" for v in self.var[r])
            if self.temperature is not None:
                ln += f" {self.temperature[r]:>8.3f}"
            lines.append(ln)
        if max_rows is not None and k > max_rows:
            lines.append(f"... {k - max_rows} more")
        return "\n".join(lines)


def _from_raw(d: dict[str, Any], fs: float | None, units: str) -> DwellSet:
    t = d["t"]
    if t is None and fs is not None:
        t = 0.5 * (d["start"] + d["stop"] - 1) / fs
    nv = d.get("noise_var")
    return DwellSet(
        d["mean"],
        d["var"],
        d["count"],
        t,
        d["temperature"],
        start=d["start"],
        stop=d["stop"],
        fs=fs,
        threshold=d.get("threshold"),
        noise_std=None if nv is None else np.sqrt(nv),
        units=units,
    )


def dwell_stats(
    samples: ArrayLike,
    bounds: ArrayLike,
    *,
    t: ArrayLike | None = None,
    temperature: ArrayLike | None = None,
    fs: float | None = None,
    units: str = "",
) -> DwellSet:
    """Per-dwell mean, variance (ddof = 1) and count over ``[start, stop)`` bounds.

    Parameters
    ----------
    samples : (N, 3) array of float64, float32, int16 or int32
        Raw counts or physical units; read in place whatever the strides.
    bounds : (k, 2) int
        ``[start, stop)`` sample indices, non-overlapping.
    t : (N,) float, optional
        Sample times in s; each dwell's ``t`` is the mid time ``(t[start] + t[stop-1]) / 2``.
    temperature : (N,) float, optional
        Temperature per sample; each dwell gets its mean.
    fs : float, optional
        Sample rate in Hz (gives dwell times when ``t`` is absent).
    """
    s = samples_array(samples)
    b = bounds_array(bounds)
    n = s.shape[0]
    fsv = None if fs is None else positive(fs, "fs", " (Hz)")
    d = _core.dwell_stats_raw(
        s, b, channel(t, n, "t"), channel(temperature, n, "temperature")
    )
    return _from_raw(d, fsv, units)


@dataclass(frozen=True)
class DetectorSettings:
    """Static-interval detector settings (defaults need no tuning on the real sessions).

    window_s : moving-window length, s.
    k : a window is static when every axis's variance is below ``k`` x its noise variance.
    min_dwell_s : shortest dwell kept after trimming, s.
    trim_s : settling removed at both ends of each static run, s.
    noise_quantile : quantile of the window variances taken as the noise level.
    block_s : granularity of the compressed statistics, s.
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
        nv = None
        if self.noise_std is not None:
            ns = np.asarray(self.noise_std, dtype=np.float64).reshape(-1)
            if ns.shape != (3,) or not np.all(np.isfinite(ns)) or np.any(ns <= 0):
                raise CalibrationError("noise_std must be three positive numbers (x, y, z)")
            nv = [float(v) ** 2 for v in ns]
        return dict(
            window_s=float(self.window_s),
            k=float(self.k),
            min_dwell_s=float(self.min_dwell_s),
            trim_s=float(self.trim_s),
            noise_quantile=float(self.noise_quantile),
            block_s=float(self.block_s),
            noise_var=nv,
        )


def detect_dwells(
    samples: ArrayLike,
    fs: float,
    *,
    t: ArrayLike | None = None,
    temperature: ArrayLike | None = None,
    settings: DetectorSettings | None = None,
    units: str = "",
    **kw: Any,
) -> DwellSet:
    """Find the static intervals of a stream and return their statistics.

    A window of ``window_s`` seconds slides over the stream; it is static when each axis's
    variance is below ``k`` times that axis's noise variance, which is estimated from the data
    itself (a low quantile of all window variances, i.e. the quiet parts of the recording).
    Static runs are trimmed by ``trim_s`` at both ends (settling) and kept when at least
    ``min_dwell_s`` long. The threshold used is returned as ``DwellSet.threshold`` (variance,
    squared input units) with the noise estimate ``DwellSet.noise_std``.

    Keyword arguments override :class:`DetectorSettings` fields (``window_s=0.5`` ...).
    """
    s = samples_array(samples)
    fsv = positive(fs, "fs", " (sample rate in Hz)")
    st = settings or DetectorSettings()
    if kw:
        st = DetectorSettings(**{**st.__dict__, **kw})
    n = s.shape[0]
    d = _core.detect_dwells_raw(
        s,
        fsv,
        t=channel(t, n, "t"),
        temperature=channel(temperature, n, "temperature"),
        **st.raw_kwargs(),
    )
    return _from_raw(d, fsv, units)


class DwellAccumulator:
    """Streaming per-dwell statistics for acquisition scripts.

    ``DwellAccumulator(bounds)`` accumulates known ``[start, stop)`` dwells;
    ``DwellAccumulator(fs=...)`` (optionally with detector settings) keeps compressed block
    statistics and detects dwells at :meth:`finish`. Push chunks of any size; dwells may span
    chunks. :meth:`finish` returns exactly what :func:`dwell_stats` / :func:`detect_dwells`
    return on the concatenated stream.
    """

    def __init__(
        self,
        bounds: ArrayLike | None = None,
        *,
        fs: float | None = None,
        settings: DetectorSettings | None = None,
        units: str = "",
        **kw: Any,
    ) -> None:
        self.fs = None if fs is None else positive(fs, "fs", " (sample rate in Hz)")
        self.units = units
        self._dtype: np.dtype[Any] | None = None
        if bounds is not None:
            self._raw = _core.RawDwellAccumulator(bounds=bounds_array(bounds))
            self.mode = "bounds"
        elif self.fs is not None:
            st = settings or DetectorSettings()
            if kw:
                st = DetectorSettings(**{**st.__dict__, **kw})
            self._raw = _core.RawDwellAccumulator(fs=self.fs, **st.raw_kwargs())
            self.mode = "detect"
        else:
            raise CalibrationError("give bounds (k, 2) or fs (Hz) for automatic detection")

    @property
    def position(self) -> int:
        """Samples pushed so far."""
        return int(self._raw.position)

    def push(
        self,
        chunk: ArrayLike,
        t: ArrayLike | None = None,
        temperature: ArrayLike | None = None,
    ) -> None:
        """Add a chunk (m, 3) of samples (and optional per-sample t, temperature)."""
        a = np.asarray(chunk)
        if a.ndim == 2 and a.shape[0] == 0:
            return
        c = samples_array(a, "chunk")
        if self._dtype is None:
            self._dtype = c.dtype
        elif c.dtype != self._dtype:
            c = c.astype(np.float64) if self._dtype == np.float64 else c
        m = c.shape[0]
        self._raw.push(c, channel(t, m, "t"), channel(temperature, m, "temperature"))

    def finish(self) -> DwellSet:
        """The dwell table of everything pushed so far."""
        return _from_raw(self._raw.finish(), self.fs, self.units)
