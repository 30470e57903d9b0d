"""Shared pieces of the command line: the command groups, error handling, options, output.

Every command prints a readable table by default and JSON with ``--json``; bad input gives
one line on stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import functools
import json
import os
import re
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar

import click
import numpy as np

from .._core import CalibrationError
from .._files import atomic_write
from .._plain import plain

F = TypeVar("F", bound=Callable[..., Any])


#: Python keyword arguments named in library messages -> the command-line option that sets
#: them. `friendly` rewrites messages with it, so the command line speaks its own language.
CLI_WORDS: dict[str, str] = {
    "fs": "--fs",
    "count": "--count",
    "columns": "--columns",
    "time_column": "--time-column",
    "window_s": "--window",
    "min_dwell_s": "--min-dwell",
    "trim_s": "--trim",
    "k": "--k",
    "chunk_rows": "--chunk-rows",
    "g": "--g",
    "fit": "--calibration",
    "bounds": "--bounds",
}
#: Library phrases that are a flag on the command line.
CLI_PHRASES: dict[str, str] = {"means=True": "--means",
                               "time_column='none', fs=RATE": "--time-column none --fs RATE",
                               " (or give noise_std=)": ""}  # no such option


def cli_words(
    msg: str,
    phrases: Mapping[str, str] | None = None,
    names: Mapping[str, str] | None = None,
) -> str:
    """A library message in the terms of the command line: options, not Python keywords.

    ``phrases`` (a command's own, exact text -> CLI text) are replaced first, then ``names``
    (argument -> option) where a name stands for the argument (``outlier_k must ...``,
    ``radius (...)``, ``radius looks ...``), then the shared ``keyword=`` spellings of
    :data:`CLI_WORDS` (``give fs= (Hz)`` -> ``give --fs (Hz)``, ``columns=[...]``).
    """
    for py, cli in {**(phrases or {}), **CLI_PHRASES}.items():
        msg = msg.replace(py, cli)
    for kw, opt in (names or {}).items():
        msg = re.sub(rf"(^|\s){re.escape(kw)}(?= must| \(| looks| =)", rf"\g<1>{opt}", msg)

    def repl(m: re.Match[str]) -> str:
        opt = CLI_WORDS[m.group(1)]
        return opt + (" ..." if m.group(2) else "")

    keys = "|".join(sorted(map(re.escape, CLI_WORDS), key=len, reverse=True))
    msg = re.sub(rf"(?<![\w-])({keys})=(\[\.\.\.\])?(?![\w\d+-]|\.\w)", repl, msg)
    # A setting quoted with its value (``min_dwell_s = 1 s``, ``window_s = 0.5 s``): the
    # option with its value. (One-letter names other than k stay: ``g = 9.81`` may be a
    # statement about gravity, not the option.)
    long_keys = "|".join(sorted((re.escape(k) for k in CLI_WORDS if len(k) > 2 or k == "k"),
                                key=len, reverse=True))
    return re.sub(rf"(?<![\w-])({long_keys}) = (?=[-+\d.])",
                  lambda m: CLI_WORDS[m.group(1)] + " ", msg)


def _fail(msg: str) -> None:
    text = cli_words(msg)
    click.echo(f"accelcal: error: {text}", err=True)
    ctx = click.get_current_context(silent=True)
    if ctx is not None and ctx.params.get("as_json"):
        # A script that asked for JSON reads the refusal as JSON too (stdout), exit 2.
        click.echo(json.dumps({"error": text, "exit_code": 2}))
    sys.exit(2)


#: A command's parameters that name files it reads, with the words for them.
_READS = {"file": "the recording", "files": "the recording", "table": "the table",
          "cal": "the calibration file", "calibration": "the calibration file",
          "bounds": "the bounds file", "nominal_path": "the nominal calibration",
          "manifest": "the manifest"}
#: A command's parameters that name files it writes, with their options.
_WRITES = {"output": "-o", "dwells_out": "--dwells-out", "plot_path": "--plot",
           "summary": "--summary"}


def _same_path(a: str, b: str) -> bool:
    """Whether paths ``a`` and ``b`` name one file. ``-`` as both is standard input and
    output; otherwise ``-`` is a file of that name (``dwells ./- -o -`` writes one)."""
    if a == "-" and b == "-":
        return False
    try:
        return os.path.samefile(a, b)
    except OSError:  # one does not exist (yet): the same name is the same file
        return Path(a).resolve() == Path(b).resolve()


def check_outputs(params: Mapping[str, Any]) -> None:
    """Refuse, before anything is read or written, a command whose output file would replace
    one of its inputs or another of its outputs: nothing a user gave is ever overwritten."""
    outs = [(opt, str(params[k])) for k, opt in _WRITES.items() if params.get(k)]
    ins = [(words, str(v)) for k, words in _READS.items() if params.get(k)
           for v in (params[k] if isinstance(params[k], (tuple, list)) else [params[k]])]
    for i, (opt, path) in enumerate(outs):
        for words, src in ins:
            if _same_path(path, src):
                raise CalibrationError(f"{opt} {path} would overwrite {words} {src}; nothing "
                                       "was written: choose another path")
        for opt2, path2 in outs[:i]:
            if _same_path(path, path2):
                raise CalibrationError(f"{opt2} and {opt} name the same file ({path}); "
                                       "nothing was written: choose two paths")


def _memory_message(e: MemoryError, chunked: bool) -> str:
    """One line for running out of memory: what could not be had (numpy and the core name
    the size) and what to do."""
    what = (str(e).strip().splitlines() or [""])[0]
    if what and not what.lower().startswith("out of memory"):
        what = f"out of memory ({what})"
    what = what or "out of memory"
    hint = ("give a smaller --chunk-rows, or run with more memory free"
            if chunked else "run with more memory free (or on a shorter recording)")
    return f"{what}: {hint}"


def friendly(fn: F) -> F:
    """Turn user-facing failures into one clear line and exit status 2 (and refuse outputs
    that would overwrite an input: :func:`check_outputs`)."""

    @functools.wraps(fn)
    def wrapper(*a: Any, **kw: Any) -> Any:
        try:
            check_outputs(kw)
            return fn(*a, **kw)
        except CalibrationError as e:
            _fail(str(e))
        except BrokenPipeError:  # output piped into `head`: not an error
            sys.exit(0)
        except FileNotFoundError as e:
            _fail(f"file not found: {e.filename or e}")
        except (OSError, ValueError) as e:
            _fail(str(e))
        except MemoryError as e:  # a limit (ulimit -v, a container) or a very long input
            _fail(_memory_message(e, "chunk_rows" in kw))
        except (KeyboardInterrupt, SystemExit, GeneratorExit):
            raise
        except BaseException as e:  # noqa: BLE001 - the last resort (a Rust panic surfaces as
            # pyo3's PanicException, a BaseException): one line, the traceback on request.
            if os.environ.get("ACCELCAL_DEBUG"):
                raise
            first = (str(e).strip().splitlines() or [""])[0]
            if len(first) > 200:
                first = first[:197] + "..."
            click.echo(
                f"accelcal: internal error: {type(e).__name__}: {first} "
                "(set ACCELCAL_DEBUG=1 for the traceback and please report it)",
                err=True,
            )
            sys.exit(3)

    return wrapper  # type: ignore[return-value]


def emit_json(obj: Any) -> None:
    click.echo(json.dumps(plain(obj, strict=True), indent=2))


def recording_options(fn: F) -> F:
    """``--fs``, ``--columns``, ``--time-column`` and ``--quiet``: how to read a recording."""
    fn = click.option("--quiet", is_flag=True,
                      help="No progress bar (none is shown off a terminal either).")(fn)
    fn = click.option("--time-column", "time_column", default=None,
                      help="Time column (name or 0-based index; s, or ms/us/ns when the name "
                           "says so or when given as 'NAME [ms]'), else recognised by name; "
                           "'none': use no time column (then give --fs).")(fn)
    fn = click.option("--columns", default=None,
                      help="Accelerometer columns, e.g. ax,ay,az or 1,2,3 (0-based); a "
                           "fourth names the temperature column (1,2,3,12).")(fn)
    return click.option("--fs", type=float, default=None,
                        help="Sample rate, Hz (else from the file's metadata or time "
                             "column).")(fn)  # type: ignore[no-any-return]


def gravity_options(fn: F) -> F:
    """``--g`` or ``--lat``/``--height``: the reference gravity."""
    fn = click.option("--height", type=float, default=0.0, show_default=True, help="Height, m.")(fn)
    fn = click.option("--lat", type=float, default=None,
                      help="Latitude, deg (when --g is not known).")(fn)
    return click.option("--g", "g", type=float, default=None,
                        help="Reference gravity, in the units the calibrated output should "
                             "have: m/s^2 (9.78-9.83 at sea level), g (1) or cm/s^2.")(fn)  # type: ignore[no-any-return]


def _tqdm_disable(quiet: bool) -> bool | None:
    # tqdm: None disables the bar when stderr is not a terminal.
    return True if quiet else None


def _plot_available() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def _need_plot(path: str | None) -> None:
    if path and not _plot_available():
        raise CalibrationError("plots need matplotlib: pip install 'accelcal[plot]'")


def _save_fig(fig: Any, path: str) -> None:
    from ..plots import save_figure

    save_figure(fig, path)


def echo_notes(notes: list[str]) -> None:
    """What a person should know about how the recording was read (stderr, one line each)."""
    for n in cli_notes(notes):
        click.echo(f"note: {n}", err=True)


def cli_notes(notes: list[str]) -> list[str]:
    """The notes in the command line's words (``--count``, not ``count=``), for the text
    output and the JSON alike."""
    return [cli_words(n) for n in notes]


def open_recording(file: str, fs: float | None, columns: str | None,
                   time_column: str | None) -> Any:
    from ..io import open_recording as _open

    return _open(file, columns=columns, fs=fs, time_column=time_column)


#: Columns of a dwell table (``DwellSet.to_csv``) that a header row must hold to be read as
#: one without its first comment line (a table edited, or written by a script of its own).
_DWELL_TABLE_COLUMNS = {"mean_x", "mean_y", "mean_z", "var_x", "var_y", "var_z", "count"}


def is_dwell_table(file: str) -> bool:
    """True for a dwell table written by ``accelcal dwells -o`` (or ``--dwells-out``): its
    first line, or, without it, a comma-separated header row naming the means, variances and
    counts of the dwells (``mean_x ... var_x ... count``)."""
    if file == "-" or not os.path.isfile(file):  # a pipe must not be read here
        return False
    try:
        with open(file, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    if head.startswith(b"# accelcal dwell table"):
        return True
    for ln in head.decode("utf-8", "replace").splitlines():
        if ln.strip() and not ln.lstrip().startswith("#"):
            return _DWELL_TABLE_COLUMNS <= {c.strip() for c in ln.split(",")}
    return False


def stream_dwells(file: str, fs: float | None, columns: str | None, time_column: str | None,
                  quiet: bool, desc: str, bounds: str | None = None, means: bool = False,
                  count: int | None = None, **detector: Any) -> tuple[Any, Any]:
    """Detect the dwells of a recording in one streaming pass (bounded memory, progress bar),
    or take them from a ``--bounds`` file; or read a table of dwell means (``--means``, or
    a file of unknown rate whose rows look like poses, with a note).

    Returns the DwellSet and the opened recording (rows read, notes), or, for a dwell table
    written by ``accelcal dwells -o``, the table and None.
    """
    if is_dwell_table(file):
        if bounds or count:  # --means says what it is
            opt = "bounds" if bounds else "count"
            raise CalibrationError(f"--{opt}: {file} is a dwell table already")
        from ..dwell import DwellSet

        return DwellSet.from_csv(file), None
    from ..io import _stream_dwells

    d, rec = _stream_dwells(file, fs=fs, columns=columns, time_column=time_column,
                            bounds=bounds, progress=False if quiet else None, desc=desc,
                            means=True if means else None, count=count,
                            **({} if bounds else detector))
    return d, rec


def detector_options(fn: F) -> F:
    """``--window``, ``--k``, ``--min-dwell`` and ``--trim``: the dwell detector's settings."""
    fn = click.option("--trim", "trim_s", type=float, default=0.1, show_default=True,
                      help="Settling cut from each end of a rest, s (a rest must last "
                           "--window + --min-dwell + 2 x --trim to be found).")(fn)
    fn = click.option("--min-dwell", "min_dwell_s", type=float, default=1.0, show_default=True,
                      help="Shortest dwell kept, s.")(fn)
    fn = click.option("--k", "k", type=float, default=6.0, show_default=True,
                      help="Dwell detector threshold factor (x noise variance).")(fn)
    return click.option(  # type: ignore[no-any-return]
        "--window", "window_s", type=float, default=1.0, show_default=True,
        help="Dwell detector window, s (at least 8 samples).")(fn)


def means_option(fn: F) -> F:
    """``--means``: the file is a table of dwell means (one pose per row); ``--count N``: the
    samples behind each of its means, for per-pose std columns without a count column."""
    fn = click.option(
        "--count", "count", type=click.IntRange(min=1), default=None,
        help="Samples averaged into each pose's mean, for a table of dwell means with "
             "per-pose std columns (x_std...) but no count column: each mean's noise is then "
             "std / sqrt(N).")(fn)
    return click.option(  # type: ignore[no-any-return]
        "--means", "means", is_flag=True,
        help="FILE is a table of dwell means, one pose per row (per-pose x_std... and n "
             "columns give their noise). A file of unknown rate of at most 2000 rows whose "
             "consecutive rows are typically 30 deg or more apart is read so without it, "
             "with a note; closer poses (a sensor turned slowly) need --means.")(fn)


def bounds_option(fn: F) -> F:
    """``--bounds FILE``: known dwells instead of detection."""
    return click.option(  # type: ignore[no-any-return]
        "--bounds", "bounds", type=click.Path(dir_okay=False), default=None,
        help="Known dwells instead of detection: a JSON or CSV file of [start, stop) rows "
             "(or start_s, stop_s in seconds from the first sample); imucal's session list "
             "works as it is (its rotation sections are left out).")(fn)


def without_faults(d: Any) -> tuple[Any, list[str]]:
    """The dwells whose output followed the sensor, and a note naming those left out
    (saturated, stuck or frozen axes: ``DwellSet.faults``)."""
    from ..dwell import fault_text

    faults = d.faults()
    if not faults:
        return d, []
    k = len({f.dwell for f in faults})
    kept = d.drop_faults(faults)
    return kept, [f"{k} of {len(d)} dwells left out, {len(kept)} used: their output did not "
                  f"follow the sensor, so their means are not the pose's:\n  "
                  f"{fault_text(d, faults)}"]


def without_moving(d: Any, g: float) -> tuple[Any, list[str]]:
    """The dwells that can be at rest, and a note naming those left out
    (:func:`~accelcal.static.off_norm_dwells`)."""
    from ..static import without_off_norm

    kept, off = without_off_norm(d, g)
    if off is None:
        return d, []
    return kept, [f"{off.text(g)}: left out, {len(kept)} used"]


def dwell_notes(d: Any, rec: Any = None) -> list[str]:
    """What the dwells ``d`` show about the recording, in the terms of the command line:
    shorter detector settings that find more dwells (:func:`~accelcal.dwell.shorter_text`),
    vibrating stretches (:func:`~accelcal.dwell.vibrating_text`), dwells too unsteady to be
    rests, and (with the recording ``rec``) a unit its column names declare that the dwells'
    norms contradict."""
    from ..dwell import shorter_text, unsteady_text, vibrating_text
    from ..io import _names_of, declared_units_note

    out = [cli_words(n) for n in shorter_text(d)]
    out += vibrating_text(d, option="--k ") + unsteady_text(d)
    if rec is not None and len(d):
        unit = declared_units_note(_names_of(rec.lay), float(np.median(
            np.linalg.norm(np.asarray(d.mean, dtype=np.float64), axis=1))))
        out += [unit] if unit else []
    return out


def count_of(n: int, noun: str = "dwell") -> str:
    """``1 dwell``, ``2 dwells``."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def source_line(file: str, rec: Any, d: Any) -> str:
    """``FILE: N samples at F Hz -> k dwells`` (or the dwell table's size)."""
    if rec is None:
        fs = "" if d.fs is None else f" (recorded at {d.fs:.6g} Hz)"
        return f"{file}: dwell table with {count_of(len(d))}{fs}"
    if rec.pose_table:
        return f"{file}: table of dwell means, {len(d)} poses"
    rate = "rate unknown" if rec.fs is None else f"at {rec.fs:.6g} Hz"
    line = f"{file}: {rec.rows} samples {rate} -> {count_of(len(d))}"
    if getattr(d, "dropped", 0):
        line += (f" ({d.dropped} rows with NaN or inf samples: dropouts, left out of the "
                 "dwell statistics)")
    return line


def _resolve_g(g: float | None, lat: float | None, height: float,
               file: str | None = None, fs: float | None = None, columns: str | None = None,
               time_column: str | None = None) -> tuple[float, str]:
    """The reference gravity and where it came from. Without one, a recording ``file`` is
    opened first, so that a problem with reading it is reported in the same run."""
    from ..static import local_gravity

    if g is not None:
        return g, "given"
    if lat is not None:
        return local_gravity(lat, height), f"WGS84 normal gravity at {lat:g} deg, {height:g} m"
    if file is not None and file != "-" and not is_dwell_table(file):
        open_recording(file, fs, columns, time_column)
    raise CalibrationError("give the reference gravity with --g (local gravity in m/s^2, e.g. "
                           "9.81; 1 for an output in g) or --lat/--height (WGS84 normal "
                           "gravity)")


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="accelcal")
def main() -> None:
    """Calibrate accelerometers from the norm of what they measure.

    Recordings: delimited text (with or without a header; also gzip, bzip2 or xz), .npy,
    .npz, HDF5, MATLAB .mat, spreadsheets (.xlsx), Parquet and Feather tables, LabVIEW
    TDMS, miniSEED and ROS bags;
    columns are found by name or given with --columns.
    """


class _SystemGroup(click.Group):
    """``calibrate``: a recording given where the system belongs gets the command to run."""

    def resolve_command(self, ctx: click.Context, args: list[str]) -> Any:
        name = args[0] if args else ""
        if name and self.get_command(ctx, name) is None and (
                os.path.exists(name) or name == "-" or os.sep in name or "." in name):
            systems = ", ".join(f"{c} {'FILE' if c == 'static' else 'TABLE'}"
                                for c in self.list_commands(ctx))
            ctx.fail(f"{name!r} is a recording, not a system: name the system first, "
                     f"`accelcal calibrate static {' '.join(args)}` for static dwells "
                     f"(the systems: {systems})")
        return super().resolve_command(ctx, args)


@main.group(cls=_SystemGroup)
def calibrate() -> None:
    """Calibrate from a recording (static), a centrifuge table or a gradiometer table."""


def write_json_file(path: str | Path, obj: Any) -> None:
    atomic_write(path, json.dumps(plain(obj, strict=True), indent=2) + "\n")
