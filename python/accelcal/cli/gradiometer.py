"""``calibrate gradiometer``: per-startup bias from an azimuth table."""

from __future__ import annotations

import click

from ._common import calibrate, emit_json, friendly, write_json_file


@calibrate.command("gradiometer")
@click.argument("table", type=click.Path())
@click.option("--drift/--no-drift", default=None, help="Fit a linear bias drift (needs t_s).")
@click.option("--sigma", type=float, default=None, help="Noise std of one average, E.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Write the result as JSON.")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@friendly
def calibrate_gradiometer(table: str, drift: bool | None, sigma: float | None,
                          output: str | None, as_json: bool) -> None:
    """Gradiometer per-startup bias from azimuth_deg, inline_E, cross_E[, t_s] rows."""
    from ..gradiometer import calibrate_gradiometer_table

    sb = calibrate_gradiometer_table(table, drift=drift, sigma=sigma)
    if output:
        write_json_file(output, sb.to_dict())
    if as_json:
        emit_json(sb.to_dict())
        return
    click.echo(sb.summary())
    if output:
        click.echo(f"wrote {output}")
