"""Commands on raw recordings: ``dwells`` (static intervals and their statistics) and
``apply`` (a calibration applied to a stream). Both read the recording in one streaming pass
with bounded memory, whatever its length."""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import stat
import struct
import sys
import zipfile
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import IO, Any

import click
import numpy as np

from .._core import CalibrationError
from .._files import atomic_open, atomic_path, file_record, temp_beside
from ._common import (
    _need_plot,
    _save_fig,
    bounds_option,
    cli_notes,
    count_of,
    detector_options,
    dwell_notes,
    echo_notes,
    emit_json,
    friendly,
    main,
    means_option,
    open_recording,
    recording_options,
    source_line,
    stream_dwells,
)


class _Envelope:
    """A decimated picture of the stream for the figure: mean, min and max of every axis over
    bins of ``bin_rows`` samples (bins restart at chunk boundaries)."""

    def __init__(self, bin_rows: int) -> None:
        self.bin = max(int(bin_rows), 1)
        self.pos = 0
        self.idx: list[np.ndarray] = []
        self.mean: list[np.ndarray] = []
        self.lo: list[np.ndarray] = []
        self.hi: list[np.ndarray] = []

    def push(self, s: np.ndarray) -> None:
        m = s.shape[0]
        starts = np.arange(0, m, self.bin)
        x = np.asarray(s, dtype=np.float64)
        self.idx.append(self.pos + starts + np.minimum(self.bin, m - starts) / 2.0)
        width = np.diff(np.append(starts, m))
        self.mean.append(np.add.reduceat(x, starts, axis=0) / width[:, None])
        self.lo.append(np.minimum.reduceat(x, starts, axis=0))
        self.hi.append(np.maximum.reduceat(x, starts, axis=0))
        self.pos += m

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return (np.concatenate(self.idx), np.concatenate(self.mean), np.concatenate(self.lo),
                np.concatenate(self.hi))


def _units_of(names: tuple[str, ...]) -> str:
    from ..io import _split_unit

    units = {_split_unit(n)[1] for n in names}
    return units.pop() if len(units) == 1 and "" not in units else ""


@main.command()
@click.argument("file", type=click.Path(allow_dash=True))
@recording_options
@detector_options
@bounds_option
@means_option
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Write the dwell table as CSV (calibrate static reads it back).")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None,
              help="The stream with the dwells shaded (PNG/PDF/SVG).")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@friendly
def dwells(
    file: str,
    fs: float | None,
    columns: str | None,
    time_column: str | None,
    quiet: bool,
    window_s: float,
    k: float,
    min_dwell_s: float,
    trim_s: float,
    bounds: str | None,
    means: bool,
    count: int | None,
    output: str | None,
    plot_path: str | None,
    as_json: bool,
) -> None:
    """Detect the static dwells of a recording (or take them from --bounds) and print their
    statistics."""
    from ..io import _progress_bar

    _need_plot(plot_path)
    if plot_path and means:
        raise CalibrationError("--plot draws the stream of samples; a table of dwell means "
                               "(--means) has none")
    if not plot_path:
        d, rec = stream_dwells(file, fs, columns, time_column, quiet, "dwells", bounds, means,
                               count=count, window_s=window_s, k=k, min_dwell_s=min_dwell_s,
                               trim_s=trim_s)
    else:
        # The same single pass, also keeping a decimated picture of the stream.
        from ..io import _named_dwells, read_bounds

        rec = open_recording(file, fs, columns, time_column)
        known = read_bounds(bounds) if bounds else None
        acc = rec.dwell_accumulator(known, window_s=window_s, k=k, min_dwell_s=min_dwell_s,
                                    trim_s=trim_s)
        env = _Envelope((rec.rows_estimate() or 100_000) // 4000)
        with _progress_bar(rec, "dwells", False if quiet else None) as cb:
            for s, t, temp in rec.chunks(None, cb):
                acc.push(s, t, temp)
                env.push(s)
        if rec.rows == 0:
            raise CalibrationError(f"{rec.path}: no data rows")
        d = _named_dwells(acc.finish(), known)
    notes = ([] if rec is None else rec.notes()) + dwell_notes(d)
    faults = d.faults()
    if faults:
        from ..dwell import fault_text

        notes.append(f"{len({f.dwell for f in faults})} of {len(d)} dwells have an output that "
                     "did not follow the sensor (calibrate and diagnose leave them out):\n  "
                     + fault_text(d, faults))
    if output:
        # The table names its recording and the detector's settings (when it detected them).
        if rec is not None:
            d.source = file_record(file)
            if not bounds and not rec.pose_table:
                d.detector = {"window_s": window_s, "k": k, "min_dwell_s": min_dwell_s,
                              "trim_s": trim_s}
        d.to_csv(output)
    if plot_path:
        from ..plots import dwells_figure

        idx, mean, lo, hi = env.arrays()
        fig = dwells_figure(idx / rec.fs, mean, lo, hi, d, units=_units_of(_names(rec)),
                            title=os.path.basename(file))
        _save_fig(fig, plot_path)
    if as_json:
        out = d.to_dict()
        out.update(file=file, samples=None if rec is None else rec.rows,
                   notes=cli_notes(notes))
        emit_json(out)
        return
    echo_notes(notes)
    click.echo(source_line(file, rec, d) if rec is not None else
               f"{file}: {count_of(len(d))}")
    if d.noise_std is not None and d.threshold is not None:
        unit = (_units_of(_names(rec)) if rec is not None else "") or d.units or (
            "the recording's units")
        click.echo(
            "detector's noise level per axis x, y, z (a low quantile of the window stds, "
            "from the data): "
            + " ".join(f"{v:.4g}" for v in d.noise_std)
            + f" [{unit}]; threshold = {k:g} x noise variance"
        )
    click.echo(d.table())
    for p in (output, plot_path):
        if p:
            click.echo(f"wrote {p}")


def _names(rec: Any) -> tuple[str, ...]:
    from ..io import _names_of

    return _names_of(rec.lay)


# ---- apply: streaming writers ------------------------------------------------------------------
#: Outputs that are this process's standard output: written as ``-`` is (text, the summary
#: line on stderr), not opened by name.
STDOUT_NAMES = frozenset({"-", "/dev/stdout", "/dev/fd/1", "/proc/self/fd/1"})
_NPY_HEADER_LEN = 128  # magic + header, padded: room for any 64-bit row count


def _npy_header(rows: int, ncols: int) -> bytes:
    shape = f"({rows},)" if ncols == 0 else f"({rows}, {ncols})"
    d = f"{{'descr': '<f8', 'fortran_order': False, 'shape': {shape}, }}"
    pad = _NPY_HEADER_LEN - 10 - len(d) - 1
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", _NPY_HEADER_LEN - 10) + (
        d + " " * pad + "\n").encode("latin-1")


class _NpyWriter:
    """A float64 .npy written row block by row block; the row count is fixed at the end."""

    def __init__(self, fh: IO[bytes], ncols: int, what: str) -> None:
        if not fh.seekable():
            raise CalibrationError(
                f"{what}: a .npy output must be a regular file (its row count is written at "
                "the end); use a .csv output to write to a pipe")
        self.fh, self.ncols, self.rows = fh, ncols, 0
        self.start = fh.tell()
        fh.write(_npy_header(0, ncols))

    def write(self, block: np.ndarray) -> None:
        self.fh.write(np.ascontiguousarray(block, dtype="<f8").tobytes())
        self.rows += block.shape[0]

    def close(self) -> None:
        end = self.fh.tell()
        self.fh.seek(self.start)
        self.fh.write(_npy_header(self.rows, self.ncols))
        self.fh.seek(end)


class _Output:
    """Where calibrated rows go: .csv (text), .npy (t, ax, ay, az), .npz (samples, t),
    .h5/.hdf5 (datasets samples, t; needs h5py). Everything goes through a temporary file
    that replaces the output only when complete (an interrupted run leaves it untouched)."""

    KINDS = {".csv": "csv", ".txt": "csv", ".dat": "csv", ".tsv": "csv", "": "csv",
             ".npy": "npy", ".npz": "npz", ".h5": "h5", ".hdf5": "h5"}

    def __init__(self, path: str, has_t: bool, header: list[str]) -> None:
        self.path = path
        self.stdout = path in STDOUT_NAMES
        p = Path(path)
        suffix = p.suffix.lower()
        from ..io import COMPRESSED_SUFFIXES

        self.compress = COMPRESSED_SUFFIXES.get(suffix)  # after .csv / .txt
        if self.compress is not None:
            suffix = Path(p.stem).suffix.lower()
        kind = self.KINDS.get(suffix) if not self.stdout else "csv"
        if kind is None or (self.compress is not None and kind != "csv"):
            raise CalibrationError(
                f"{path}: unknown output format {p.suffix!r}: give .csv or .txt (text, also "
                ".csv.gz, .csv.bz2, .csv.xz), .npy, .npz or .h5, or - for standard output")
        self.kind = kind
        self.has_t = has_t
        self.header = header
        self.rows = 0
        self.stack = ExitStack()

    def __enter__(self) -> _Output:
        with ExitStack() as setup:
            setup.push(self.stack)
            self.stack.__enter__()
            if self.stdout:  # text on standard output (a pipe)
                self.fh = sys.stdout.buffer
            elif self.kind != "h5":  # HDF5 writes its temporary file by name (below)
                self.fh = self.stack.enter_context(atomic_open(self.path, "wb"))
            if self.compress is not None:
                from ..io import compression_open

                self.fh = self.stack.enter_context(compression_open(self.compress)(self.fh, "wb"))
            if self.kind == "csv":
                for h in self.header:
                    self.fh.write(f"# {h}\n".encode())
                self.fh.write(b"t_s,ax,ay,az\n" if self.has_t else b"ax,ay,az\n")
            elif self.kind == "npy":
                self.npy = [_NpyWriter(self.fh, 4 if self.has_t else 3, self.path)]
            elif self.kind == "npz":
                # One temporary .npy per array beside the output, zipped at the end: named,
                # locked and cleaned as the output's own temporary file (a run killed
                # outright leaves them to the next write of the output to remove).
                self.names = ["samples", "t"] if self.has_t else ["samples"]
                self.tmp_names: list[str] = []
                files = []
                for n in self.names:
                    fd, tmp = self.stack.enter_context(temp_beside(self.path, f".{n}.npy"))
                    files.append(self.stack.enter_context(os.fdopen(fd, "w+b")))
                    self.tmp_names.append(tmp)
                self.npy = [_NpyWriter(f, 3 if n == "samples" else 0, self.path)
                            for n, f in zip(self.names, files, strict=True)]
            else:
                try:
                    import h5py
                except ImportError:
                    raise CalibrationError(
                        f"{self.path}: writing HDF5 needs h5py: pip install 'accelcal[hdf5]'"
                    ) from None
                # By name, not through a Python file object: a write error (disk full) in
                # HDF5's file-object callbacks can crash the process.
                self.tmp = self.stack.enter_context(atomic_path(self.path, "an HDF5 output"))
                with self._h5_errors():
                    # HDF5's own file lock would clash with ours (held while it is written).
                    # No chunk cache: every write reaches the file at once, its error raised
                    # there (dirty chunks failing to flush on close crash h5py/HDF5 2.0).
                    self.h5 = self.stack.enter_context(
                        h5py.File(self.tmp, "w", locking=False, rdcc_nbytes=0))
                    self.h5.create_dataset("samples", shape=(0, 3), maxshape=(None, 3),
                                           dtype="f8", chunks=(65536, 3))
                    if self.has_t:
                        self.h5.create_dataset("t", shape=(0,), maxshape=(None,), dtype="f8",
                                               chunks=(65536,))
                    self.h5.attrs["units"] = "m/s^2"
                    for h in self.header:
                        k, _, v = h.partition(": ")
                        if v:
                            self.h5.attrs[k] = v
            setup.pop_all()
        return self

    def write(self, t: np.ndarray | None, a: np.ndarray) -> None:
        m = a.shape[0]
        if self.has_t and t is None:
            raise CalibrationError(f"{self.path}: a chunk came without its sample times")
        if self.kind == "csv":
            from .._core import format_rows

            self.fh.write(format_rows(a, t if self.has_t else None))
        elif self.kind == "npy":
            self.npy[0].write(a if t is None or not self.has_t else np.column_stack([t, a]))
        elif self.kind == "npz":
            self.npy[0].write(a)
            if self.has_t:
                self.npy[1].write(np.asarray(t))
        else:
            with self._h5_errors():
                ds = self.h5["samples"]
                ds.resize(self.rows + m, axis=0)
                ds[self.rows:] = a
                if self.has_t:
                    ts = self.h5["t"]
                    ts.resize(self.rows + m, axis=0)
                    ts[self.rows:] = t
        self.rows += m

    @contextmanager
    def _h5_errors(self) -> Iterator[None]:
        """Any error of h5py (disk full, file too large, ...) as one line naming the output,
        not the temporary file."""
        try:
            yield
        except (CalibrationError, KeyboardInterrupt, SystemExit, GeneratorExit):
            raise
        except Exception as e:  # noqa: BLE001 - h5py raises OSError, RuntimeError, ...
            tmp = getattr(self, "tmp", None)
            msg = (str(e).strip().splitlines() or [type(e).__name__])[0]
            # HDF5 buries the system's error in its own text ("file write failed: ...,
            # errno = 28, ..."): the system's words, which say what to do.
            found = re.search(r"\berrno = (\d+)", str(e))
            code = e.errno if isinstance(e, OSError) and e.errno else (
                int(found.group(1)) if found else None)
            if code:
                msg = f"[Errno {code}] {os.strerror(code)}"
            if tmp:
                msg = msg.replace(tmp, self.path).replace(os.path.basename(tmp), self.path)
            raise CalibrationError(f"cannot write the HDF5 output {self.path!r}: {msg}") from None

    def _finish(self) -> None:
        if self.kind == "npy":
            self.npy[0].close()
        elif self.kind == "npz":
            with zipfile.ZipFile(self.fh, "w", zipfile.ZIP_STORED, allowZip64=True) as z:
                for w in self.npy:
                    w.close()
                    w.fh.flush()
                for name, tmp in zip(self.names, self.tmp_names, strict=True):
                    z.write(tmp, arcname=f"{name}.npy")

    def __exit__(self, *exc: Any) -> bool | None:
        if exc[0] is None:
            try:
                self._finish()
            except BaseException:
                if not self._close(*sys.exc_info()):
                    raise
                return None
        return self._close(*exc)

    def _close(self, *exc: Any) -> bool | None:
        if self.kind != "h5":
            return self.stack.__exit__(*exc)
        try:
            return self.stack.__exit__(*exc)
        except BaseException as e:
            if e is exc[1]:
                raise
            with self._h5_errors():  # closing the file failed (disk full): said as such
                raise


@main.command()
@click.argument("cal", type=click.Path())
@click.argument("file", type=click.Path(allow_dash=True))
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True,
              help="Calibrated stream, in the units of the calibration's g (m/s^2 or g): "
                   ".csv (t_s, ax, ay, az; also .csv.gz, .csv.bz2, .csv.xz), .npy ((N, 4) t_s, "
                   "ax, ay, az), .npz (samples, t) or .h5 (samples, t; needs h5py); - writes "
                   "the text to standard output.")
@recording_options
@click.option("--chunk-rows", type=click.IntRange(min=1), default=500_000, show_default=True,
              help="Rows calibrated at a time (memory use is about 100 bytes per row).")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@friendly
def apply(cal: str, file: str, output: str, fs: float | None, columns: str | None,
          time_column: str | None, quiet: bool, chunk_rows: int, as_json: bool) -> None:
    """Apply a calibration file to a recording, streaming chunk by chunk."""
    from .._triad_model import median_norm
    from ..io import _progress_bar
    from ..static import TriadModel

    to_stdout = output in STDOUT_NAMES
    if to_stdout and as_json:
        raise CalibrationError(f"-o {output} writes the calibrated rows to standard output, "
                               "where --json would write too: give one of them")
    model, cal_sha256 = _load_model(cal)
    rec = open_recording(file, fs, columns, time_column)
    has_t = rec.lay.time is not None or rec.fs is not None or (
        rec.arrays is not None and rec.arrays.t is not None)
    assert isinstance(model, TriadModel)
    unit = model.units or "units of g"  # the calibrated output is in the units of its g
    from .._triad_model import accelcal_version

    # The calibration by its content too: a file replaced under the same name is told apart.
    header = [f"calibrated by accelcal from {cal}", f"calibration_sha256: {cal_sha256}",
              f"accelcal_version: {accelcal_version()}", f"source: {file}", f"units: {unit}"]
    if rec.lay.t0_text:
        header.append(f"t0: {rec.lay.t0_text}")
    if rec.fs is not None:
        header.append(f"fs_hz: {rec.fs!r}")
    with _Output(output, has_t, header) as out, \
            _progress_bar(rec, "apply", False if quiet else None) as cb:
        norms: list[float] = []
        for chunk, t, _temp in rec.chunks(chunk_rows, cb):
            cal_chunk = model.apply(chunk, check_units=False)  # norms checked below
            if len(norms) < 8 and len(cal_chunk):  # the calibrated norm, on the first chunks
                # of the finite rows: dropouts (NaN rows) pass through as NaN
                chunk_norm = median_norm(cal_chunk, finite=True)
                if not math.isnan(chunk_norm):
                    norms.append(chunk_norm)
            out.write(t, cal_chunk)
    if rec.rows == 0:
        raise CalibrationError(f"{rec.path}: no data rows")
    from ..io import NO_RATE_NOTE

    # Applying a calibration needs no rate: without one the output has no time column only.
    notes = [n for n in rec.notes() if not n.startswith(NO_RATE_NOTE)]
    untimed = "" if has_t else rec.untimed_note()
    if untimed:  # a column that looks like a clock: said, not dropped in silence
        notes.append(untimed)
    typical = float(np.median(norms)) if norms else math.nan
    if model.g and math.isfinite(typical) and not 0.5 < typical / model.g < 2.0:
        notes.append(f"the calibrated output's norm is typically {typical:.4g} {unit}, where "
                     f"gravity (g = {model.g:g}, the calibration's) would read {model.g:g}: is "
                     "this the sensor, and are these the units, the calibration was made for?")
    if as_json:
        emit_json({"output": output, "format": out.kind, "rows": out.rows, "time_column": has_t,
                   "units": unit, "calibration": cal, "file": file,
                   "notes": cli_notes(notes)})
        return
    echo_notes(notes)
    click.echo(f"wrote {out.rows} calibrated samples ({unit}{', with t_s' if has_t else ''}) "
               f"to {'standard output' if to_stdout else output}", err=to_stdout)


def _load_model(cal: str) -> tuple[Any, str]:
    """The calibration file and the SHA-256 of its bytes, or one clear line naming what is
    wrong with it. The bytes are read once, then hashed and parsed: a pipe (``<(cat
    cal.json)``) or a FIFO can be read only once."""
    from .._files import SMALL_FILE_LIMIT, file_kind
    from ..static import TriadModel

    src = repr(str(cal))
    try:
        st = os.stat(cal)
        if not (stat.S_ISREG(st.st_mode) or stat.S_ISFIFO(st.st_mode)):
            raise CalibrationError(f"calibration file {src} is {file_kind(st.st_mode)}, "
                                   "not a file")
        with open(cal, "rb") as fh:
            data = fh.read(SMALL_FILE_LIMIT + 1)
    except OSError as e:
        raise CalibrationError(f"cannot read model {src}: {e.strerror}") from None
    if len(data) > SMALL_FILE_LIMIT:
        raise CalibrationError(f"calibration file {src} holds more than the "
                               f"{SMALL_FILE_LIMIT >> 20} MB such a file can hold: is it the "
                               "right file?")
    digest = hashlib.sha256(data).hexdigest()
    try:
        d = json.loads(data.decode("utf-8-sig"))  # a BOM, as Notepad saves it
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CalibrationError(f"{src} is not JSON: {e}") from None
    try:
        return TriadModel.from_dict(d, src), digest
    except CalibrationError:
        raise
    except KeyError as e:
        raise CalibrationError(
            f"{cal}: not a complete calibration file: the field {e.args[0]!r} is missing"
        ) from None
    except (TypeError, ValueError, IndexError) as e:
        raise CalibrationError(f"{cal}: not a valid calibration file ({e})") from None
