"""``diagnose``: the sim-to-real gap of a static session recording."""

from __future__ import annotations

from typing import Any

import click

from .._core import CalibrationError
from ._common import (
    _need_plot,
    _resolve_g,
    _save_fig,
    echo_notes,
    emit_json,
    friendly,
    gravity_options,
    main,
    recording_options,
    source_line,
    stream_dwells,
)


@main.command()
@click.argument("file", type=click.Path(allow_dash=True))
@gravity_options
@recording_options
@click.option("--noise", type=click.Choice(["allan", "white"]), default="allan",
              show_default=True,
              help="Dwell-mean noise: Allan deviation of the within-dwell samples, or "
                   "white noise (variance / count).")
@click.option("--preset", type=click.Choice(["targeted", "conservative"]), default="targeted",
              show_default=True, help="Attribution settings (conservative: noise model in doubt).")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None,
              help="Residuals against time, temperature and pose, before and after.")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@friendly
def diagnose(file: str, g: float | None, lat: float | None, height: float, fs: float | None,
             columns: str | None, time_column: str | None, quiet: bool, noise: str,
             preset: str, plot_path: str | None, as_json: bool) -> None:
    """Sim-to-real gap diagnosis of a static session recording (or of a dwell table written
    by ``accelcal dwells -o``)."""
    from ..gap import diagnose as run_diagnose

    _need_plot(plot_path)
    gv, _ = _resolve_g(g, lat, height)
    # One streaming pass: the dwell accumulator keeps what the diagnosis needs from inside
    # the dwells (means, variances and, where the accumulator provides them, within-dwell
    # noise statistics), so memory stays bounded whatever the recording's length.
    d, rec = stream_dwells(file, fs, columns, time_column, quiet, "diagnose")
    if len(d) == 0:
        raise CalibrationError(f"{file}: no static dwells detected in the recording")
    kw: dict[str, Any] = {}
    if noise == "white" and d.var is not None and d.count is not None:
        kw["noise"] = d.sem
    extra: list[str] = []
    no_allan = noise == "allan" and getattr(d, "inflation", None) is None
    if no_allan and (rec is None or file == "-"):
        extra.append("the Allan noise model needs the samples (not in a dwell table, and "
                     "standard input cannot be read twice): white noise (variance / count) used")
    if no_allan and rec is not None and file != "-":
        # This build's dwell accumulator does not give the within-dwell Allan statistics:
        # the Allan noise model needs the samples themselves, so read them (whole file).
        from ..io import read_stream

        st = read_stream(file, columns=columns, fs=fs, time_column=time_column,
                         progress=False if quiet else None)
        rep = run_diagnose(st.samples, g=gv, fs=st.fs, t=st.t, temperature=st.temperature,
                           preset=preset)
    else:
        rep = run_diagnose(d, g=gv, preset=preset, **kw)
    notes = ([] if rec is None else rec.notes()) + extra
    if plot_path:
        _save_fig(rep.plot(), plot_path)
    if as_json:
        out = rep.to_dict()
        out["notes"] = notes
        emit_json(out)
        return
    echo_notes(notes)
    click.echo(f"{source_line(file, rec, d)}, g = {gv:.6f} m/s^2")
    click.echo(rep.summary())
    if plot_path:
        click.echo(f"wrote {plot_path}")
