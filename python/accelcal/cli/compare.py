"""``accelcal compare``: two calibration files of one sensor, tested for a change."""

from __future__ import annotations

import click

from ._common import cli_words, emit_json, friendly, main

#: The library's keywords in the comparison's messages, as the command line spells them.
_PHRASES = {
    "check_sensor=False": "--no-check-sensor",
    "covariance='realistic' (--covariance realistic)": "--covariance realistic",
}


@main.command()
@click.argument("old", type=click.Path(dir_okay=False))
@click.argument("new", type=click.Path(dir_okay=False))
@click.option("--covariance", type=click.Choice(["noise_model", "realistic"]),
              default="noise_model", show_default=True,
              help="Each file's covariance to use: the noise model's (the test's nominal size "
                   "when the noise model holds) or the realistic one (scaled by chi2/dof when "
                   "above 1: conservative; for files whose chi2/dof shows the noise model too "
                   "small).")
@click.option("--independent-g", "independent_g", is_flag=True,
              help="Take the reference-gravity errors of the two files as independent even "
                   "when both used the same g (by default a shared g's error drops out).")
@click.option("--no-check-sensor", "no_check_sensor", is_flag=True,
              help="Compare calibrations of different sensor ids, models or units.")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@friendly
def compare(old: str, new: str, covariance: str, independent_g: bool, no_check_sensor: bool,
            as_json: bool) -> None:
    """Compare two calibrations of one sensor (OLD, then NEW): the parameter changes, their
    std, a Wald chi2 test and the parameters that moved beyond 3 std."""
    from .._core import CalibrationError
    from ..static import TriadModel

    a, b = TriadModel.load(old), TriadModel.load(new)
    try:
        res = a.compare(b, shared_g=not independent_g, check_sensor=not no_check_sensor,
                        covariance=covariance)
    except CalibrationError as e:
        raise CalibrationError(cli_words(f"{old} and {new}: {e}", _PHRASES)) from None
    if as_json:
        emit_json({**res.to_dict(), "old_file": old, "new_file": new})
        return
    text = res.summary()
    click.echo(cli_words(text, _PHRASES))
