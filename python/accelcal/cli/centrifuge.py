"""``calibrate centrifuge``: K2 calibration from a per-position table."""

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

#: Python keywords in messages of the fit and the option that sets each on the command line.
_PHRASES = {"pass check_units=False": "use --no-unit-check", "robust=False": "--no-screen"}
_NAMES = {
    "check_units=False": "--no-unit-check",
    "outlier_k": "--outlier-k",
    "max_draws": "--max-draws",
    "radius": "--radius",
    "sigma": "--sigma",
    "g": "--g",
}


def _cli(msg: str) -> str:
    """A message of the fit in the command line's terms (``outlier_k`` -> ``--outlier-k``)."""
    return cli_words(msg, _PHRASES, _NAMES)


@calibrate.command("centrifuge")
@click.argument("table", type=click.Path())
@click.option("--radius", type=float, required=True, help="Arm radius, m.")
@click.option("--g", "g", type=float, default=9.80665, show_default=True,
              help="Gravity used to express the centripetal acceleration in g, m/s^2.")
@click.option("--method", type=click.Choice(["nls", "taylor-paper"]), default="nls",
              show_default=True)
@click.option("--k3", is_flag=True, help="Also fit cubic (K3) coefficients.")
@click.option("--misalignment", is_flag=True, help="Also fit small-angle misalignment.")
@click.option("--sigma", type=float, default=None,
              help="Noise std of each mean output per axis, g (absolute uncertainties).")
@click.option("--no-screen", is_flag=True, help="Skip the robust screening of bad rows.")
@click.option("--outlier-k", type=float, default=5.0, show_default=True,
              help="Screening threshold as a normal tail, in standard deviations.")
@click.option("--no-unit-check", is_flag=True,
              help="Fit even when the outputs need scale factors outside 0.2..5 g/g.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Write the fit as JSON.")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None,
              help="Residuals against speed and position, excluded rows marked (PNG/PDF/SVG).")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@friendly
def calibrate_centrifuge(table: str, radius: float, g: float, method: str, k3: bool,
                         misalignment: bool, sigma: float | None, no_screen: bool,
                         outlier_k: float, no_unit_check: bool, output: str | None,
                         plot_path: str | None, as_json: bool) -> None:
    """Centrifuge calibration with K2 terms from a per-position table.

    Columns by name: the angular rate (omega_rad_s, omega, rpm, 'omega [deg/s]'), the mean
    outputs (N_ax_g ..., ax ..., in g unless the header says mg or m/s^2, converted with --g),
    and optionally speed_index and position. Rows are named by speed and position as well as
    by their 0-based index."""
    import warnings

    from ..centrifuge import (
        CentrifugeModelWarning,
        CentrifugeOutlierWarning,
        fit_centrifuge,
        read_centrifuge_table,
    )

    _need_plot(plot_path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t = read_centrifuge_table(table, g=g)  # its warnings (repeated rows) said as ours
        try:
            fit = fit_centrifuge(
                t.outputs, t.omega, radius, g=g, method=method,  # type: ignore[arg-type]
                k3=k3, misalignment=misalignment, sigma=sigma, robust=not no_screen,
                outlier_k=outlier_k, check_units=not no_unit_check, labels=t.labels(),
            )
        except CalibrationError as e:
            raise type(e)(_cli(str(e))) from None
    # The summary names the excluded rows, or the screen's model error, once; other warnings
    # (a misfit of the fit returned, a weak design) are printed as they come.
    said: tuple[type[Warning], ...] = (CentrifugeOutlierWarning,)
    if fit.screen_kept_all:
        said = (CentrifugeOutlierWarning, CentrifugeModelWarning)
    notes = [str(w.message) for w in caught if not issubclass(w.category, said)]
    if output:
        write_json_file(output, fit.to_dict())
    if plot_path:
        from ..plots import centrifuge_residual_figure

        _save_fig(centrifuge_residual_figure(fit, t.speed_index, t.position), plot_path)
    if as_json:
        out = fit.to_dict()
        out["warnings"] = notes + ([fit.excluded_text()] if len(fit.outliers) else [])
        out["rows"] = [{"index": k, "speed_index": int(s), "position": int(p),
                        "omega_rad_s": float(w)}
                       for k, (s, p, w) in enumerate(zip(t.speed_index, t.position, t.omega,
                                                         strict=True))]
        emit_json(out)
        return
    click.echo(fit.summary())
    for n in notes:
        click.echo(f"warning: {n}")
    if output:
        click.echo(f"wrote {output}")
    if plot_path:
        click.echo(f"wrote {plot_path}")
