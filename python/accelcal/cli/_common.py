"""Shared pieces of the command line: the command groups, error handling, options, output.

Every command prints a readable table by default and JSON with ``--json``; bad input gives
one line on stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import functools
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click
import numpy as np

from .._core import CalibrationError
from .._files import atomic_write

F = TypeVar("F", bound=Callable[..., Any])


def _fail(msg: str) -> None:
    click.echo(f"accelcal: error: {msg}", err=True)
    sys.exit(2)


def friendly(fn: F) -> F:
    """Turn user-facing failures into one clear line and exit status 2."""

    @functools.wraps(fn)
    def wrapper(*a: Any, **kw: Any) -> Any:
        try:
            return fn(*a, **kw)
        except CalibrationError as e:
            _fail(str(e))
        except BrokenPipeError:  # output piped into `head`: not an error
            sys.exit(0)
        except FileNotFoundError as e:
            _fail(f"file not found: {e.filename or e}")
        except (OSError, ValueError) as e:
            _fail(str(e))
        except Exception as e:  # an internal bug: still one line, the traceback on request
            if os.environ.get("ACCELCAL_DEBUG"):
                raise
            click.echo(
                f"accelcal: internal error: {type(e).__name__}: {e} "
                "(set ACCELCAL_DEBUG=1 for the traceback and please report it)",
                err=True,
            )
            sys.exit(3)

    return wrapper  # type: ignore[return-value]


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if np.isfinite(v) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def emit_json(obj: Any) -> None:
    click.echo(json.dumps(_jsonable(obj), indent=2))


def recording_options(fn: F) -> F:
    """``--fs`` and ``--columns``: how to read a recording."""
    fn = click.option("--columns", default=None,
                      help="Accelerometer columns, e.g. ax,ay,az or 1,2,3.")(fn)
    return click.option("--fs", type=float, default=None,
                        help="Sample rate, Hz (else from the file).")(fn)  # type: ignore[no-any-return]


def gravity_options(fn: F) -> F:
    """``--g`` or ``--lat``/``--height``: the reference gravity."""
    fn = click.option("--height", type=float, default=0.0, show_default=True, help="Height, m.")(fn)
    fn = click.option("--lat", type=float, default=None,
                      help="Latitude, deg (when --g is not known).")(fn)
    return click.option("--g", "g", type=float, default=None,
                        help="Reference gravity, m/s^2.")(fn)  # type: ignore[no-any-return]


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


def _load_stream(file: str, fs: float | None, columns: str | None) -> Any:
    from ..io import read_stream

    st = read_stream(file, columns=columns, fs=fs)
    if st.fs is None:
        raise CalibrationError(
            f"{file}: the sample rate is not in the file; give it with --fs (Hz)"
        )
    return st


def _resolve_g(g: float | None, lat: float | None, height: float) -> tuple[float, str]:
    from ..static import local_gravity

    if g is not None:
        return g, "given"
    if lat is not None:
        return local_gravity(lat, height), f"WGS84 normal gravity at {lat:g} deg, {height:g} m"
    raise CalibrationError("give the reference gravity with --g (m/s^2) or --lat/--height")


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="accelcal")
def main() -> None:
    """Calibrate accelerometers from the norm of what they measure."""


@main.group()
def calibrate() -> None:
    """Calibrate from a recording (static), a centrifuge table or a gradiometer table."""


def write_json_file(path: str | Path, obj: Any) -> None:
    atomic_write(path, json.dumps(_jsonable(obj), indent=2) + "\n")
