"""``calibrate centrifuge``: K2 calibration from a per-position table."""

from __future__ import annotations

import click

from ._common import calibrate, emit_json, friendly, write_json_file


@calibrate.command("centrifuge")
@click.argument("table", type=click.Path())
@click.option("--radius", type=float, required=True, help="Arm radius, m.")
@click.option("--g", "g", type=float, default=9.80665, show_default=True, help="m/s^2")
@click.option("--method", type=click.Choice(["nls", "taylor-paper"]), default="nls",
              show_default=True)
@click.option("--k3", is_flag=True, help="Also fit cubic (K3) coefficients.")
@click.option("--misalignment", is_flag=True, help="Also fit small-angle misalignment.")
@click.option("--no-screen", is_flag=True, help="Skip the robust screening of bad rows.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Write the fit as JSON.")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@friendly
def calibrate_centrifuge(table: str, radius: float, g: float, method: str, k3: bool,
                         misalignment: bool, no_screen: bool, output: str | None,
                         as_json: bool) -> None:
    """Centrifuge calibration with K2 terms from a per-position table (outputs in g)."""
    import warnings

    from ..centrifuge import calibrate_centrifuge_table

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fit = calibrate_centrifuge_table(table, radius, g=g, method=method, k3=k3,
                                         misalignment=misalignment, robust=not no_screen)
    notes = [str(w.message) for w in caught]
    if output:
        write_json_file(output, fit.to_dict())
    if as_json:
        out = fit.to_dict()
        out["warnings"] = notes
        emit_json(out)
        return
    click.echo(fit.summary())
    for n in notes:
        click.echo(f"warning: {n}")
    if output:
        click.echo(f"wrote {output}")
