"""``calibrate gradiometer``: per-startup bias from an azimuth table."""

from __future__ import annotations

import click

from .._core import CalibrationError
from ._common import (
    _need_plot,
    _save_fig,
    calibrate,
    cli_words,
    emit_json,
    friendly,
    write_json_file,
)

#: Python keywords in messages of the estimator and the option that sets each.
_PHRASES = {
    "drift=True": "--drift",
    "give sigma=": "give --sigma",
    "sigma must": "--sigma must",
    "sigma=": "--sigma",
    "dwell times t (s)": "dwell times (a t_s column, s)",
}


def _cli(msg: str) -> str:
    return cli_words(msg, _PHRASES)


@calibrate.command("gradiometer")
@click.argument("table", type=click.Path())
@click.option("--drift/--no-drift", default=None, help="Fit a linear bias drift (needs t_s).")
@click.option("--sigma", type=float, default=None, help="Noise std of one average, E.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Write the result as JSON.")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None,
              help="Inline and cross channels against azimuth with the fit (PNG/PDF/SVG).")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@friendly
def calibrate_gradiometer(table: str, drift: bool | None, sigma: float | None,
                          output: str | None, plot_path: str | None, as_json: bool) -> None:
    """Gradiometer per-startup bias from azimuth_deg, inline_E, cross_E[, t_s] rows.

    Columns by name, with units in brackets: the azimuth (azimuth_deg, azimuth, az, heading;
    deg or rad), the inline and cross channels (E, mE or 1/s^2) and optionally the time (s,
    min or h)."""
    from ..gradiometer import calibrate_gradiometer_table

    _need_plot(plot_path)
    try:
        sb = calibrate_gradiometer_table(table, drift=drift, sigma=sigma)
    except CalibrationError as e:
        raise type(e)(_cli(str(e))) from None
    if output:
        write_json_file(output, sb.to_dict())
    if plot_path:
        from ..plots import gradiometer_figure

        _save_fig(gradiometer_figure(sb), plot_path)
    if as_json:
        emit_json(sb.to_dict())
        return
    click.echo(_cli(sb.summary()))
    if output:
        click.echo(f"wrote {output}")
    if plot_path:
        click.echo(f"wrote {plot_path}")
