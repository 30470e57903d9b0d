"""Fleet calibration: many static-session recordings, one summary table.

:func:`calibrate_many` reads each recording, detects its dwells and fits it (as
``accelcal calibrate static`` does for one file), on all local cores by default or on a Dask
cluster when a client or scheduler address is given. Each recording becomes one row of a
:class:`pandas.DataFrame`; a recording that cannot be calibrated becomes a row whose
``status`` says why, never a failed run. :func:`fleet_report` summarises such a table:
parameter distributions (median, robust spread, range), outlier sensors and failures.

Needs the ``fleet`` extra (pandas, pyarrow for Parquet, Dask for clusters):
``pip install 'accelcal[fleet]'``.
"""

from __future__ import annotations

import collections
import csv as csv_module
import glob as _glob
import io as _io
import itertools
import json
import math
import os
import re
import socket
import stat
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import _quiet
from ._core import CalibrationError, DegenerateDataError
from ._files import atomic_create, atomic_write, file_kind, file_record
from ._triad import MODELS, PARAM_NAMES
from .io import file_stem

__all__ = [
    "STATUSES",
    "FleetReport",
    "calibrate_many",
    "fleet_report",
    "read_fleet_table",
]

#: Row statuses, best first.
STATUSES = ("ok", "weak", "misfit", "degenerate", "error")

#: A fit is a ``misfit`` (a faulty unit, not a calibration) when, with the noise known from
#: the dwell variances, its chi2/dof exceeds this (residuals ~30 times the noise) ...
MISFIT_CHI2_DOF = 1e3
#: ... and the RMS of its dwell norm residuals exceeds this fraction of g (a well calibrated
#: MEMS part leaves 1e-4 g; a stuck bit, a step or a drift in one output 1e-3 to 1e-2 g).
MISFIT_RMS_G = 1e-3

_METHODS = ("lm", "gauss-newton", "quadric", "linear-paper")
_MANIFEST_COLUMNS = ("path", "sensor_id", "g", "sigma_g", "lat", "height", "fs", "columns",
                     "time_column", "date", "bounds")

#: Units of the table's columns (the parameters are in the recording's own output units).
COLUMN_UNITS: dict[str, str] = {
    **{f"s{a}": "recording units per m/s^2" for a in "xyz"},
    **{f"b{a}": "recording units" for a in "xyz"},
    **{f"m{i}": "recording units per m/s^2" for i in (1, 2, 3)},
    "fs_hz": "Hz",
    "g_mps2": "m/s^2",
    "sigma_g_mps2": "m/s^2",
    "rms_mps2": "m/s^2",
    "duration_s": "s",
    "elapsed_s": "s",
    "gap_rms_after_mps2": "m/s^2",
}


# ---- options in the caller's language -----------------------------------------------------------
_PY_NAMES = {
    "g": "g= (m/s^2)", "latlon": "lat=/height=", "fs": "fs= (Hz)", "sources": "sources",
    "model": "model=", "method": "method=", "workers": "workers=", "client": "client=",
    "out": "out=", "summary": "summary=", "means": "means=True",
}
_CLI_NAMES = {
    "g": "--g (m/s^2)", "latlon": "--lat/--height", "fs": "--fs (Hz)", "sources": "FILE ...",
    "model": "--model", "method": "--method", "workers": "--workers", "client": "--scheduler",
    "out": "--out", "summary": "--summary", "means": "--means",
}


def _names(cli: bool) -> dict[str, str]:
    return _CLI_NAMES if cli else _PY_NAMES


# ---- the work for one recording ---------------------------------------------------------------
@dataclass(frozen=True)
class _Job:
    """Everything a worker needs for one recording (it reads the file itself)."""

    index: int
    path: str  # as given (reported)
    read_path: str  # absolute (read on the worker)
    sensor_id: str
    g: float | None
    g_source: str
    sigma_g: float | None  # std of g (units of g), counted in every std; None: g exact
    sigma_g_source: str  # where sigma_g came from, in the single-file command's words
    fs: float | None
    columns: Any
    time_column: Any
    model: str
    method: str
    detector: dict[str, Any]
    diagnose: bool
    date: str | None
    cli: bool
    extra: dict[str, Any] = field(default_factory=dict)
    check_g: bool = True
    bounds: str | None = None  # a file of known dwells (absolute), else detection
    means: bool = False  # every recording is a table of dwell means, one pose per row
    listed_as: tuple[str, ...] = ()  # every entry of the recording when it is listed twice
    note: str = ""  # for the row's message: the recording listed again


_INT_COLUMNS = ("n_dwells", "n_samples", "dropped_rows", "dof", "iterations")
_TEXT_COLUMNS = ("sensor_id", "path", "status", "message", "g_source", "model", "method",
                 "noise_model", "gap_best", "gap_selected", "gap_structure", "gap_error",
                 "cal_file", "worker")


def _columns(diagnose: bool) -> list[str]:
    cols = ["sensor_id", "path", "status", "message", "n_dwells", "n_samples", "dropped_rows",
            "duration_s", "fs_hz", "g_mps2", "g_source", "sigma_g_mps2", "model", "method"]
    for p in PARAM_NAMES:
        cols += [p, f"{p}_std"]
    cols += ["chi2_dof", "dof", "rms_mps2", "noise_model", "iterations", "temperature"]
    if diagnose:
        cols += ["gap_best", "gap_selected", "gap_structure", "gap_chi2_dof", "gap_p_value",
                 "gap_held_out", "gap_rms_after_mps2", "gap_error"]
    cols += ["cal_file", "elapsed_s", "worker"]
    return cols


def _blank_row(job: _Job) -> dict[str, Any]:
    row: dict[str, Any] = {c: math.nan for c in _columns(job.diagnose)}
    row.update(
        sensor_id=job.sensor_id, path=job.path, status="error", message="", n_dwells=None,
        n_samples=None, dropped_rows=None, dof=None, iterations=None,
        g_mps2=math.nan if job.g is None else job.g,
        g_source=job.g_source, sigma_g_mps2=job.sigma_g or 0.0, model=job.model,
        method=job.method, noise_model="",
        cal_file="", worker=f"{socket.gethostname()}:{os.getpid()}",
    )
    if job.diagnose:
        row.update(gap_best="", gap_selected="", gap_structure="", gap_error="")
    return row


def _structure_verdict(rep: Any) -> str:
    s = getattr(rep, "structure", None)
    if s is None:
        return ""
    v = s.get("verdict") if isinstance(s, dict) else getattr(s, "verdict", None)
    return "" if v is None else str(v)


def _fit_one(job: _Job, row: dict[str, Any]) -> Any:
    """Read, detect and fit; fills ``row`` and returns the TriadModel (None when no fit, or
    a misfit)."""
    from . import io as _aio
    from .dwell import DetectorSettings, detect_dwells, dwell_stats, fault_text, vibrating_text
    from .static import WeakDesignWarning, fit_static, unit_label, units_of_g, without_off_norm

    names = _names(job.cli)
    if job.g is None:
        row["message"] = (
            f"no reference gravity for this recording: give {names['g']} or "
            f"{names['latlon']}, or a g or lat column in the manifest"
        )
        return None
    from ._formats import is_rosbag

    mode = os.stat(job.read_path).st_mode
    if not stat.S_ISREG(mode) and not (stat.S_ISDIR(mode) and is_rosbag(job.read_path)):
        # a FIFO or a device would block the worker for ever (a ROS 2 bag is a folder)
        kind = "a folder" if stat.S_ISDIR(mode) else "not a regular file"
        row["message"] = f"{job.path} is {kind}, not a recording"
        return None
    # What the recording holds (a copy under another name is noted): path, size, SHA-256.
    source = (file_record(job.read_path) if stat.S_ISREG(mode) else
              {"path": job.read_path, "sha256": None, "bytes": None})
    if stat.S_ISREG(mode):
        row["_sha256"] = source["sha256"]
    st = _aio.read_stream(job.read_path, columns=job.columns, fs=job.fs,
                          time_column=job.time_column)
    n = len(st)
    row["n_samples"] = n
    # What the reader decided (columns found by their norm, int16 stored unsigned, a rate
    # that disagrees with the time column ...), as the single-file commands print it.
    fault_note: list[str] = [x for x in st.notes if not x.startswith(_aio.NO_RATE_NOTE)]
    from ._pose_table import looks_like_poses, too_slow_for_detection

    slow = too_slow_for_detection(st.fs, job.detector.get("window_s"))
    rests = None if job.bounds is not None or st.sections is not None else (
        _aio.step_log_dwells(st.samples, st.t, st.temperature, st.fs))
    if st.sections is not None or rests is not None:
        # An annotated session's labelled sections, or a log of rests' runs: the dwells.
        poses = False
    elif job.means:
        poses = True
    elif st.fs is None or slow:

        poses = job.bounds is None and looks_like_poses(np.asarray(st.samples, np.float64))
        if st.fs is None and not poses and job.bounds is None:
            row["message"] = (
                f"the sample rate is not in the file (no fs metadata or time column): give "
                f"{names['fs']}" + ("" if job.cli else " or an fs column in the manifest")
                + f"; or, if each row is a pose's mean (a table of dwell means), {names['means']}"
            )
            return None
    else:
        poses = False
    if poses:
        # A table of dwell means (one pose per row), as the single-file commands read it,
        # with their notes (std columns used or not ...) in place of the stream's.
        d, rec = _aio._stream_dwells(job.read_path, columns=job.columns, means=True)
        why = "unknown" if st.fs is None else f"{st.fs:.4g} Hz, too low for samples"
        fault_note = [x for x in rec.notes() if not x.startswith("read as a table of dwell")]
        fault_note.append(
            f"read as a table of dwell means, one pose per row ({n} rows" + (
                ": as asked)" if job.means else
                f": the rate is {why}, and the rows step from attitude to attitude)"))
    elif rests is not None:
        d, note = rests
        fault_note.append(note)
        fault_note += _aio.uneven_runs_note(d)
    elif job.bounds is not None or st.sections is not None:
        # Known dwells (a bounds file, or an annotated session's labelled sections): a
        # dropout inside one is an error, as ever.
        known = _aio.read_bounds(job.bounds) if job.bounds is not None else st.sections
        fault_note += known.notes
        # The reader noted what the clock did: st.t is not checked again.
        d = _aio._named_dwells(dwell_stats(st.samples, known.rows(st.fs), t=st.t,
                                           temperature=st.temperature, fs=st.fs,
                                           check_times=False), known)
    else:
        assert st.fs is not None  # no rate: returned above, or read as poses
        settings = DetectorSettings(**job.detector)
        d = detect_dwells(st.samples, st.fs, t=st.t, temperature=st.temperature,
                          settings=settings, check_times=False)
    if st.fs is not None:
        row["fs_hz"] = float(st.fs)
        row["duration_s"] = n / float(st.fs)
    row["dropped_rows"] = int(d.dropped)
    if d.dropped:  # dropouts: left out of the statistics, as the single-file commands do
        fault_note.append(f"{d.dropped} of {n} data rows hold NaN or inf samples (dropouts), "
                          "left out of the dwell statistics")
    faults = d.faults()
    if faults:  # left out, as the single-file commands do
        n_bad = len({f.dwell for f in faults})
        fault_note.append(f"{n_bad} of {len(d)} dwells left out: their output did not follow "
                          f"the sensor ({fault_text(d, faults, limit=2)})".replace("\n  ", "; "))
        d = d.drop_faults(faults)
    d, off = without_off_norm(d, job.g)
    if off is not None:  # left out, as the single-file commands do
        fault_note.append(f"{off.text(job.g)}: left out")
    fault_note += vibrating_text(d)
    k = len(d)
    row["n_dwells"] = k
    # Recorded in this context only (a Dask worker runs jobs in threads: catch_warnings would
    # swap the process-wide filters under the other jobs).
    with _quiet.recording() as caught:
        try:
            fit = fit_static(d, job.g, model=job.model, method=job.method, check_g=job.check_g,
                             sigma_g=job.sigma_g)
        except DegenerateDataError as e:
            row["status"], row["message"] = "degenerate", str(e)
            return None
    weak = [str(w.message) for w in caught if issubclass(w.category, WeakDesignWarning)]
    notes = [str(w.message) for w in caught if not issubclass(w.category, WeakDesignWarning)]
    # The realistic std (scaled by chi2/dof when the residuals exceed the noise model): the
    # one `calibrate static FILE` prints and the calibration file stores (TriadModel.std).
    vec, std = fit.vector, fit.std_realistic
    for i, p in enumerate(PARAM_NAMES[: vec.size]):
        row[p] = float(vec[i])
        row[f"{p}_std"] = float(std[i])
    row.update(
        chi2_dof=float(fit.chi2_dof), dof=int(fit.dof), rms_mps2=float(fit.rms),
        noise_model=fit.noise_model, iterations=int(fit.iterations),
    )
    temp = None if d.temperature is None else float(np.mean(d.temperature))
    row["temperature"] = math.nan if temp is None else temp
    row["status"] = "weak" if (fit.weak or weak) else "ok"
    misfit: list[str] = []
    if (fit.noise_known and fit.dof > 0 and fit.chi2_dof > MISFIT_CHI2_DOF
            and fit.rms > MISFIT_RMS_G * job.g):
        # Far beyond any noise, in both senses: not a calibration a line should load.
        row["status"] = "misfit"
        misfit.append(
            f"the fit does not explain the recording: residual RMS {fit.rms:.3g} "
            f"{unit_label(job.g)} ({fit.rms / job.g:.2g} g) and chi2/dof {fit.chi2_dof:.3g} "
            f"against the noise of its dwells, both far beyond noise (limits {MISFIT_RMS_G:g} "
            f"g and {MISFIT_CHI2_DOF:g}): a faulty unit (a stuck or coarse output bit, a step "
            "or drift in an output) or a fixture that moved; the fit is in the row, no "
            "calibration file written")
    # The single-file summary's note, at 0.001: a fleet's rows are read as a list of the
    # recordings to look at, and at 0.05 one clean recording in twenty would be on it.
    elif fit.noise_known and fit.dof > 0 and fit.chi2_p < 1e-3:
        notes.append(f"residuals exceed the noise model (chi2/dof {fit.chi2_dof:.3g}, p = "
                     f"{fit.chi2_p:.2g}): the std are scaled by chi2/dof; diagnose says what "
                     "the excess is made of")
    unit = units_of_g(job.g)
    if unit != "m/s^2":
        # The columns are named for m/s^2; a g given in g (or cm/s^2) puts them in its units.
        notes.append(f"g = {job.g:g} is in {unit or 'other units than m/s^2'}: g_mps2, "
                     "rms_mps2 and gap_rms_after_mps2 are in those units in this row")
    row["message"] = "; ".join(misfit + fault_note + weak + notes)
    meta: dict[str, Any] = {"source": job.path, "n_dwells": k, "g_source": job.g_source,
                            "sigma_g_source": job.sigma_g_source}
    if stat.S_ISREG(mode):  # what the recording held: tells a re-recorded file from a rerun
        meta["source_sha256"] = row["_sha256"]
    meta.update(_provenance(job, source, poses, rests is not None, st.sections is not None))
    kw: dict[str, Any] = {"sensor_id": job.sensor_id, "temperature": temp, "metadata": meta}
    if job.date:
        kw["date"] = job.date
    if not fit.input_units:  # the raw unit the columns' names declare alike (ax [mg])
        kw["input_units"] = _aio.declared_unit(st.names) or ""
    model = fit.to_model(**kw)
    if job.diagnose:
        from .gap import diagnose

        try:
            rep = diagnose(d, g=job.g)
            row.update(
                gap_best=str(rep.best), gap_selected=",".join(rep.selected),
                gap_structure=_structure_verdict(rep), gap_chi2_dof=float(rep.chi2_per_dof),
                gap_p_value=float(rep.p_value), gap_held_out=float(rep.held_out_gap),
                gap_rms_after_mps2=float(rep.rms_after),
            )
        except CalibrationError as e:
            row["gap_error"] = str(e)
    return None if row["status"] == "misfit" else model  # no file a line could load


def _provenance(job: _Job, source: dict[str, Any], poses: bool, step_log: bool,
                sections: bool) -> dict[str, Any]:
    """What a fleet calibration file records of how it was made, as ``calibrate static -o``
    does for one file: the input (absolute path, size, SHA-256), the model and method, where
    the dwells came from and the detector's settings when they were detected, the manifest's
    bounds file, rate and columns when given (the command line and the time written are
    added when the file is written)."""
    dwells_from = ("table of dwell means" if poses else "step log rests" if step_log
                   else "bounds file" if job.bounds is not None
                   else "annotated sections" if sections else "detected")
    out: dict[str, Any] = {
        "input": source, "model": job.model, "method": job.method,
        "dwells_from": dwells_from,
        "detector": dict(job.detector) if dwells_from == "detected" else None,
    }
    if job.bounds is not None:
        out["bounds"] = file_record(job.bounds)
    if job.fs is not None:
        out["fs"] = float(job.fs)
    if not _missing(job.columns):
        out["columns"] = job.columns if isinstance(job.columns, str) else [
            c if isinstance(c, (int, str)) else str(c) for c in job.columns]
    if not _missing(job.time_column):
        out["time_column"] = job.time_column if isinstance(job.time_column, (int, str)) \
            else str(job.time_column)
    return out


def _calibrate_one(job: _Job) -> tuple[dict[str, Any], Any]:
    """One recording -> (row, TriadModel or None). Never raises for a bad recording."""
    t0 = time.perf_counter()
    row = _blank_row(job)
    model = None
    try:
        model = _fit_one(job, row)
    except DegenerateDataError as e:
        row["status"], row["message"] = "degenerate", str(e)
    except CalibrationError as e:
        msg = str(e)
        named = job.path in msg or job.read_path in msg
        # the row's message names its file, as the reader's own messages do
        row["status"], row["message"] = "error", msg if named else f"{job.path}: {msg}"
    except FileNotFoundError as e:
        row["status"], row["message"] = "error", f"file not found: {e.filename or e}"
    except OSError as e:
        row["status"], row["message"] = "error", f"cannot read the file: {e}"
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as e:  # noqa: BLE001 - a bug (or a Rust panic) stays in its row
        row["status"] = "error"
        row["message"] = f"internal error: {type(e).__name__}: {e} (please report it)"
    if model is None and row["status"] in ("ok", "weak"):
        row["status"] = "error"
    row["elapsed_s"] = time.perf_counter() - t0
    return row, model


def _init_worker() -> None:
    """Process-pool initializer: one rayon thread per worker (set before the extension's
    thread pool starts), so N workers use N cores."""
    os.environ["RAYON_NUM_THREADS"] = "1"


def _calibrate_chunk_dask(jobs: list[_Job]) -> list[tuple[dict[str, Any], Any]]:
    """A Dask task: a few recordings, each isolated as on the local pool."""
    # A Dask worker runs one task per thread: keep rayon to one thread there too, unless
    # the worker was started with its own RAYON_NUM_THREADS.
    os.environ.setdefault("RAYON_NUM_THREADS", "1")
    return [_calibrate_one(j) for j in jobs]


def _chunk_size(n_jobs: int, n_threads: int) -> int:
    """Recordings per Dask task: at least 8 tasks per worker thread (load balance, progress),
    at most 16 recordings (each task then carries enough work that the scheduler's cost per
    task, about 10 ms of CPU, stays small against the fits)."""
    return max(1, min(16, n_jobs // max(1, 8 * n_threads)))


# ---- sources --------------------------------------------------------------------------------
def _need_pandas() -> Any:
    try:
        import pandas as pd
    except ImportError:
        raise CalibrationError(
            "fleet calibration needs pandas: pip install 'accelcal[fleet]'"
        ) from None
    return pd


_SHEETS = (".xlsx", ".xlsm", ".xls", ".ods")


def _has_path_column(names: Any) -> bool:
    """A table whose column names hold ``path`` lists recordings (a manifest)."""
    return "path" in {str(c).strip().lower() for c in names}


def _is_manifest_file(p: str) -> bool:
    low = p.lower()
    if low.endswith((".parquet", ".pq")):
        # A manifest has a path column; a recording in Parquet has accelerometer columns.
        try:
            import pyarrow.parquet as parquet

            names = parquet.read_schema(p).names
        except Exception:  # noqa: BLE001 - missing pyarrow or unreadable: the manifest's reader says why
            return True
        return _has_path_column(names)
    if low.endswith(_SHEETS) and os.path.isfile(p):
        # A workbook is a manifest when its first sheet has a path column (a recording in a
        # workbook has accelerometer columns instead).
        try:
            head = _need_pandas().read_excel(p, nrows=0)
        except Exception:  # noqa: BLE001 - not readable here: the recording reader says why
            return False
        return _has_path_column(head.columns)
    if not low.endswith((".csv", ".tsv", ".txt")) or not os.path.isfile(p):
        return False
    with open(p, encoding="utf-8", errors="replace") as fh:
        for line in itertools.islice(fh, 50):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            fields = [f.strip().strip("\"'").lower() for f in re.split(r"[,;\t]", s)]
            return "path" in fields
    return False


def _read_table(path: str) -> Any:
    pd = _need_pandas()
    low = path.lower()
    try:
        text_columns = {"sensor_id": str, "path": str, "columns": str}
        if low.endswith((".parquet", ".pq")):
            return pd.read_parquet(path)
        if low.endswith(_SHEETS):
            return pd.read_excel(path, dtype=text_columns)
        return pd.read_csv(path, comment="#", sep=None, engine="python", dtype=text_columns)
    except FileNotFoundError:
        raise CalibrationError(f"table not found: {path}") from None
    except ImportError as e:
        what = ("openpyxl (a workbook): pip install 'accelcal[excel]'" if low.endswith(_SHEETS)
                else "pyarrow (Parquet): pip install 'accelcal[fleet]'")
        raise CalibrationError(f"reading {path} needs {what} ({e})") from None
    except (ValueError, OSError) as e:
        raise CalibrationError(f"cannot read the table {path}: {e}") from None


def _missing(v: Any) -> bool:
    if v is None:
        return True
    if isinstance(v, float) and math.isnan(v):
        return True
    try:
        import pandas as pd

        if v is pd.NA or v is pd.NaT:
            return True
    except ImportError:  # pragma: no cover
        pass
    return isinstance(v, str) and not v.strip()


def _sources_table(sources: Any, names: dict[str, str]) -> tuple[list[dict[str, Any]], Path]:
    """Rows (dicts with at least 'path') and the folder relative paths are read from."""
    pd = _need_pandas()
    base = Path.cwd()
    if isinstance(sources, pd.DataFrame):
        table = sources.copy()
    elif isinstance(sources, (str, os.PathLike)):
        s = os.fspath(sources)
        if any(c in s for c in "*?[") and not os.path.exists(s):
            files = sorted(_glob.glob(s, recursive=True))
            if not files:
                raise CalibrationError(f"no recording matches {s!r}")
            return [{"path": f} for f in files], base
        if _is_manifest_file(s):
            table = _read_table(s)
            base = Path(s).resolve().parent
        else:
            return [{"path": s}], base
    elif isinstance(sources, Iterable):
        items = list(sources)
        rows = []
        for x in items:
            if not isinstance(x, (str, os.PathLike)):
                raise CalibrationError(
                    f"{names['sources']} must hold file paths; got {type(x).__name__} {x!r}"
                )
            rows.append({"path": os.fspath(x)})
        if not rows:
            raise CalibrationError(f"{names['sources']}: no recordings given")
        return rows, base
    else:
        raise CalibrationError(
            f"{names['sources']} must be a list of paths, a glob such as 'rec/*.csv', or a "
            f"manifest (CSV/Parquet path or DataFrame); got {type(sources).__name__}"
        )
    if "path" not in table.columns:
        raise CalibrationError(
            f"the manifest needs a 'path' column (one recording per row); it has "
            f"{list(map(str, table.columns))}"
        )
    if len(table) == 0:
        raise CalibrationError("the manifest has no rows")
    return table.to_dict("records"), base


def _num(v: Any, what: str, where: str) -> float | None:
    if _missing(v):
        return None
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: {what} must be a number; got {v!r}") from None
    if not math.isfinite(x):
        raise CalibrationError(f"{where}: {what} must be finite; got {v!r}")
    return x


def _safe_name(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", s).strip("._") or "sensor"


def _file_key(read_path: str) -> tuple[Any, ...]:
    """What identifies a recording: its file (a hard link or another spelling of the path is
    the same file), else its path with ``.``, ``..`` and symbolic links resolved."""
    try:
        st = os.stat(read_path)
    except OSError:  # missing here (a cluster's worker may see it): compare the paths
        return ("path", os.path.realpath(read_path))
    if stat.S_ISREG(st.st_mode):
        return ("file", st.st_dev, st.st_ino)
    return ("path", os.path.realpath(read_path))


def _row_settings(r: dict[str, Any]) -> dict[str, Any]:
    return {k: (None if _missing(v) else v) for k, v in r.items() if k != "path"}


def _join(items: Sequence[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def _once_each(jobs: list[_Job], rows: list[dict[str, Any]]
               ) -> tuple[list[_Job], list[bool], list[tuple[Any, ...]]]:
    """Each recording once: a recording listed again with the same settings (overlapping
    globs, the same path spelled two ways, a symbolic link to it, a manifest row repeated) is
    calibrated once, in the row of its first entry, whose ``listed_as`` then names every
    entry. Manifest rows that give one recording other settings (known bounds in one and
    detection in the other, say) are different calibrations: each is kept, and its row notes
    the other. Returns the jobs (renumbered), whether each row names its sensor, and each
    job's file key."""
    from dataclasses import replace as _replace

    keys = [_file_key(j.read_path) for j in jobs]
    settings = [_row_settings(r) for r in rows]
    same: dict[int, list[int]] = {}  # first entry -> its entries with the same settings
    first: dict[tuple[Any, ...], list[int]] = {}  # file -> first entries of its settings
    for i, key in enumerate(keys):
        heads = first.setdefault(key, [])
        k = next((h for h in heads if settings[h] == settings[i]), None)
        if k is None:
            heads.append(i)
            same[i] = [i]
        else:
            same[k].append(i)
    out: list[_Job] = []
    given: list[bool] = []
    out_keys: list[tuple[Any, ...]] = []
    for k, idx in same.items():
        j = jobs[k]
        listed = tuple(jobs[i].path for i in idx) if len(idx) > 1 else ()
        others = [h for h in first[keys[k]] if h != k]
        note = _listed_note(j.path, listed)
        if others:
            a = settings[k]
            diff = {c for h in others for c in {*a, *settings[h]}
                    if a.get(c) != settings[h].get(c)}
            rows_ = _join([str(h) for h in others])
            note = "; ".join(x for x in (note, (
                f"the same recording is also in manifest row{'s' if len(others) > 1 else ''} "
                f"{rows_}, with other {_join(sorted(diff))}: calibrated for each")) if x)
        out.append(_replace(j, index=len(out), listed_as=listed, note=note))
        given.append(not _missing(rows[k].get("sensor_id")))
        out_keys.append(keys[k])
    return out, given, out_keys


def _distinct_ids(jobs: list[_Job], given: list[bool],
                  keys: list[tuple[Any, ...]]) -> list[_Job]:
    """Sensor ids taken from the stems of different files that collide (``a/acceldata.txt``
    and ``b/acceldata.txt``) get their folder's name in front (``a_acceldata``), then a number
    if they still collide; ids a manifest gives are kept as they are, and so are those of one
    file calibrated with different settings (one sensor)."""
    from dataclasses import replace as _replace

    files: dict[str, set[tuple[Any, ...]]] = collections.defaultdict(set)
    for j, g, key in zip(jobs, given, keys, strict=True):
        if not g:
            files[j.sensor_id].add(key)
    out, seen = [], set()
    named: dict[tuple[Any, ...], str] = {}
    for j, g, key in zip(jobs, given, keys, strict=True):
        sid = j.sensor_id
        if not g and len(files[sid]) > 1:
            if key in named:
                sid = named[key]
            else:
                sid = f"{Path(j.path).parent.name or 'root'}_{sid}"
                base, k = sid, 2
                while sid in seen:
                    sid, k = f"{base}-{k}", k + 1
                named[key] = sid
            j = _replace(j, sensor_id=sid)
        seen.add(sid)
        out.append(j)
    return out


def _listed_note(path: str, listed_as: tuple[str, ...]) -> str:
    """The row's note for a recording listed more than once."""
    if not listed_as:
        return ""
    spell = sorted(set(listed_as), key=listed_as.index)
    how = f"as {path} each time" if len(spell) == 1 else f"as {_join(spell)}"
    return f"the same recording is listed {len(listed_as)} times ({how}): calibrated once"


def _make_jobs(
    rows: list[dict[str, Any]], base: Path, *, g: float | None, lat: float | None,
    height: float | None, fs: float | None, columns: Any, time_column: Any, model: str,
    method: str, detector: dict[str, Any], diagnose: bool, cli: bool, check_g: bool = True,
    means: bool = False, sigma_g: float | None = None,
) -> list[_Job]:
    from .static import LAT_FORMULA_SIGMA_G, local_gravity

    names = _names(cli)
    jobs = []
    for i, r in enumerate(rows):
        p = r.get("path")
        if _missing(p):
            raise CalibrationError(f"manifest row {i}: the path is empty")
        path = os.fspath(p) if isinstance(p, (str, os.PathLike)) else str(p)
        read_path = str(base / path) if not os.path.isabs(path) else path
        where = f"manifest row {i} ({path})"
        sid = r.get("sensor_id")
        sensor_id = file_stem(path) if _missing(sid) else str(sid)
        rg = _num(r.get("g"), "g (m/s^2)", where)
        rsg = _num(r.get("sigma_g"), "sigma_g (m/s^2)", where)
        rlat = _num(r.get("lat"), "lat (deg)", where)
        rh = _num(r.get("height"), "height (m)", where)
        rfs = _num(r.get("fs"), "fs (Hz)", where)
        if rfs is not None and rfs <= 0:
            raise CalibrationError(f"{where}: fs must be positive (Hz); got {rfs}")
        h = rh if rh is not None else (height if height is not None else 0.0)
        gv: float | None
        if rg is not None:
            gv, src = rg, "manifest g"
        elif rlat is not None:
            gv, src = local_gravity(rlat, h), f"WGS84 normal gravity at {rlat:g} deg, {h:g} m"
        elif g is not None:
            gv, src = g, "given"
        elif lat is not None:
            gv, src = local_gravity(lat, h), f"WGS84 normal gravity at {lat:g} deg, {h:g} m"
        else:
            gv, src = None, ""
        # As the single-file command: a g from the latitude formula carries its typical
        # error against a gravimeter unless a sigma_g is given (row, then keyword).
        sg = rsg if rsg is not None else sigma_g
        sg_src = ("manifest sigma_g" if rsg is not None else "given" if sigma_g is not None
                  else "none given")
        if sg is None and src.startswith("WGS84"):
            sg = LAT_FORMULA_SIGMA_G
            sg_src = "the latitude formula's typical error against a gravimeter (local anomalies)"
        cols = r.get("columns")
        date = r.get("date")
        rb = r.get("bounds")
        bounds = None if _missing(rb) else str(base / str(rb))  # an absolute one stays
        extra = {k: v for k, v in r.items() if k not in _MANIFEST_COLUMNS}
        jobs.append(_Job(
            index=i, path=path, read_path=os.path.abspath(read_path), sensor_id=sensor_id,
            g=gv, g_source=src, sigma_g=sg, sigma_g_source=sg_src,
            fs=rfs if rfs is not None else fs,
            columns=columns if _missing(cols) else cols,
            time_column=time_column if _missing(r.get("time_column")) else r.get("time_column"),
            model=model, method=method,
            detector=detector, diagnose=diagnose,
            date=None if _missing(date) else str(date), cli=cli, extra=extra,
            check_g=check_g and not src.startswith("WGS84"),  # local gravity by construction
            bounds=bounds, means=means,
        ))
    jobs, given, keys = _once_each(jobs, rows)
    jobs = _distinct_ids(jobs, given, keys)
    if all(j.g is None for j in jobs):
        raise CalibrationError(
            f"give the reference gravity: {names['g']} or {names['latlon']}"
            + ("" if cli else ", or g or lat columns in the manifest")
        )
    return jobs


# ---- execution ------------------------------------------------------------------------------
def _bar(total: int, progress: bool | None) -> Any:
    from tqdm import tqdm

    disable = None if progress is None else not progress
    return tqdm(total=total, unit="rec", desc="calibrating", disable=disable, leave=False)


Result = tuple[dict[str, Any], Any]
#: Called with each job and its result as the result arrives.
Done = Callable[[_Job, Result], None]


def _run_local(jobs: list[_Job], workers: int, progress: bool | None, done: Done) -> None:
    with _bar(len(jobs), progress) as bar:
        if workers == 1:
            for j in jobs:
                done(j, _calibrate_one(j))
                bar.update(1)
            return
        _run_pool(jobs, workers, done, bar)


def _pool_worker(conn: Any) -> None:
    """A local worker process: calibrates each job the caller sends down ``conn`` and sends
    its result back, until the caller sends None or closes the pipe."""
    _init_worker()
    try:
        while True:
            try:
                job = conn.recv()
            except EOFError:
                return
            if job is None:
                return
            res = _calibrate_one(job)
            try:
                conn.send(res)
            except Exception as e:  # noqa: BLE001 - e.g. a result that cannot be sent back
                conn.send(_failed(job, f"worker failed: {type(e).__name__}: {e}"))
    except KeyboardInterrupt:  # Ctrl-C reaches the whole process group: the caller stops
        return


@dataclass
class _Worker:
    proc: Any
    conn: Any
    job: _Job | None = None
    results: int = 0


def _run_pool(jobs: list[_Job], workers: int, done: Done, bar: Any) -> None:
    """The jobs over ``workers`` processes, one job at a time in each. A worker that dies
    (out of memory, killed, a crash in native code) fails only the recording it was
    calibrating; a fresh process takes its place and the others go on."""
    import multiprocessing
    from multiprocessing.connection import wait

    # spawn: fresh interpreters, so rayon's pool starts in each worker after _init_worker
    # has set its size (a forked rayon pool would not survive the fork).
    ctx = multiprocessing.get_context("spawn")
    queue = collections.deque(jobs)
    pool: list[_Worker] = []  # the workers at work
    started: list[_Worker] = []
    early = n_done = 0  # workers that died before sending back any result; results
    again: set[int] = set()  # jobs given out again (their worker stopped as on Ctrl-C)

    def start() -> None:
        mine, theirs = ctx.Pipe()
        p = ctx.Process(target=_pool_worker, args=(theirs,), daemon=True)
        p.start()
        theirs.close()
        pool.append(_Worker(p, mine))
        started.append(pool[-1])

    try:
        for _ in range(min(workers, len(queue))):
            start()
        while pool:
            for w in list(pool):  # work for the idle, a stop for the idle without work
                if w.job is None:
                    if not queue:
                        pool.remove(w)
                    try:
                        if queue:
                            w.job = queue.popleft()
                            w.conn.send(w.job)
                        else:
                            w.conn.send(None)
                    except OSError:  # died before it had the job: its death is seen below
                        if w.job is not None:
                            queue.appendleft(w.job)
                            w.job = None
            if not pool:
                break
            ready = set(wait([w.conn for w in pool] + [w.proc.sentinel for w in pool]))
            for w in list(pool):
                if w.conn not in ready and w.proc.sentinel not in ready:
                    continue
                job, eof, res = w.job, False, None
                try:
                    if w.conn.poll():
                        res = w.conn.recv()
                except (EOFError, OSError):  # the pipe broke: the worker died
                    eof = True
                if res is not None:
                    # (Outside the try: an error in the caller's hands, such as a file it
                    # cannot write, is not a worker's death.)
                    assert job is not None
                    w.job, w.results, n_done = None, w.results + 1, n_done + 1
                    done(job, res)
                    bar.update(1)
                    continue
                if not eof and w.proc.sentinel not in ready:
                    continue
                # The worker died.
                w.proc.join(5.0)
                code = w.proc.exitcode
                pool.remove(w)
                w.conn.close()
                if job is not None and code == 0 and job.index not in again:
                    again.add(job.index)  # once: a recording that stops it cleanly fails
                    queue.appendleft(job)  # Ctrl-C stopped it: the caller stops too
                elif job is not None:
                    done(job, _failed(job, f"the worker process calibrating this recording "
                                           f"died ({_exit_text(code)}); {_died_hint()}"))
                    bar.update(1)
                early += w.results == 0
                if queue and early >= max(2, workers) and not n_done:
                    # every worker dies on start (a script without the __main__ guard):
                    # the rest would too
                    while queue:
                        j = queue.popleft()
                        done(j, _failed(j, f"a worker process died on start "
                                           f"({_exit_text(code)}); {_died_hint()}"))
                        bar.update(1)
                if queue:
                    start()
    finally:  # after Ctrl-C (or an error in the caller's hands) the workers stop now
        for w in pool:
            if w.proc.is_alive():
                w.proc.terminate()
        for w in started:
            w.proc.join(5.0)
            if w.proc.is_alive():  # pragma: no cover - ignored SIGTERM
                w.proc.kill()
                w.proc.join()
            w.conn.close()


def _exit_text(code: int | None) -> str:
    """How a worker process ended, in words."""
    import signal

    if code is None:
        return "it did not exit"
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        if -code == signal.SIGKILL:
            return f"killed by {name}: out of memory, or killed from outside"
        return f"killed by {name}"
    return f"exit status {code}"
def _died_hint() -> str:
    """What to do when a local worker died: run from a script, the likely cause is a call at
    its top level (each spawned worker imports the script and reaches the call again)."""
    main = sys.modules.get("__main__")
    if getattr(main, "__file__", None):
        return ("if calibrate_many is called at the top level of a script, put the call under "
                "'if __name__ == \"__main__\":' (each worker is a fresh interpreter that "
                "imports the script), or pass workers=1; else run this recording alone to "
                "see why")
    return "run this recording alone to see why"


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        return os.cpu_count() or 1


def _failed(job: _Job, msg: str) -> Result:
    row = _blank_row(job)
    row["message"] = msg
    row["worker"] = ""
    return row, None


def _need_distributed() -> Any:
    try:
        import distributed
    except ImportError:
        raise CalibrationError(
            "running on a Dask cluster needs dask.distributed: pip install 'accelcal[fleet]'"
        ) from None
    return distributed


#: How long to keep trying to reach a scheduler given by address, s.
_CONNECT_TIMEOUT_S = 20.0


def _run_dask(jobs: list[_Job], client: Any, progress: bool | None, cli: bool,
              done: Done) -> None:
    distributed = _need_distributed()
    names = _names(cli)
    own = False
    if isinstance(client, str):
        try:
            client = distributed.Client(client, timeout=f"{_CONNECT_TIMEOUT_S:g}s")
        except (OSError, TimeoutError, ValueError) as e:
            raise CalibrationError(
                f"cannot reach the Dask scheduler at {client!r} ({names['client']}): {e}"
            ) from None
        own = True
    elif not isinstance(client, distributed.Client):
        raise CalibrationError(
            f"{names['client']} must be a dask.distributed.Client or a scheduler address "
            f"such as 'tcp://host:8786'; got {type(client).__name__}"
        )
    try:
        if not client.scheduler_info().get("workers"):
            try:  # a scheduler without workers would queue the recordings for ever
                client.wait_for_workers(1, timeout=_CONNECT_TIMEOUT_S)
            except Exception:  # noqa: BLE001 - dask raises its own TimeoutError types
                raise CalibrationError(
                    f"the Dask cluster at {client.scheduler.address} ({names['client']}) has "
                    f"no workers (waited {_CONNECT_TIMEOUT_S:g} s); start some with "
                    "`dask worker ADDRESS`"
                ) from None
        n_threads = sum(int(w.get("nthreads", 1))
                        for w in client.scheduler_info().get("workers", {}).values())
        size = _chunk_size(len(jobs), n_threads)
        chunks = [jobs[i : i + size] for i in range(0, len(jobs), size)]
        futs = client.map(_calibrate_chunk_dask, chunks, pure=False)
        by_key = {f.key: c for f, c in zip(futs, chunks, strict=True)}
        try:
            with _bar(len(jobs), progress) as bar:
                for f in distributed.as_completed(futs):
                    chunk = by_key[f.key]
                    try:
                        res = f.result()
                    except Exception as e:  # noqa: BLE001 - a lost worker stays in its rows
                        res = [_failed(j, f"the Dask task failed: {type(e).__name__}: {e}")
                               for j in chunk]
                    f.release()
                    for j, r in zip(chunk, res, strict=True):
                        done(j, r)
                    bar.update(len(chunk))
        except BaseException:  # Ctrl-C: cancel what is still queued on the cluster
            client.cancel(futs)
            raise
    finally:
        if own:
            client.close()


# ---- output ---------------------------------------------------------------------------------
def _frame(results: list[Result], jobs: list[_Job], diagnose: bool) -> Any:
    pd = _need_pandas()
    cols = _columns(diagnose)
    extra_keys: list[str] = []
    for j in jobs:
        for k in j.extra:
            if k not in extra_keys:
                extra_keys.append(k)
    recs = []
    for (row, _), j in zip(results, jobs, strict=True):
        r = {c: row.get(c) for c in cols}
        for k in extra_keys:
            r[k if k not in cols else f"manifest_{k}"] = j.extra.get(k)
        recs.append(r)
    df = pd.DataFrame.from_records(recs, columns=cols + [
        k if k not in cols else f"manifest_{k}" for k in extra_keys])
    for c in _INT_COLUMNS:
        df[c] = df[c].astype("Int64")
    str_cols = ["sensor_id", "path", "status", "message", "g_source", "model", "method",
                "noise_model", "cal_file", "worker"]
    if diagnose:
        str_cols += ["gap_best", "gap_selected", "gap_structure", "gap_error"]
    float_cols = [c for c in cols if c not in str_cols
                  and c not in _INT_COLUMNS]
    for c in float_cols:
        df[c] = df[c].astype("float64")
    df.attrs["units"] = dict(COLUMN_UNITS)
    return df


def _stamp(date: Any) -> str:
    """``YYYYmmddTHHMMSSZ`` (UTC) of an ISO 8601 date; naive dates are taken as UTC."""
    import datetime as dt

    try:
        d = dt.datetime.fromisoformat(str(date).strip().replace("Z", "+00:00"))
    except ValueError:
        return "undated"
    if d.tzinfo is not None:
        d = d.astimezone(dt.timezone.utc)
    return d.strftime("%Y%m%dT%H%M%SZ")


def _cal_name(model: Any) -> str:
    """``<sensor_id>_<UTC date>.json``, the name TriadModel gives its own files: later
    calibrations of a sensor sit beside earlier ones, and the file of a time is found by
    sensor id and date."""
    own = getattr(model, "default_filename", None)
    if callable(own):
        return str(own())
    return f"{_safe_name(model.sensor_id)}_{_stamp(model.date)}.json"


def _add_note(row: dict[str, Any], note: str) -> None:
    if note:
        row["message"] = "; ".join(x for x in (row.get("message") or "", note) if x)


#: What a calibration file records of the run that wrote it, not of the calibration: two
#: files that differ only there hold the same calibration.
_RUN_KEYS = ("written", "command")


def _calibration_content(data: bytes) -> Any:
    """A calibration file's JSON without :data:`_RUN_KEYS` (None when it is not JSON)."""
    try:
        d = json.loads(data)
    except (ValueError, UnicodeDecodeError):
        return None
    if isinstance(d, dict) and isinstance(d.get("metadata"), dict):
        d["metadata"] = {k: v for k, v in d["metadata"].items() if k not in _RUN_KEYS}
    return d


def _same_bytes(path: Path, data: bytes) -> bool:
    """Whether ``path`` holds this calibration: the same bytes, or the same content apart
    from the time it was written and the command line (a rerun of the same batch)."""
    try:
        st = os.lstat(path)
        if not stat.S_ISREG(st.st_mode) or st.st_size > 50_000_000:
            return False
        old = path.read_bytes()
    except OSError:
        return False
    if old == data:
        return True
    content = _calibration_content(old)
    return content is not None and content == _calibration_content(data)


#: The settings a calibration file records (metadata keys), compared to say how two
#: calibrations of one recording differ.
_SETTING_KEYS = ("model", "method", "dwells_from", "detector", "g_source", "sigma_g", "fs",
                 "columns", "time_column", "check_g")


def _settings_diff(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """The recorded settings that differ between two calibration files' dicts, worded
    ``detector k 6 (this run: 20)``; empty when none of them does. A setting a file does not
    record (one written by an earlier version) is not compared."""
    def flat(d: dict[str, Any]) -> dict[str, Any]:
        md_ = d.get("metadata")
        md: dict[str, Any] = md_ if isinstance(md_, dict) else {}
        out: dict[str, Any] = {"g": d.get("g")}
        for key in (*_SETTING_KEYS, "bounds"):
            if key not in md:
                continue
            v = md[key]
            if key == "bounds":
                out["bounds file"] = v.get("sha256") if isinstance(v, dict) else v
            elif isinstance(v, dict):
                out.update({f"{key} {k}": x for k, x in v.items()})
            else:
                out[key] = v
        return out

    a, b = flat(old), flat(new)
    return [f"{k} {a[k]} (this run: {b[k]})" for k in a if k in b and a[k] != b[k]]


def _holder(path: Path, model: Any) -> str:
    """What an existing file in the calibration folder holds, in a few words."""
    try:
        st = os.lstat(path)
        if not stat.S_ISREG(st.st_mode) or st.st_size > 50_000_000:
            raise ValueError
        d = json.loads(path.read_text(encoding="utf-8"))
        if d.get("format") != "accelcal.TriadModel":
            raise ValueError
        src = d.get("metadata", {}).get("source")
    except (OSError, ValueError, AttributeError, UnicodeDecodeError):
        return "not a calibration of this recording"
    if src is None:
        return "a calibration of another recording"
    if src != model.metadata.get("source"):
        return f"the calibration of {src}"
    sha = d.get("metadata", {}).get("source_sha256")
    if sha is not None and sha != model.metadata.get("source_sha256"):
        return f"the calibration of an earlier recording in {src}"
    diff = _settings_diff(d, model.to_dict())
    if diff:
        return f"another calibration of {src} (other settings: {_join(diff)})"
    return f"another calibration of {src} (other settings)"


class _SaveError(OSError):
    """A calibration file that could not be written; ``filename`` is its name."""


def _save_new(model: Any, folder: Path, used: set[str],
              names: dict[str, str]) -> tuple[Path, str, bool]:
    """Write a calibration file into ``folder`` without ever replacing a file there.

    Its name is ``<sensor_id>_<date>.json``, else ``-2``, ``-3`` ... : the first name that no
    other recording of this run took (``used``) and that is free in the folder. A file already
    there with exactly the same content (the same recording, the same result: a rerun of a
    batch with a manifest date; the time it was written and the command line aside) is kept
    as it is and stands for this calibration. Returns the
    file, the row's note when a name was taken by an existing file, and whether the file was
    already there.
    """
    base = _cal_name(model)
    data = model.to_json().encode()
    taken: list[str] = []
    k = 1
    while True:
        name = base if k == 1 else f"{base[:-5]}-{k}.json"
        k += 1
        if name in used:  # another recording of this run: -2 as ever, no note
            continue
        target = folder / name
        # Complete under a temporary name, then linked to its name: a reader (or another
        # run) sees no half file, and a file of that name is never replaced.
        try:
            created = atomic_create(target, data)
        except OSError as e:  # named after the calibration file, not the temporary one
            raise _SaveError(e.errno, e.strerror, str(target)) from e
        if created:
            same = False
            break
        if _same_bytes(target, data):
            same = True
            break
        taken.append(f"{name} ({_holder(target, model)})")
    used.add(name)
    note = ""
    if taken:
        more = f" and {len(taken) - 3} more" if len(taken) > 3 else ""
        note = (f"{names['out']} already holds {_join(taken[:3])}{more}: this calibration is "
                f"written as {name}, the existing file{'s' if len(taken) > 1 else ''} kept")
    return target, note, same


def _summary_paths(summary: str | os.PathLike[str]) -> tuple[Path, Path]:
    p = Path(summary)
    if p.suffix.lower() == ".csv":
        return p.with_suffix(".parquet"), p
    return p, p.with_suffix(".csv")


#: Columns that every fleet table this tool writes has (and a table of other results, in all
#: likelihood, has not): what tells a fleet table from another file of that name.
_TABLE_MARK = ("sensor_id", "path", "status", "message", "n_dwells", "chi2_dof", "cal_file")


def _is_fleet_table(path: Path) -> bool:
    """Whether the regular file ``path`` is a fleet table (Parquet or CSV) this tool wrote:
    it has the table's columns (a CSV after its ``# key: value`` lines)."""
    try:
        if path.suffix.lower() == ".csv":
            with open(path, encoding="utf-8", errors="replace", newline="") as fh:
                line = fh.readline(1 << 20)
                while line.startswith("#"):  # the run's record (a long command line too)
                    while line and not line.endswith("\n"):
                        line = fh.readline(1 << 20)
                    line = fh.readline(1 << 20)
            cols = next(csv_module.reader([line.rstrip("\r\n")]), [])
        else:
            import pyarrow.parquet as pq

            cols = list(pq.read_schema(path).names)
    except Exception:  # noqa: BLE001 - unreadable, not Parquet, no pyarrow: not recognised
        return False
    return set(_TABLE_MARK) <= set(cols)


def _check_table_paths(summary: str | os.PathLike[str], named: bool, overwrite: bool,
                       names: dict[str, str]) -> None:
    """Before any work: the table's files may be written. The file the caller named is
    replaced (atomically); the other one (the CSV beside a Parquet table, and both in ``out``
    when no table was named) only when it is a fleet table written before, or ``overwrite``:
    a file the caller did not name is never replaced silently. A symbolic link or a folder in
    the way is refused here rather than after the run."""
    pq, csv = _summary_paths(summary)
    given = Path(summary) if named else None
    over = "--overwrite" if names is _CLI_NAMES else "overwrite=True"
    for p in (pq, csv):
        try:
            st = os.lstat(p)
        except OSError:
            continue  # missing (or unreachable: the write says why)
        if stat.S_ISLNK(st.st_mode):
            raise CalibrationError(
                f"{names['summary']}: {str(p)!r} is a symbolic link to {os.readlink(p)!r}; "
                "the table is not written through a link: give another name (or the link's "
                "target); nothing was done")
        if stat.S_ISDIR(st.st_mode):
            raise CalibrationError(f"{names['summary']}: {str(p)!r} is a folder; give "
                                   "another name; nothing was done")
        if p == given or overwrite or (stat.S_ISREG(st.st_mode) and _is_fleet_table(p)):
            continue
        what = ("not a fleet table" if stat.S_ISREG(st.st_mode)
                else file_kind(st.st_mode))
        why = (f"{names['summary']} {summary} writes it beside {given}" if given else
               f"{names['out']} writes the table there")
        raise CalibrationError(
            f"{str(p)!r} exists and is {what}: {why} (the table is written as Parquet and as "
            f"CSV), which would replace it. Move it, choose another {names['summary']}, or "
            f"give {over} to replace it; nothing was done")


#: The run's attrs a fleet table file records (Parquet: key-value metadata ``accelcal_<key>``
#: besides pandas' own copy of the attrs; CSV: leading ``# key: value`` lines).
_RUN_ATTRS = ("accelcal_version", "detector", "command")


def _run_lines(df: Any) -> list[tuple[str, str]]:
    """``(key, text)`` of the run's attrs a table file records (JSON for the detector)."""
    out = []
    for key in _RUN_ATTRS:
        v = df.attrs.get(key)
        if v is not None:
            out.append((key, v if isinstance(v, str) else json.dumps(v, sort_keys=True)))
    return out


def _write_table(df: Any, parquet: Path, csv: Path, names: dict[str, str],
                 folder: Path | None = None, written: Sequence[str] = ()) -> None:
    """Write the table as Parquet and as CSV. When a file cannot be written (disk full, no
    permission) the other is still tried, and one CalibrationError names what could not be
    written, what was, and the calibration files ``written`` into ``folder``."""
    buf = _table_parquet(df, names)
    head = "".join(f"# {k}: {' '.join(v.split())}\n" for k, v in _run_lines(df))
    ok: list[str] = []
    failed: list[str] = []
    for path, data in ((parquet, buf), (csv, head + df.to_csv(index=False))):
        try:
            atomic_write(path, data)
            ok.append(str(path))
        except OSError as e:
            failed.append(f"{path} ({_os_error(e)})")
    if not failed:
        return
    msg = f"could not write the table: {' and '.join(failed)}"
    if ok:
        msg += f"; wrote {ok[0]}"
    if folder is not None:
        msg += (f"; the calibration files written ({len(written)}) are in {folder}"
                if written else f"; no calibration file was written to {folder}")
    raise CalibrationError(msg)


def _os_error(e: OSError) -> str:
    """An OSError without the (temporary) file name it carries: ``[Errno 28] No space left
    on device``."""
    return f"[Errno {e.errno}] {e.strerror}" if e.strerror else str(e)


def _table_parquet(df: Any, names: dict[str, str]) -> bytes:
    """The Parquet bytes of the table, the run's record in its key-value metadata."""
    buf = _io.BytesIO()
    try:
        df.to_parquet(buf, index=False)
        run = _run_lines(df)
        if run:
            import pyarrow.parquet as pq

            buf.seek(0)
            table = pq.read_table(buf)
            meta = dict(table.schema.metadata or {})
            meta.update({(k if k.startswith("accelcal_") else f"accelcal_{k}").encode():
                         v.encode() for k, v in run})
            buf = _io.BytesIO()
            pq.write_table(table.replace_schema_metadata(meta), buf)
    except ImportError as e:
        raise CalibrationError(
            f"writing {names['summary']} as Parquet needs pyarrow: pip install "
            f"'accelcal[fleet]' ({e})"
        ) from None
    return buf.getvalue()


def _comment_lines(path: str) -> list[str]:
    """The leading ``#`` lines of a text table (a fleet table's run record)."""
    lines = []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if not line.startswith("#"):
                break
            lines.append(line)
    return lines


def read_fleet_table(path: str | os.PathLike[str]) -> Any:
    """Read a table written by :func:`calibrate_many` (Parquet, or the CSV beside it)."""
    pd = _need_pandas()
    p = os.fspath(path)
    if p.lower().endswith((".parquet", ".pq")):
        return _read_table(p)
    try:
        head = _comment_lines(p)  # the run's record: accelcal version, detector, command
        # The text columns as text, even when every cell is empty (no note in any row).
        df = pd.read_csv(p, keep_default_na=False, na_values=[""], skiprows=len(head),
                         dtype={c: str for c in _TEXT_COLUMNS})
    except FileNotFoundError:
        raise CalibrationError(f"table not found: {p}") from None
    except (ValueError, OSError) as e:
        raise CalibrationError(f"cannot read the table {p}: {e}") from None
    for line in head:
        key, sep, text = line[1:].strip().partition(": ")
        if sep and key in _RUN_ATTRS:
            try:
                df.attrs[key] = json.loads(text) if key == "detector" else text
            except ValueError:
                df.attrs[key] = text
    for c in _INT_COLUMNS:
        if c in df.columns:
            df[c] = df[c].astype("Int64")
    for c in df.columns:
        if df[c].dtype == object or str(df[c].dtype).startswith("str"):
            df[c] = df[c].fillna("").astype(object)
    return df


def _check_outputs(out_paths: Sequence[Path], jobs: list[_Job], sources: Any,
                   names: dict[str, str]) -> None:
    given = {os.path.realpath(j.read_path) for j in jobs}
    if isinstance(sources, (str, os.PathLike)) and os.path.exists(sources):
        given.add(os.path.realpath(sources))
    for p in out_paths:
        if os.path.realpath(p) in given:
            raise CalibrationError(
                f"{names['summary']}/{names['out']} would overwrite an input: {p}; "
                "choose another name"
            )


# ---- the entry point ------------------------------------------------------------------------
def calibrate_many(
    sources: Any,
    *,
    g: float | None = None,
    lat: float | None = None,
    height: float | None = None,
    fs: float | None = None,
    columns: Any = None,
    time_column: Any = None,
    model: str = "lower",
    method: str = "lm",
    detector: Any = None,
    diagnose: bool = False,
    client: Any = None,
    workers: int | None = None,
    out: str | os.PathLike[str] | None = None,
    summary: str | os.PathLike[str] | None = None,
    progress: bool | None = None,
    check_g: bool = True,
    means: bool = False,
    sigma_g: float | None = None,
    overwrite: bool = False,
    _cli: bool = False,
    _command: str | None = None,
) -> Any:
    """Calibrate many static-session recordings; one row per recording.

    Each recording is read, its dwells are detected and the static model is fitted, exactly
    as ``accelcal calibrate static FILE`` does for one file. A recording that cannot be
    calibrated gives a row whose ``status`` says why; it never stops the run.

    Parameters
    ----------
    sources : list of paths, a glob (``"rec/*.csv"``), or a manifest
        A manifest is a DataFrame or a CSV/Parquet/workbook file with a ``path`` column and
        optional ``sensor_id``, ``g`` (m/s^2) or ``lat`` (deg) / ``height`` (m), ``sigma_g``
        (m/s^2), ``fs`` (Hz),
        ``columns`` ("ax,ay,az"), ``time_column``, ``date`` and ``bounds`` (a file of known
        dwells, :func:`accelcal.io.read_bounds`, used instead of detection) columns; a value
        in a row overrides the keyword default, an empty cell uses it. Relative paths in a
        manifest file are relative to the manifest's folder. Other manifest columns are
        carried into the result. A recording listed more than once with the same settings (the
        same file, however its path is spelled or linked) is calibrated once, in the row of its
        first entry, whose ``message`` names the entries; manifest rows that give one
        recording different settings are each calibrated, and each row names the others.
    g : reference gravity, m/s^2 (or ``lat``, deg, and ``height``, m: WGS84 normal gravity).
    sigma_g : std of the reference gravity, m/s^2, counted in every std as in
        :func:`~accelcal.fit_static` (a manifest's ``sigma_g`` column overrides it). A g from
        a latitude (``lat`` keyword or column) gets 1e-3 m/s^2, the formula's typical error
        against a gravimeter, unless one is given; otherwise None: g taken as exact.
    fs : sample rate, Hz, when the files do not give it.  columns, time_column : the
        accelerometer columns and the time column, as for :func:`accelcal.io.read_stream`.
    model, method : as for :func:`~accelcal.fit_static`.
    detector : :class:`~accelcal.DetectorSettings` for the dwell detector (default settings
        otherwise).
    diagnose : also run :func:`~accelcal.diagnose` (Allan-deviation noise model from the
        raw stream) and add the gap verdict columns.
    client : a ``dask.distributed.Client`` or a scheduler address (``"tcp://host:8786"``):
        the recordings are mapped over the cluster in small batches (up to 16 per task) and
        each file is read on the worker that processes it (the paths must be readable there).
        Default: a local process pool.
    workers : local processes (default: all cores; 1 runs in this process). Each process
        runs rayon with one thread, so N processes use N cores.
    out : folder for the calibration files: one TriadModel per calibrated recording, named
        ``<sensor_id>_<UTC date>.json`` (``YYYYmmddTHHMMSSZ``; the date is the manifest's
        ``date`` or the time of the fit), written atomically, so later calibrations of a
        sensor sit beside earlier ones and ``TriadModel.find`` picks the one valid at a time.
        A file already in the folder is never replaced: a name taken (by this run, or by an
        earlier one: a manifest date, two runs within a second) gives ``-2``, ``-3`` ..., and
        when an earlier file took it the row's ``message`` says so. A file there with exactly
        the content this run would write (the same recording, by path and by the SHA-256 the
        file records in ``metadata["source_sha256"]``, the same settings and result) is kept
        as it is and named in ``cal_file``. The table is also written there as
        ``fleet.parquet`` and ``fleet.csv`` (replaced by each run; a file of that name that
        is not a fleet table is not: see ``summary``) unless ``summary`` says otherwise.
    summary : path of the table (Parquet; the CSV is written beside it with a ``.csv``
        suffix), written atomically. The file named is replaced; the other one (and both
        ``fleet.*`` files in ``out``) only when it is a fleet table written before (it has
        the table's columns) or ``overwrite``: another file there is refused before any
        work (CalibrationError naming it).
    progress : progress bar over recordings on stderr: True, False, or None (only when stderr
        is a terminal).
    check_g : refuse a reference gravity outside 9.74-9.85 m/s^2 (default), as
        :func:`~accelcal.fit_static` does; False for a centrifuge or another planet.
    means : every recording is a table of dwell means, one pose per row (as ``--means`` for
        one file); without it such a table is recognised only when its rate is unknown and
        its rows step from attitude to attitude.
    overwrite : let the table replace a file beside it that is not a fleet table (see
        ``summary``); calibration files are never replaced.

    Returns
    -------
    pandas.DataFrame
        One row per recording, in input order: ``sensor_id``, ``path``, ``status`` (``ok``,
        ``weak``, ``misfit`` (residual RMS above ``MISFIT_RMS_G`` g and chi2/dof above
        ``MISFIT_CHI2_DOF``, the noise known: a faulty unit; the fit is in the row, no file
        written), ``degenerate`` or ``error`` (also a fit whose calibration file could not
        be written: disk full, no permission, a name too long; the message names the file and
        the fit stays in the row)), ``message`` (why, for anything but ``ok``),
        ``n_dwells``, ``n_samples``, ``duration_s``, ``fs_hz``, ``g_mps2``, ``g_source``,
        ``sigma_g_mps2`` (0: g taken as exact), ``model``, ``method``, each parameter
        ``sx ... m3`` with ``<name>_std`` (the
        recording's units: scale and coupling per m/s^2, bias in recording units; NaN when
        not fitted, and m1..m3 for ``model="diag"``), ``chi2_dof``, ``dof``, ``rms_mps2``,
        ``noise_model``, ``iterations``, ``temperature``, with ``diagnose=True`` ``gap_best``,
        ``gap_selected``, ``gap_structure``, ``gap_chi2_dof``, ``gap_p_value``,
        ``gap_held_out``, ``gap_rms_after_mps2``, ``gap_error``; then ``cal_file``,
        ``elapsed_s`` and ``worker`` (host:pid). ``DataFrame.attrs["units"]`` names the units,
        ``attrs["duplicates"]`` maps a recording listed more than once to its other entries,
        ``attrs["cal_files_kept"]`` lists the identical calibration files found in ``out``.

    Raises
    ------
    CalibrationError
        Only for the call itself (no gravity anywhere, unknown model or method, no
        recordings, an unreachable scheduler, an output that would overwrite an input or a
        file that is not a fleet table), and when the table cannot be written (the message
        names the file, the OS error and the calibration files written).
    """
    names = _names(_cli)
    _need_pandas()
    if model not in MODELS:
        raise CalibrationError(f"{names['model']} must be one of {', '.join(MODELS)}; "
                               f"got {model!r}")
    if method not in _METHODS:
        raise CalibrationError(f"{names['method']} must be one of {', '.join(_METHODS)}; "
                               f"got {method!r}")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int)
                                or workers < 1):
        raise CalibrationError(f"{names['workers']} must be a positive integer (processes); "
                               f"got {workers!r}")
    if workers is not None and client is not None:
        raise CalibrationError(f"{names['workers']} sets local processes; with "
                               f"{names['client']} the cluster's workers do the work")
    if g is not None:
        gv = _num(g, "g (m/s^2)", names["g"])
        if gv is None or gv <= 0:
            raise CalibrationError(f"{names['g']} must be positive; got {g!r}")
        g = gv
    from .dwell import DetectorSettings

    if detector is None:
        detector = DetectorSettings()
    elif not isinstance(detector, DetectorSettings):
        raise CalibrationError("detector must be an accelcal.DetectorSettings")
    det = dict(detector.__dict__)
    from ._triad_model import accelcal_version, iso_utc

    # What the table records of the run (DataFrame.attrs, the Parquet file's key-value
    # metadata, the CSV's leading comment lines); the command line is the CLI's.
    run = {"accelcal_version": accelcal_version(), "detector": dict(det), "command": _command}
    rows, base = _sources_table(sources, names)
    jobs = _make_jobs(rows, base, g=g, lat=lat, height=height, fs=fs, columns=columns,
                      time_column=time_column, model=model, method=method, detector=det,
                      diagnose=diagnose, cli=_cli, check_g=check_g, means=means,
                      sigma_g=sigma_g)
    named = summary is not None
    if summary is None and out is not None:
        summary = Path(out) / "fleet.parquet"
    if summary is not None:
        _check_outputs(list(_summary_paths(summary)), jobs, sources, names)
        _check_table_paths(summary, named, overwrite, names)

    results: list[Result | None] = [None] * len(jobs)
    kept: list[str] = []
    written: list[str] = []  # the calibration files this run wrote
    used: set[str] = set()
    folder = None if out is None else Path(out)
    first_unsaved = 0  # the calibration files are written in input order (-2 names alike)

    def save(res: Result) -> None:
        row, model_obj = res
        if folder is None or model_obj is None:
            return
        # How the file was made, as `calibrate static -o` records it (the settings are
        # recorded by the worker).
        if _command is not None:
            model_obj.metadata["command"] = _command
        model_obj.metadata["written"] = iso_utc(None)
        _check_outputs([folder / _cal_name(model_obj)], jobs, sources, names)
        try:
            folder.mkdir(parents=True, exist_ok=True)
            path, note, same = _save_new(model_obj, folder, used, names)
        except OSError as e:  # disk full, no permission, a name too long: this row's error
            what = (f"the calibration file {e.filename} could not be written"
                    if isinstance(e, _SaveError) else f"the folder {folder} could not be made")
            row["status"] = "error"
            row["message"] = "; ".join(x for x in (
                f"{what} ({_os_error(e)}); the fit is in this row", row.get("message") or "")
                if x)
            return
        row["cal_file"] = str(path)
        _add_note(row, note)
        (kept if same else written).append(str(path))

    def done(j: _Job, res: Result) -> None:
        """Each result as it arrives: its calibration file is written (atomically) as soon
        as those of the recordings before it are."""
        nonlocal first_unsaved
        _add_note(res[0], j.note)
        results[j.index] = res
        while first_unsaved < len(jobs) and results[first_unsaved] is not None:
            save(results[first_unsaved])  # type: ignore[arg-type]
            first_unsaved += 1

    try:
        if client is not None:
            _run_dask(jobs, client, progress, _cli, done)
        else:
            n = workers if workers is not None else _cores()
            _run_local(jobs, max(1, min(n, len(jobs))), progress, done)
    except KeyboardInterrupt as e:
        # What finished is kept: its calibration files, and the table of its rows.
        for res in results[first_unsaved:]:
            if res is not None:
                save(res)
        finished = [i for i, r in enumerate(results) if r is not None]
        what = f"interrupted after {len(finished)} of {len(jobs)} recordings"
        if summary is not None and finished:
            pq, csv = _summary_paths(summary)
            df = _table([results[i] for i in finished], [jobs[i] for i in finished],  # type: ignore[misc]
                        diagnose, kept, run)
            try:
                _write_table(df, pq, csv, names, folder, written)
                what += f": wrote the table of those to {pq} and {csv}"
                if folder is not None:
                    what += f", and their calibration files to {folder}"
            except CalibrationError as err:
                what += f": {err}"
        elif finished and folder is not None:
            what += f": wrote their calibration files to {folder}"
        e.args = (what,)
        raise
    df = _table(results, jobs, diagnose, kept, run)  # type: ignore[arg-type]
    if summary is not None:
        pq, csv = _summary_paths(summary)
        _write_table(df, pq, csv, names, folder, written)
    return df


def _table(results: list[Result], jobs: list[_Job], diagnose: bool, kept: list[str],
           run: dict[str, Any]) -> Any:
    """The table of these results, with a note on recordings that hold the same bytes, and
    the run's ``run`` (accelcal version, detector settings, command line) in its attrs."""
    _same_content(results, jobs)
    df = _frame(results, jobs, diagnose)
    df.attrs["duplicates"] = {j.path: list(j.listed_as[1:]) for j in jobs if j.listed_as}
    df.attrs["cal_files_kept"] = kept
    df.attrs.update(run)
    return df


def _same_content(results: list[Result], jobs: list[_Job]) -> None:
    """Recordings in different files with exactly the same bytes (by SHA-256: a copy of one
    recording under another name) are each calibrated, as different files; each row's
    message names the others."""
    by_sha: dict[str, list[int]] = collections.defaultdict(list)
    for i, (row, _) in enumerate(results):
        if row.get("_sha256"):
            by_sha[row["_sha256"]].append(i)
    for sha, idx in by_sha.items():
        if len(idx) < 2:
            continue
        keys = {i: _file_key(jobs[i].read_path) for i in idx}
        for i in idx:
            # the same file given twice with other settings says so already
            others = list(dict.fromkeys(jobs[k].path for k in idx if keys[k] != keys[i]))
            if not others:
                continue
            more = f" and {len(others) - 3} more" if len(others) > 3 else ""
            _add_note(results[i][0], (
                f"the same bytes as {_join(others[:3])}{more} (SHA-256 {sha[:12]}...): a "
                "copy of one recording under another name? Each file is calibrated as a "
                "unit of its own"))


# ---- the fleet report -----------------------------------------------------------------------
@dataclass
class FleetReport:
    """Summary of a fleet table (see :func:`fleet_report`).

    n : recordings.  counts : status -> number of recordings.
    distributions : one dict per parameter over the ``ok`` rows: ``param``, ``unit``, ``n``,
        ``median``, ``spread`` (robust std: 1.4826 x the median absolute deviation), ``min``,
        ``max``, ``screened`` (whether the outlier test could run on it).
    outliers : one dict per (sensor, parameter) with robust ``|z| > z_limit``: ``sensor_id``,
        ``path``, ``param``, ``value``, ``median``, ``z``.
    failed : one dict per recording with status misfit, degenerate or error: ``sensor_id``,
        ``path``, ``status``, ``message``.  weak : the same for status weak.
    z_limit : the outlier threshold on the robust z.
    noted : the same for ``ok`` recordings whose message says what was left out or noticed
        (dropout rows, dwells whose output did not follow the sensor, vibrating stretches):
        calibrated, but worth a look on a production line.
    unscreened : one dict per parameter the outlier test could not run on: ``param`` and
        ``reason`` (fewer than 3 ok recordings, or a spread of 0: at least half the values
        are equal, as copies of one recording give, and no robust z can be formed). Its
        outliers are then unknown, not absent.
    """

    n: int
    counts: dict[str, int]
    distributions: list[dict[str, Any]]
    outliers: list[dict[str, Any]]
    failed: list[dict[str, Any]]
    weak: list[dict[str, Any]]
    z_limit: float
    table: Any = field(repr=False, default=None)
    noted: list[dict[str, Any]] = field(default_factory=list)
    unscreened: list[dict[str, Any]] = field(default_factory=list)

    def summary(self) -> str:
        """The report as text."""
        c = self.counts
        L = [f"fleet: {self.n} recordings: " + ", ".join(f"{c.get(s, 0)} {s}" for s in STATUSES)]
        if self.distributions:
            L.append(f"parameter distributions over the {c.get('ok', 0)} ok recordings "
                     "(spread = 1.4826 x MAD):")
            L.append(f"  {'param':<10} {'median':>12} {'spread':>11} {'min':>12} {'max':>12}"
                     "  unit")
            for d in self.distributions:
                L.append(f"  {d['param']:<10} {d['median']:>12.6g} {d['spread']:>11.3g} "
                         f"{d['min']:>12.6g} {d['max']:>12.6g}  {d['unit']}")
        skipped = {u["param"] for u in self.unscreened}
        screened = [d["param"] for d in self.distributions if d["param"] not in skipped]
        if self.outliers:
            L.append(f"outlier sensors (robust |z| > {self.z_limit:g}):")
            by: dict[str, list[dict[str, Any]]] = {}
            for o in self.outliers:
                by.setdefault(f"{o['sensor_id']} ({o['path']})", []).append(o)
            for who, items in by.items():
                L.append(f"  {who}: " + ", ".join(
                    f"{o['param']} = {o['value']:.6g} (z = {o['z']:+.1f})" for o in items))
        elif screened and skipped:
            L.append(f"no outlier sensors among {', '.join(screened)} (robust |z| > "
                     f"{self.z_limit:g})")
        elif screened:
            L.append(f"no outlier sensors (robust |z| > {self.z_limit:g})")
        elif not self.distributions:
            L.append("outlier test not run: no ok recordings")
        # Say which parameters were not screened, and why: "no outliers" would claim a test
        # that did not run (grouped by reason: copies of one recording give them all).
        why: dict[str, list[str]] = {}
        for u in self.unscreened:
            why.setdefault(u["reason"], []).append(u["param"])
        for reason, ps in why.items():
            L.append(f"outlier test not run for {', '.join(ps)}: {reason}")
        if self.weak:
            L.append(f"weakly determined ({len(self.weak)}):")
            L += [f"  {f['sensor_id']} ({f['path']}): {f['message']}" for f in self.weak]
        if self.noted:
            L.append(f"calibrated, with notes ({len(self.noted)}):")
            L += [f"  {f['sensor_id']} ({f['path']}): {f['message']}" for f in self.noted]
        if self.failed:
            L.append(f"failed recordings ({len(self.failed)}):")
            L += [f"  {f['sensor_id']} ({f['path']}): {f['status']}: {f['message']}"
                  for f in self.failed]
        return "\n".join(L)

    def __str__(self) -> str:
        return self.summary()

    def to_dict(self) -> dict[str, Any]:
        return {
            "n": self.n, "counts": dict(self.counts), "distributions": self.distributions,
            "outliers": self.outliers, "failed": self.failed, "weak": self.weak,
            "noted": self.noted, "unscreened": self.unscreened, "z_limit": self.z_limit,
        }

    def plot(self, fig: Any = None) -> Any:
        """One histogram per parameter (ok recordings), outliers marked and named."""
        from .plots import _plt

        plt = _plt()
        dists = self.distributions
        if not dists:
            raise CalibrationError("no ok recordings to plot")
        ncol = 3
        nrow = math.ceil(len(dists) / ncol)
        if fig is None:
            fig = plt.figure(figsize=(4.0 * ncol, 2.9 * nrow))
        axs = np.atleast_1d(fig.subplots(nrow, ncol)).reshape(-1)
        ok = self.table[self.table["status"] == "ok"]
        for ax, d in zip(axs, dists, strict=False):
            p = d["param"]
            x = ok[p].to_numpy(dtype=float)
            x = x[np.isfinite(x)]
            ax.hist(x, bins=min(40, max(5, int(np.sqrt(x.size)) * 2)), color="0.6")
            ax.axvline(d["median"], color="k", lw=0.8)
            for o in (o for o in self.outliers if o["param"] == p):
                ax.axvline(o["value"], color="tab:red", lw=1.2)
                ax.annotate(f"{o['sensor_id']} z={o['z']:+.0f}", (o["value"], 1.0),
                            xycoords=("data", "axes fraction"), rotation=90, va="top",
                            ha="right", fontsize=7, color="tab:red")
            ax.set_xlabel(f"{p} ({d['unit']})")
            ax.set_ylabel("recordings")
            ax.locator_params(axis="x", nbins=5)
        for ax in axs[len(dists):]:
            ax.set_axis_off()
        n_out = len({o["sensor_id"] for o in self.outliers})
        skipped = ", ".join(u["param"] for u in self.unscreened)
        fig.suptitle(f"fleet of {self.n}: {self.counts.get('ok', 0)} ok; {n_out} outlier "
                     f"sensor(s) (red, robust |z| > {self.z_limit:g})"
                     + (f"; not screened: {skipped}" if skipped else ""))
        fig.tight_layout()
        return fig


def _unit(p: str) -> str:
    return COLUMN_UNITS.get(p, "")


def fleet_report(table: Any, *, z: float = 5.0) -> FleetReport:
    """Summarise a fleet table (a DataFrame from :func:`calibrate_many`, or the path of its
    Parquet/CSV file): distributions of every fitted parameter over the ``ok`` recordings,
    outlier sensors with robust ``|z| > z`` on any parameter (z = (value - median) /
    (1.4826 x MAD)), and the recordings that failed, with their reasons. A parameter the
    test cannot run on (fewer than 3 ok recordings, or a spread of 0: at least half the
    values equal, as copies of one recording give) is listed in ``unscreened`` with the
    reason, and the summary says so instead of "no outlier sensors"."""
    from .static import median_and_spread

    pd = _need_pandas()
    df = table if isinstance(table, pd.DataFrame) else read_fleet_table(table)
    missing = {"sensor_id", "path", "status", "message"} - set(df.columns)
    if missing:
        raise CalibrationError(
            f"not a fleet table from calibrate_many: columns {sorted(missing)} are missing"
        )
    zl = float(z)
    if not (math.isfinite(zl) and zl > 0):
        raise CalibrationError(f"z must be a positive number (robust z limit); got {z!r}")
    counts = {s: int((df["status"] == s).sum()) for s in STATUSES}
    ok = df[df["status"] == "ok"]
    dists: list[dict[str, Any]] = []
    outliers: list[dict[str, Any]] = []
    unscreened: list[dict[str, Any]] = []
    params = [p for p in PARAM_NAMES if p in df.columns]
    for p in params:
        x = ok[p].to_numpy(dtype=float)
        good = np.isfinite(x)
        if not good.any():
            continue
        xs = x[good]
        med, spread = median_and_spread(xs)
        screened = spread > 0 and xs.size >= 3
        dists.append({"param": p, "unit": _unit(p), "n": int(xs.size), "median": med,
                      "spread": spread, "min": float(xs.min()), "max": float(xs.max()),
                      "screened": screened})
        if xs.size < 3:
            unscreened.append({"param": p, "reason": f"fewer than 3 ok recordings ({xs.size})"
                                                     " to take a median and a spread from"})
        elif not spread > 0:
            n_diff = int((xs != med).sum())
            unscreened.append({"param": p, "reason": (
                f"its spread is 0: {xs.size - n_diff} of the {xs.size} ok recordings give "
                f"exactly the median (copies of one recording?), {n_diff} of the {xs.size} "
                "differ from it, and no robust z can be formed")})
        if screened:
            zz = (x - med) / spread
            for i in np.flatnonzero(good & (np.abs(zz) > zl)):
                r = ok.iloc[int(i)]
                outliers.append({"sensor_id": str(r["sensor_id"]), "path": str(r["path"]),
                                 "param": p, "value": float(x[i]), "median": med,
                                 "z": float(zz[i])})
    outliers.sort(key=lambda o: (str(o["sensor_id"]), -abs(float(o["z"]))))

    def rows(status: Sequence[str], noted: bool = False) -> list[dict[str, Any]]:
        sel = df[df["status"].isin(status)]
        if noted:
            sel = sel[sel["message"].fillna("").astype(str) != ""]
        return [{"sensor_id": str(r.sensor_id), "path": str(r.path), "status": str(r.status),
                 "message": str(r.message)} for r in sel.itertuples()]

    return FleetReport(len(df), counts, dists, outliers, rows(("misfit", "degenerate", "error")),
                       rows(("weak",)), zl, df, noted=rows(("ok",), noted=True),
                       unscreened=unscreened)
