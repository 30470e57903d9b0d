"""Readers for accelerometer recordings: delimited text (with or without header and metadata
lines), ``.npy`` and ``.npz``; plus chunked reading that streams large files into
:class:`~accelcal.DwellAccumulator`.

Layout rules for text files
---------------------------
* Fields are separated by commas, semicolons, tabs or runs of whitespace (decided from the
  first data row).
* Lines before the data may be metadata: ``key,value``, ``key: value``, ``key = value``, each
  optionally commented with ``#``. A numeric ``Fs`` / ``fs`` / ``sample_rate`` / ``rate``
  (any case) gives the sample rate.
* The last non-numeric line with at least three fields right before the data is the header.
* Accelerometer columns are chosen by name (``ax``/``ay``/``az``, ``acc_x``..., ``accx``...,
  ``accel_x``..., and only when none of those exist ``x``/``y``/``z``; unit suffixes such as
  ``acc_x [m/s^2]`` are ignored). A time column is recognised by name (``t``, ``time``,
  ``timestamp``, ``t[s]``, ``time_s``, ``time_ms`` ...; ``ms``/``us``/``ns`` units are converted
  to s) and a temperature column by a name starting with ``temp``.
* Without a header, three columns are ``x, y, z`` and four columns whose first column is
  strictly increasing (over the first 10 000 rows) are ``t, x, y, z``; anything else needs
  ``columns=``.
"""

from __future__ import annotations

import itertools
import os
import re
import zipfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, TextIO

import numpy as np
from numpy.typing import NDArray

from ._core import CalibrationError
from ._validate import positive

__all__ = ["Stream", "iter_stream", "read_stream", "stream_dwells"]

#: Rows sniffed at the start of a text file (layout, time-column check, fs estimate).
_SNIFF_ROWS = 10_000
#: Most lines accepted before the first data row.
_MAX_PREAMBLE = 1_000

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
}
_TIME_BASES = {"t", "time", "timestamp", "timestamps", "tstamp", "elapsed", "elapsedtime"}
_TIME_UNITS = {
    "": 1.0,
    "s": 1.0,
    "sec": 1.0,
    "secs": 1.0,
    "seconds": 1.0,
    "ms": 1e-3,
    "msec": 1e-3,
    "us": 1e-6,
    "µs": 1e-6,
    "ns": 1e-9,
}
_ACC_NAME = re.compile(
    r"^(?:a|acc|accl|accel|acceleration|accelerometer|linacc|rawacc|accraw)([xyz])$"
)
_SAMPLE_KEYS = ("samples", "acc", "accel", "acceleration", "a", "data", "x")
_T_KEYS = ("t", "time", "timestamp", "timestamps")
_FS_NPZ_KEYS = ("fs", "fs_hz", "sample_rate", "sampling_rate", "rate")
_TEMP_KEYS = ("temperature", "temp", "temperature_c", "temp_c")


@dataclass
class Stream:
    """A recording read from a file.

    Attributes
    ----------
    samples : (N, 3) array
        Accelerometer output x, y, z in the file's units (float64 for text files; the stored
        dtype for ``.npy``/``.npz``).
    t : (N,) float64 or None
        Sample times in s (from the time column, else ``arange(N) / fs``; None when neither).
    fs : float or None
        Sample rate in Hz: given > file metadata > median interval of the time column.
    metadata : dict
        ``key -> value`` strings from the lines before the data (and scalar ``.npz`` entries).
    names : tuple of str
        Names of the three chosen columns (``"0"``, ``"1"`` ... when the file has no header).
    path : str
        The file read.
    temperature : (N,) float64 or None
        Temperature per sample when a temperature column was recognised.
    """

    samples: NDArray[Any]
    t: NDArray[np.float64] | None
    fs: float | None
    metadata: dict[str, str] = field(default_factory=dict)
    names: tuple[str, ...] = ()
    path: str = ""
    temperature: NDArray[np.float64] | None = None

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


def _norm(name: str) -> str:
    base, _ = _split_unit(name)
    return re.sub(r"[^0-9a-zµ]", "", base.lower())


def _time_scale(name: str) -> float | None:
    """Factor to seconds when ``name`` is a time column, else None."""
    base, unit = _split_unit(name)
    b = base.lower().strip()
    if not unit:
        m = re.match(r"^(.*?)[_\s-]+(s|sec|secs|seconds|ms|msec|us|µs|ns)$", b)
        if m:
            b, unit = m.group(1), m.group(2)
    b = re.sub(r"[^0-9a-z]", "", b)
    if b not in _TIME_BASES:
        return None
    return _TIME_UNITS.get(unit.lower().strip())


def _is_temperature(name: str) -> bool:
    return _norm(name).startswith("temp")


def _auto_acc(names: Sequence[str], path: str) -> list[int] | None:
    """Indices of the x, y, z accelerometer columns chosen by name, or None."""
    norm = [_norm(n) for n in names]
    for tier in ("acc", "plain"):
        found: dict[str, list[int]] = {"x": [], "y": [], "z": []}
        for i, n in enumerate(norm):
            if tier == "acc":
                m = _ACC_NAME.match(n)
                if m:
                    found[m.group(1)].append(i)
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
    return None


def _resolve_columns(columns: Any, names: Sequence[str] | None, ncols: int, path: str) -> list[int]:
    """User ``columns`` (3 names/indices or "a,b,c") to 0-based indices."""
    if isinstance(columns, str):
        columns = [c.strip() for c in columns.split(",")]
    try:
        cols = list(columns)
    except TypeError:
        raise CalibrationError(
            f"columns must be 3 names or 0-based indices; got {columns!r}"
        ) from None
    if len(cols) != 3:
        raise CalibrationError(f"columns must name exactly 3 columns (x, y, z); got {cols!r}")
    return [_resolve_one(c, names, ncols, path, "columns") for c in cols]


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
    try:
        float(s)
    except ValueError:
        return False
    return True


def _split(line: str, delim: str | None) -> list[str]:
    if delim is None:
        return line.split()
    return [f.strip() for f in line.split(delim)]


def _guess_delim(line: str) -> str | None:
    for d in (",", ";", "\t"):
        if d in line:
            return d
    return None


def _meta_pair(line: str) -> tuple[str, str] | None:
    s = line.strip().lstrip("#%").strip()
    if not s:
        return None
    for sep in ("=", ":", ",", ";", "\t"):
        if sep in s:
            k, v = s.split(sep, 1)
            k, v = k.strip(), v.strip().rstrip(",;").strip()
            if k and not _is_number(k) and sep in ",;\t" and any(x in v for x in ",;\t"):
                return None  # a row of several fields, not key,value
            if k and not _is_number(k):
                return k, v
            return None
    return None


def _fs_from_meta(meta: dict[str, str]) -> float | None:
    for k, v in meta.items():
        if re.sub(r"[^0-9a-z]", "", k.lower()) in _FS_KEYS:
            tok = v.split()
            if tok and _is_number(tok[0]):
                f = float(tok[0])
                if np.isfinite(f) and f > 0:
                    return f
    return None


@dataclass
class _Layout:
    path: str
    delim: str | None
    skip: int  # lines before the first data row
    ncols: int
    names: tuple[str, ...] | None  # header names, None without header
    acc: list[int]
    time: int | None
    time_scale: float
    temp: int | None
    metadata: dict[str, str]
    fs: float | None
    head: NDArray[np.float64] = field(repr=False, default_factory=lambda: np.empty((0, 0)))


def _open_text(path: str) -> TextIO:
    try:
        return open(path, encoding="utf-8", errors="strict", newline=None)
    except FileNotFoundError:
        raise CalibrationError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise CalibrationError(f"{path}: is a directory, not a recording file") from None
    except OSError as e:
        raise CalibrationError(f"{path}: cannot read file ({e.strerror})") from None


def _load_rows(
    lines: list[str], delim: str | None, ncols: int, path: str, first_line: int
) -> NDArray[np.float64]:
    """Parse data lines into a float64 (m, ncols) array with a clear error on bad rows."""
    if not lines:
        return np.empty((0, ncols))
    try:
        a = np.loadtxt(lines, delimiter=delim, dtype=np.float64, ndmin=2, comments="#")
    except ValueError as e:
        msg = str(e).splitlines()[0] if str(e) else "unparseable value"
        m = re.search(r"row (\d+)", msg)
        where = ""
        if m:
            where = f" (near line {first_line + int(m.group(1))})"
        raise CalibrationError(f"{path}: non-numeric or ragged data{where}: {msg}") from None
    if a.shape[0] and a.shape[1] != ncols:
        raise CalibrationError(
            f"{path}: data rows have {a.shape[1]} columns but the first data row has {ncols}"
        )
    return a


def _sniff(path: str, columns: Any, fs: float | None, time_column: Any) -> _Layout:
    meta: dict[str, str] = {}
    header: list[str] | None = None
    skip = 0
    first: str | None = None
    with _open_text(path) as fh:
        try:
            for line in fh:
                s = line.strip()
                if not s:
                    skip += 1
                    continue
                delim = _guess_delim(s)
                fields = _split(s, delim)
                if (
                    not s.startswith(("#", "%", "//"))
                    and all(_is_number(f) for f in fields if f)
                    and len(fields) >= 1
                ):
                    first = s
                    break
                skip += 1
                if skip > _MAX_PREAMBLE:
                    raise CalibrationError(
                        f"{path}: no numeric data row in the first {_MAX_PREAMBLE} lines"
                    )
                body = s.lstrip("#%/").strip()
                bf = _split(body, _guess_delim(body))
                if len(bf) >= 3 and not any(_is_number(f) for f in bf if f) and "=" not in body:
                    header = bf
                    continue
                header = None
                kv = _meta_pair(s)
                if kv:
                    meta[kv[0]] = kv[1]
            if first is None:
                if skip == 0:
                    raise CalibrationError(f"{path}: file is empty")
                raise CalibrationError(f"{path}: no numeric data rows found")
            delim = _guess_delim(first)
            ncols = len(_split(first, delim))
            head_lines = [first, *itertools.islice(fh, _SNIFF_ROWS - 1)]
        except UnicodeDecodeError:
            raise CalibrationError(f"{path}: not a text file (cannot decode as UTF-8)") from None
    head = _load_rows(head_lines, delim, ncols, path, skip + 1)
    names: tuple[str, ...] | None = None
    if header is not None:
        if len(header) == ncols:
            names = tuple(h.strip().strip("\"'") for h in header)
        else:
            raise CalibrationError(
                f"{path}: header has {len(header)} names but data rows have {ncols} columns"
            )
    return _decide(path, names, ncols, head, meta, delim, skip, columns, fs, time_column)


def _decide(
    path: str,
    names: tuple[str, ...] | None,
    ncols: int,
    head: NDArray[Any],
    meta: dict[str, str],
    delim: str | None,
    skip: int,
    columns: Any,
    fs: float | None,
    time_column: Any,
) -> _Layout:
    """Choose accelerometer, time and temperature columns and the sample rate."""
    tcol: int | None = None
    tscale = 1.0
    if time_column is not None:
        tcol = _resolve_one(time_column, names, ncols, path, "time_column")
        if names is not None:
            tscale = _time_scale(names[tcol]) or 1.0
    elif names is not None:
        for i, n in enumerate(names):
            sc = _time_scale(n)
            if sc is not None:
                tcol, tscale = i, sc
                break
    if columns is not None:
        acc = _resolve_columns(columns, names, ncols, path)
    elif names is not None:
        found = _auto_acc(names, path)
        if found is None:
            raise CalibrationError(
                f"{path}: no accelerometer columns recognised among {list(names)}; "
                "give columns=[...] (3 names or 0-based indices)"
            )
        acc = found
    else:
        rest = [i for i in range(ncols) if i != tcol]
        if len(rest) == 3:
            acc = rest
        elif ncols == 4 and tcol is None and _increasing(head[:, 0]):
            tcol, acc = 0, [1, 2, 3]
        else:
            raise CalibrationError(
                f"{path}: {ncols} columns and no header row: cannot tell which are the "
                "accelerometer x, y, z; give columns=[...] (0-based indices) and, if there is "
                "one, time_column="
            )
    if tcol is not None and tcol in acc:
        tcol = None
    temp = None
    if names is not None:
        for i, n in enumerate(names):
            if i not in acc and i != tcol and _is_temperature(n):
                temp = i
                break
    fsv = positive(fs, "fs", " (sample rate in Hz)") if fs is not None else _fs_from_meta(meta)
    if fsv is None and tcol is not None:
        fsv = _fs_from_time(head[:, tcol] * tscale, path)
    return _Layout(
        path=path,
        delim=delim,
        skip=skip,
        ncols=ncols,
        names=names,
        acc=acc,
        time=tcol,
        time_scale=tscale,
        temp=temp,
        metadata=meta,
        fs=fsv,
        head=head,
    )


def _increasing(x: NDArray[Any]) -> bool:
    return bool(x.shape[0] >= 2 and np.all(np.isfinite(x)) and np.all(np.diff(x) > 0))


def _fs_from_time(t: NDArray[Any], path: str) -> float | None:
    """Sample rate from the median interval of (the first rows of) a time column."""
    if t.shape[0] < 2:
        return None
    d = np.diff(t.astype(np.float64))
    d = d[np.isfinite(d)]
    if d.size == 0:
        return None
    med = float(np.median(d))
    if not med > 0:
        raise CalibrationError(
            f"{path}: the time column is not increasing (median interval {med!r}); "
            "give fs= or time_column="
        )
    return 1.0 / med


def _names_of(lay: _Layout) -> tuple[str, ...]:
    if lay.names is None:
        return tuple(str(i) for i in lay.acc)
    return tuple(lay.names[i] for i in lay.acc)


def _text_chunks(lay: _Layout, chunk_rows: int) -> Iterator[NDArray[np.float64]]:
    with _open_text(lay.path) as fh:
        try:
            for _ in range(lay.skip):
                next(fh)
            line_no = lay.skip + 1
            while True:
                lines = list(itertools.islice(fh, chunk_rows))
                if not lines:
                    return
                a = _load_rows(lines, lay.delim, lay.ncols, lay.path, line_no)
                line_no += len(lines)
                if a.shape[0]:
                    yield a
        except UnicodeDecodeError:
            raise CalibrationError(
                f"{lay.path}: not a text file (cannot decode as UTF-8)"
            ) from None


# ---- numpy files ------------------------------------------------------------------------------
def _npy_layout(
    path: str,
    arr: NDArray[Any],
    columns: Any,
    fs: float | None,
    time_column: Any,
    meta: dict[str, str],
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
    return _decide(path, None, arr.shape[1], head, meta, None, 0, columns, fs, time_column)


def _np_load(path: str, mmap: bool = False) -> Any:
    try:
        return np.load(path, allow_pickle=False, mmap_mode="r" if mmap else None)
    except FileNotFoundError:
        raise CalibrationError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise CalibrationError(f"{path}: is a directory, not a recording file") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise CalibrationError(f"{path}: cannot read as a NumPy file ({e})") from None


def _read_npz(path: str, columns: Any, fs: float | None, time_column: Any) -> Stream:
    try:
        # Open the file here: np.load leaks its handle when the zip is corrupt.
        with open(path, "rb") as fh:
            z = np.load(fh, allow_pickle=False)
            if not hasattr(z, "files"):
                raise CalibrationError(f"{path}: not a .npz archive (rename it .npy?)")
            with z:
                files = list(z.files)
                data = {k: z[k] for k in files}
    except FileNotFoundError:
        raise CalibrationError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise CalibrationError(f"{path}: is a directory, not a recording file") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise CalibrationError(f"{path}: cannot read as a .npz archive ({e})") from None
    return _from_arrays(path, data, columns, fs, time_column)


def _read_h5(path: str, columns: Any, fs: float | None, time_column: Any) -> Stream:
    """HDF5 (optional extra ``hdf5``): datasets by name as in ``.npz``; attributes as metadata."""
    try:
        import h5py
    except ImportError:
        raise CalibrationError(
            f"{path}: reading HDF5 needs h5py: pip install 'accelcal[hdf5]'"
        ) from None
    data: dict[str, Any] = {}
    try:
        with h5py.File(path, "r") as f:

            def visit(name: str, obj: Any) -> None:
                if isinstance(obj, h5py.Dataset):
                    leaf = name.split("/")[-1]
                    data[leaf if leaf not in data else name] = obj[()]

            f.visititems(visit)
            for k, v in f.attrs.items():
                if np.ndim(v) == 0 and k not in data:
                    data[k] = np.asarray(v)
    except FileNotFoundError:
        raise CalibrationError(f"{path}: file not found") from None
    except (OSError, ValueError) as e:
        raise CalibrationError(f"{path}: cannot read as an HDF5 file ({e})") from None
    return _from_arrays(path, data, columns, fs, time_column)


def _from_arrays(
    path: str, data: dict[str, Any], columns: Any, fs: float | None, time_column: Any
) -> Stream:
    files = list(data)
    key = next((k for k in _SAMPLE_KEYS if k in data and np.ndim(data[k]) == 2), None)
    if key is None:
        two = [k for k in files if np.ndim(data[k]) == 2]
        if len(two) != 1:
            raise CalibrationError(
                f"{path}: cannot tell which array holds the samples (keys {files}); "
                f"name it one of {list(_SAMPLE_KEYS)}"
            )
        key = two[0]
    arr = data[key]
    meta = {k: str(v.item()) for k, v in data.items() if np.ndim(v) == 0}
    fsv: float | None = fs
    if fsv is None:
        fk = next((k for k in _FS_NPZ_KEYS if k in data and np.ndim(data[k]) == 0), None)
        if fk is not None:
            fsv = positive(data[fk].item(), f"{path}: {fk}", " (Hz)")
    lay = _npy_layout(path, arr, columns, fsv, time_column, meta)
    n = arr.shape[0]
    t = None
    tk = next((k for k in _T_KEYS if k in data), None)
    if tk is not None and lay.time is None:
        t = np.asarray(data[tk], dtype=np.float64).reshape(-1)
        if t.shape != (n,):
            raise CalibrationError(
                f"{path}: {tk!r} has {t.shape[0]} values but samples have {n} rows"
            )
        if lay.fs is None:
            lay.fs = _fs_from_time(t[:_SNIFF_ROWS], path)
    elif lay.time is not None:
        t = np.asarray(arr[:, lay.time], dtype=np.float64) * lay.time_scale
    temp = None
    mk = next((k for k in _TEMP_KEYS if k in data), None)
    if mk is not None:
        temp = np.asarray(data[mk], dtype=np.float64).reshape(-1)
        if temp.shape != (n,):
            raise CalibrationError(
                f"{path}: {mk!r} has {temp.shape[0]} values but samples have {n} rows"
            )
    if t is None and lay.fs is not None:
        t = np.arange(n, dtype=np.float64) / lay.fs
    samples = arr if lay.acc == [0, 1, 2] and arr.shape[1] == 3 else arr[:, lay.acc]
    return Stream(samples, t, lay.fs, meta, _names_of(lay), path, temp)


# ---- public API -------------------------------------------------------------------------------
def _path(path: str | os.PathLike[str]) -> str:
    try:
        return os.fspath(path)
    except TypeError:
        raise CalibrationError(f"path must be a file path; got {path!r}") from None


def _kind(p: str) -> str:
    low = p.lower()
    if low.endswith(".npy"):
        return "npy"
    if low.endswith(".npz"):
        return "npz"
    if low.endswith((".h5", ".hdf5", ".hdf")):
        return "h5"
    return "text"


def read_stream(
    path: str | os.PathLike[str],
    *,
    columns: Any = None,
    fs: float | None = None,
    time_column: Any = None,
) -> Stream:
    """Read a recording as it is (text, ``.npy`` or ``.npz``).

    Parameters
    ----------
    path : str or path-like
        The file. ``.npy`` holds an (N, 3) or (N, >=3) array; ``.npz`` holds ``samples`` (or
        ``acc``, ``a``, ``data``) and optionally ``t``, ``fs``, ``temperature``; anything else
        is read as delimited text (see the module docstring for the layout rules).
    columns : 3 names or 0-based indices, or "ax,ay,az", optional
        The accelerometer x, y, z columns; chosen by name when omitted.
    fs : float, optional
        Sample rate in Hz; overrides the file's metadata and time column.
    time_column : name or 0-based index, optional
        The time column (s, or ms/us/ns when the name says so); recognised by name when omitted.

    Returns
    -------
    Stream
        ``samples`` (N, 3), ``t`` (N,) s or None, ``fs`` Hz or None, ``metadata``, ``names``,
        ``path``, ``temperature`` (N,) or None.

    Raises
    ------
    CalibrationError
        Missing, unreadable, empty or non-numeric file, or columns that cannot be chosen.
    """
    p = _path(path)
    kind = _kind(p)
    if kind == "npz":
        return _read_npz(p, columns, fs, time_column)
    if kind == "h5":
        return _read_h5(p, columns, fs, time_column)
    if kind == "npy":
        arr = _np_load(p)
        if not isinstance(arr, np.ndarray):
            raise CalibrationError(f"{p}: not a .npy array file")
        lay = _npy_layout(p, arr, columns, fs, time_column, {})
        data = arr
    else:
        lay = _sniff(p, columns, fs, time_column)
        chunks = list(_text_chunks(lay, 1_000_000))
        data = np.concatenate(chunks) if len(chunks) > 1 else chunks[0]
    n = data.shape[0]
    if kind == "npy" and lay.acc == [0, 1, 2] and data.shape[1] == 3:
        samples = data
    else:
        samples = np.ascontiguousarray(data[:, lay.acc])
    t = None
    if lay.time is not None:
        t = np.asarray(data[:, lay.time], dtype=np.float64) * lay.time_scale
    elif lay.fs is not None:
        t = np.arange(n, dtype=np.float64) / lay.fs
    temp = None if lay.temp is None else np.asarray(data[:, lay.temp], dtype=np.float64)
    return Stream(samples, t, lay.fs, dict(lay.metadata), _names_of(lay), p, temp)


def _layout_for(p: str, columns: Any, fs: float | None, time_column: Any) -> tuple[_Layout, Any]:
    kind = _kind(p)
    if kind == "npy":
        arr = _np_load(p, mmap=True)
        if not isinstance(arr, np.ndarray):
            raise CalibrationError(f"{p}: not a .npy array file")
        return _npy_layout(p, arr, columns, fs, time_column, {}), arr
    if kind in ("npz", "h5"):
        return _Layout(p, None, 0, 3, None, [0, 1, 2], None, 1.0, None, {}, None), None
    return _sniff(p, columns, fs, time_column), None


def _chunks(
    p: str, columns: Any, fs: float | None, time_column: Any, chunk_rows: int
) -> tuple[
    float | None,
    Iterator[tuple[NDArray[Any], NDArray[np.float64] | None, NDArray[np.float64] | None]],
]:
    """Sample rate and an iterator of (samples, t, temperature) chunks."""
    if (
        not isinstance(chunk_rows, (int, np.integer))
        or isinstance(chunk_rows, bool)
        or chunk_rows < 1
    ):
        raise CalibrationError(f"chunk_rows must be a positive integer; got {chunk_rows!r}")
    chunk_rows = int(chunk_rows)
    kind = _kind(p)
    if kind in ("npz", "h5"):
        s = (_read_npz if kind == "npz" else _read_h5)(p, columns, fs, time_column)

        def gen_npz() -> Iterator[Any]:
            for i in range(0, len(s), chunk_rows):
                sl = slice(i, i + chunk_rows)
                yield (
                    s.samples[sl],
                    None if s.t is None else s.t[sl],
                    None if s.temperature is None else s.temperature[sl],
                )

        return s.fs, gen_npz()
    lay, arr = _layout_for(p, columns, fs, time_column)

    def gen() -> Iterator[Any]:
        pos = 0
        source = (
            (np.asarray(arr[i : i + chunk_rows]) for i in range(0, arr.shape[0], chunk_rows))
            if arr is not None
            else _text_chunks(lay, chunk_rows)
        )
        for a in source:
            m = a.shape[0]
            samples = (
                a
                if (arr is not None and lay.acc == [0, 1, 2] and a.shape[1] == 3)
                else a[:, lay.acc]
            )
            if lay.time is not None:
                t = np.asarray(a[:, lay.time], dtype=np.float64) * lay.time_scale
            elif lay.fs is not None:
                t = np.arange(pos, pos + m, dtype=np.float64) / lay.fs
            else:
                t = None
            temp = None if lay.temp is None else np.asarray(a[:, lay.temp], dtype=np.float64)
            pos += m
            yield samples, t, temp

    return lay.fs, gen()


def iter_stream(
    path: str | os.PathLike[str],
    *,
    chunk_rows: int = 500_000,
    columns: Any = None,
    fs: float | None = None,
    time_column: Any = None,
) -> Iterator[tuple[NDArray[Any], NDArray[np.float64] | None]]:
    """Read a recording chunk by chunk without loading it whole.

    Same layout rules and arguments as :func:`read_stream`. ``.npy`` files are memory-mapped;
    ``.npz`` files are loaded whole (the format cannot be streamed).

    Yields
    ------
    samples : (m, 3) array
        At most ``chunk_rows`` rows; concatenated, the chunks equal ``read_stream(path).samples``.
    t : (m,) float64 or None
        Sample times in s (time column, else from ``fs``; None when neither is known).
    """
    _, it = _chunks(_path(path), columns, fs, time_column, chunk_rows)
    for s, t, _temp in it:
        yield s, t


def stream_dwells(
    path: str | os.PathLike[str],
    *,
    fs: float | None = None,
    bounds: Any = None,
    columns: Any = None,
    time_column: Any = None,
    chunk_rows: int = 500_000,
    units: str = "",
    progress: bool | None = False,
    **detector_kw: Any,
) -> Any:
    """Dwell statistics of a (large) recording, streamed chunk by chunk.

    ``progress``: show a progress bar of rows read (True), only when stderr is a terminal
    (None), or never (False, the default for library use).

    With ``bounds`` (k, 2) the given ``[start, stop)`` dwells are accumulated; otherwise the
    static intervals are detected (needs ``fs`` from the argument, the file's metadata or its
    time column; ``detector_kw`` are :class:`~accelcal.DetectorSettings` fields). Memory use is
    one chunk plus compressed block statistics. The result equals :func:`~accelcal.dwell_stats`
    / :func:`~accelcal.detect_dwells` on ``read_stream(path)`` with the same ``t`` and
    ``temperature`` channels.

    Returns
    -------
    DwellSet
    """
    from .dwell import DwellAccumulator

    p = _path(path)
    fsv, it = _chunks(p, columns, fs, time_column, chunk_rows)
    if bounds is None and fsv is None:
        raise CalibrationError(
            f"{p}: the sample rate is unknown (no fs metadata or time column); give fs= (Hz)"
        )
    acc = DwellAccumulator(
        bounds, fs=fsv, units=units, **({} if bounds is not None else detector_kw)
    )
    pushed = 0
    from tqdm import tqdm

    disable = True if progress is False else (None if progress is None else False)
    with tqdm(unit=" rows", unit_scale=True, desc=os.path.basename(p), disable=disable,
              leave=False) as bar:
        for s, t, temp in it:
            acc.push(s, t, temp)
            pushed += s.shape[0]
            bar.update(s.shape[0])
    if pushed == 0:
        raise CalibrationError(f"{p}: no data rows")
    return acc.finish()
