"""Commands on raw recordings: ``dwells`` (static intervals and their statistics) and
``apply`` (a calibration applied to a stream)."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from .._core import CalibrationError
from .._files import atomic_open
from ._common import _tqdm_disable, emit_json, friendly, main, recording_options


@main.command()
@click.argument("file", type=click.Path())
@recording_options
@click.option("--window", "window_s", type=float, default=1.0, show_default=True, help="s")
@click.option("--k", type=float, default=6.0, show_default=True, help="Threshold factor.")
@click.option("--min-dwell", "min_dwell_s", type=float, default=1.0, show_default=True, help="s")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Write the dwell table as CSV.")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
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
    quiet: bool,
) -> None:
    """Detect the static dwells of a recording and print their statistics."""
    from ..io import stream_dwells

    d = stream_dwells(file, fs=fs, columns=columns, window_s=window_s, k=k,
                      min_dwell_s=min_dwell_s, progress=False if quiet else None)
    if output:
        d.to_csv(output)
    if as_json:
        emit_json(d.to_dict())
        return
    click.echo(f"{file}: {len(d)} dwells at {d.fs:.6g} Hz")
    if d.noise_std is not None and d.threshold is not None:
        click.echo(
            "noise std per axis (from the data): "
            + " ".join(f"{v:.4g}" for v in d.noise_std)
            + f"; threshold = {k:g} x noise variance"
        )
    click.echo(d.table())
    if output:
        click.echo(f"wrote {output}")


@main.command()
@click.argument("cal", type=click.Path())
@click.argument("file", type=click.Path())
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True,
              help="Calibrated stream: .csv (t_s, ax, ay, az in m/s^2) or .npy.")
@recording_options
@click.option("--chunk-rows", type=int, default=500_000, show_default=True)
@click.option("--quiet", is_flag=True, help="No progress bar.")
@friendly
def apply(cal: str, file: str, output: str, fs: float | None, columns: str | None,
          chunk_rows: int, quiet: bool) -> None:
    """Apply a calibration file to a recording, streaming chunk by chunk."""
    from tqdm import tqdm

    from ..io import iter_stream
    from ..static import TriadModel

    model = TriadModel.load(cal)
    out = Path(output)
    if out.resolve() == Path(file).resolve():
        raise CalibrationError("the output would overwrite the input recording; choose -o")
    chunks = tqdm(iter_stream(file, chunk_rows=chunk_rows, columns=columns, fs=fs),
                  unit="chunk", desc="apply", disable=_tqdm_disable(quiet))
    n = 0
    if out.suffix == ".npy":
        parts = [model.apply(chunk) for chunk, _t in chunks]
        arr = np.concatenate(parts) if parts else np.empty((0, 3))
        n = len(arr)
        with atomic_open(out, "wb") as fh:
            np.save(fh, arr)
    else:
        with atomic_open(out, "w") as fh:
            fh.write(f"# calibrated by accelcal with {cal}; units m/s^2\n")
            fh.write("t_s,ax,ay,az\n")
            for chunk, t in chunks:
                a = model.apply(chunk)
                tt = t if t is not None else np.full(len(a), np.nan)
                np.savetxt(fh, np.column_stack([tt, a]), delimiter=",", fmt="%.10g")
                n += len(a)
    click.echo(f"wrote {n} calibrated samples to {output}")
