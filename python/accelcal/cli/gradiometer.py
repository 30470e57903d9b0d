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
    "sigma_theta must": "--sigma-theta must",
    "sigma_theta is the std": "--sigma-theta is the std",
    "sigma and sigma_theta": "--sigma and --sigma-theta",
    "a wrong sigma or sigma_theta": "a wrong --sigma or --sigma-theta",
    "drift=True": "--drift",
    "give sigma=": "give --sigma",
    "sigma must": "--sigma must",
    "sigma=": "--sigma",
    "dwell times t (s)": "dwell times (a t_s column, s)",
    "pass np.degrees(azimuth) as azimuth_deg, or check_units=False if they are degrees":
        "give the azimuths in degrees or say the column is in radians ('azimuth [rad]'), or "
        "use --no-unit-check if they are degrees",
    "multiply s^-2 by 1e9, or check_units=False if they are E":
        "say the unit in the header ('inline [1/s^2]', 'cross [1/s^2]'), or use "
        "--no-unit-check if they are E",
    "convert them, or check_units=False if they are E":
        "convert them to E (or say the unit in the header: '[mE]', '[1/s^2]'), or use "
        "--no-unit-check if they are E",
    "a wrong sigma": "a wrong --sigma",
    "(from sigma)": "(from --sigma)",
    "pass np.degrees(azimuth) as azimuth_deg":
        "give the azimuths in degrees or say the column is in radians ('azimuth [rad]')",
}


def _cli(msg: str) -> str:
    return cli_words(msg, _PHRASES)


@calibrate.command("gradiometer")
@click.argument("table", type=click.Path())
@click.option("--drift/--no-drift", default=None, help="Fit a linear bias drift (needs t_s).")
@click.option("--sigma", type=float, default=None, help="Noise std of one average, E.")
@click.option("--sigma-theta", "sigma_theta", type=float, default=0.0, show_default=True,
              help="Std of independent azimuth errors of the platform (its azimuth "
                   "repeatability), deg; its first-order effect at the fitted gradient is "
                   "added to the std.")
@click.option("--no-unit-check", is_flag=True,
              help="Fit azimuths as degrees even when they look like radians, and channels "
                   "as E even when their size says otherwise.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Write the result as JSON.")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None,
              help="Inline and cross channels against azimuth with the fit (PNG/PDF/SVG).")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@friendly
def calibrate_gradiometer(table: str, drift: bool | None, sigma: float | None,
                          sigma_theta: float, no_unit_check: bool, output: str | None,
                          plot_path: str | None, as_json: bool) -> None:
    """Gradiometer per-startup bias from azimuth_deg, inline_E, cross_E[, t_s] rows.

    Columns by name, with units in brackets: the azimuth (azimuth_deg, azimuth, az, heading;
    deg or rad), the inline and cross channels (E, mE or 1/s^2) and optionally the time (s,
    min or h). Azimuths in a column that does not say [rad] but that look like radians,
    and channels whose size says they are not E (every value below 1e-3: 1/s^2; any above
    1e7: counts) are refused (see accelcal.startup_bias; --no-unit-check fits them as
    given); with --sigma, residuals that exceed it are reported. --sigma-theta (deg) adds
    the platform's independent azimuth errors to the std."""
    import warnings

    from ..gradiometer import calibrate_gradiometer_table

    _need_plot(plot_path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            sb = calibrate_gradiometer_table(table, drift=drift, sigma=sigma,
                                             check_units=not no_unit_check,
                                             sigma_theta=sigma_theta)
        except CalibrationError as e:
            raise type(e)(_cli(str(e))) from None
    text = _cli(sb.summary())
    # The summary states the misfit note; other warnings (or more words) are printed as well.
    notes = [m for m in (_cli(str(w.message)) for w in caught) if m not in text]
    if output:
        write_json_file(output, sb.to_dict())
    if plot_path:
        from ..plots import gradiometer_figure

        _save_fig(gradiometer_figure(sb), plot_path)
    if as_json:
        out = sb.to_dict()
        out["warnings"] = [_cli(str(w.message)) for w in caught]
        emit_json(out)
        return
    click.echo(text)
    for n in notes:
        click.echo(f"warning: {n}")
    if output:
        click.echo(f"wrote {output}")
    if plot_path:
        click.echo(f"wrote {plot_path}")
