"""The ``accelcal`` command line.

Every command prints a readable table by default and JSON with ``--json``; bad input gives
one line on stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import functools
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click
import numpy as np

from ._core import CalibrationError
from ._files import atomic_write

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
        except FileNotFoundError as e:
            _fail(f"file not found: {e.filename or e}")
        except (OSError, ValueError) as e:
            _fail(str(e))

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


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="accelcal")
def main() -> None:
    """Calibrate accelerometers from the norm of what they measure."""


@main.command()
@click.option("--quick", is_flag=True, help="Shorter simulated session (for a fast look).")
@click.option("--out", type=click.Path(file_okay=False), default=None, help="Folder for figures.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@friendly
def demo(quick: bool, out: str | None, seed: int) -> None:
    """Run the main job on built-in simulated data and print what it finds."""
    from .demo import run_demo

    click.echo(run_demo(quick=quick, out=out, seed=seed))


@main.command()
@click.argument("file", type=click.Path())
@click.option("--fs", type=float, default=None, help="Sample rate, Hz (else from the file).")
@click.option("--columns", default=None, help="Accelerometer columns, e.g. ax,ay,az or 1,2,3.")
@click.option("--window", "window_s", type=float, default=1.0, show_default=True, help="s")
@click.option("--k", type=float, default=6.0, show_default=True, help="Threshold factor.")
@click.option("--min-dwell", "min_dwell_s", type=float, default=1.0, show_default=True, help="s")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Write the dwell table as CSV.")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@friendly
def dwells(
    file: str,
    fs: float | None,
    columns: str | None,
    window_s: float,
    k: float,
    min_dwell_s: float,
    output: str | None,
    as_json: bool,
) -> None:
    """Detect the static dwells of a recording and print their statistics."""
    from .io import stream_dwells

    d = stream_dwells(file, fs=fs, columns=columns, window_s=window_s, k=k,
                      min_dwell_s=min_dwell_s)
    if output:
        d.to_csv(output)
    if as_json:
        emit_json(d.to_dict())
        return
    click.echo(f"{file}: {len(d)} dwells at {d.fs} Hz")
    if d.noise_std is not None and d.threshold is not None:
        click.echo(
            "noise std per axis (from the data): "
            + " ".join(f"{v:.4g}" for v in d.noise_std)
            + f"; threshold = {k:g} x noise variance"
        )
    click.echo(d.table())
    if output:
        click.echo(f"wrote {output}")


def write_json_file(path: str | Path, obj: Any) -> None:
    atomic_write(path, json.dumps(_jsonable(obj), indent=2) + "\n")


if __name__ == "__main__":  # pragma: no cover
    main()
