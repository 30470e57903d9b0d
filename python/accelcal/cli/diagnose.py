"""``diagnose``: the sim-to-real gap of a static session recording."""

from __future__ import annotations

import warnings
from typing import Any

import click

from .._core import CalibrationError
from ..dwell import TimeStepWarning
from ._common import (
    _need_plot,
    _resolve_g,
    _save_fig,
    bounds_option,
    cli_notes,
    cli_words,
    detector_options,
    dwell_notes,
    echo_notes,
    emit_json,
    friendly,
    gravity_options,
    main,
    means_option,
    recording_options,
    source_line,
    stream_dwells,
    without_faults,
    without_moving,
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
@click.option("--calibration", "calibration", type=click.Path(dir_okay=False), default=None,
              help="Check an existing calibration (a TriadModel JSON written by "
                   "'calibrate static -o') against this session instead of refitting it.")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None,
              help="The gap figure: residuals against time, temperature or pose (sphere map), "
                   "tilt, and the noise panel (Allan deviation and the noise models).")
@detector_options
@bounds_option
@means_option
@click.option("--no-check-g", "no_check_g", is_flag=True,
              help="Accept a reference gravity outside Earth's range (deliberate other units).")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@friendly
def diagnose(file: str, g: float | None, lat: float | None, height: float, fs: float | None,
             columns: str | None, time_column: str | None, quiet: bool, noise: str,
             preset: str, calibration: str | None, plot_path: str | None,
             window_s: float, k: float, min_dwell_s: float, trim_s: float, bounds: str | None,
             means: bool,
             count: int | None, no_check_g: bool, as_json: bool) -> None:
    """Sim-to-real gap diagnosis of a static session recording (or of a dwell table written
    by ``accelcal dwells -o``)."""
    from ..gap import diagnose as run_diagnose
    from ..gap import made_with_g
    from ..static import TriadModel, unit_label

    _need_plot(plot_path)
    fit = TriadModel.load(calibration) if calibration else None
    g_note = ""
    g0 = made_with_g(fit)
    if g is None and lat is None and g0 is not None:
        # The calibration file says the g it was made with: the check uses it (a new site's
        # g differs by up to 0.5 %: the report names such a common offset).
        unit = f"{fit.units} " if fit is not None and fit.units else ""
        g, g_note = g0, (f"g = {g0:.7g} {unit}from the calibration file (the g it was made "
                         "with); give --g if this site's differs")
    gv, _ = _resolve_g(g, lat, height, file, fs, columns, time_column)
    # One streaming pass: the dwell accumulator keeps what the diagnosis needs from inside
    # the dwells (means, variances and, where the accumulator provides them, within-dwell
    # noise statistics), so memory stays bounded whatever the recording's length.
    d, rec = stream_dwells(file, fs, columns, time_column, quiet, "diagnose", bounds, means,
                           count=count, window_s=window_s, k=k, min_dwell_s=min_dwell_s,
                           trim_s=trim_s)
    # A dwell table, or a table of dwell means: no samples to read again.
    tabled = rec is None or rec.pose_table
    if len(d) == 0:
        raise CalibrationError(f"{file}: no static dwells detected in the recording")
    # A g computed from --lat/--height is local gravity by construction (up to 50 km).
    kw: dict[str, Any] = {"fit": fit, "check_g": not no_check_g and g is not None}
    if noise == "white":
        kw["noise_model"] = "white"
    extra: list[str] = [g_note] if g_note else []
    no_allan = noise == "allan" and getattr(d, "inflation", None) is None
    if no_allan and (tabled or file == "-" or bounds):
        why = ("standard input cannot be read twice" if file == "-" else
               "a table of dwells or of pose means has none" if tabled else
               "the given dwells are read in one pass")
        extra.append(f"the Allan noise model needs the samples ({why}): white noise "
                     "(variance / count) used")
    run: tuple[Any, ...] = (d,)
    if no_allan and not tabled and file != "-" and not bounds:
        # A dwell table without the within-dwell Allan statistics: the Allan noise model
        # needs the samples themselves, so read them (whole file) and detect the dwells again.
        from ..dwell import detect_dwells
        from ..io import read_stream

        st = read_stream(file, columns=columns, fs=fs, time_column=time_column,
                         progress=False if quiet else None)
        if st.fs is None:
            raise CalibrationError(f"{file}: the sample rate is unknown; give --fs (Hz)")
        from ..dwell import DetectorSettings

        det = DetectorSettings(window_s=window_s, k=k, min_dwell_s=min_dwell_s, trim_s=trim_s)
        d = detect_dwells(st.samples, st.fs, t=st.t, temperature=st.temperature, settings=det,
                          check_times=False)  # the reader noted what the clock did
        run = (st.samples,)
        kw.update(fs=st.fs, t=st.t, temperature=st.temperature, detector=det)
    src = source_line(file, rec, d)
    if fit is not None and not fit.own_dwells(d.mean) and _same_file(
            fit.metadata.get("source"), file):
        extra.append(f"the calibration was made from this same recording ({calibration} names "
                     "it as its source), from other dwells: the check is not independent of "
                     "it; check it against another session")
    extra += dwell_notes(d, rec)
    d, fault_notes = without_faults(d)
    d, moving_notes = without_moving(d, gv)
    fault_notes += moving_notes
    if fault_notes:
        # The dwells that are left (the samples would bring the faulty ones back).
        extra += fault_notes
        run = (d,)
        for key in ("fs", "t", "temperature", "detector"):
            kw.pop(key, None)
    try:
        with warnings.catch_warnings():
            # The reader noted what the clock did; the dwell pass would say it again.
            warnings.simplefilter("ignore", TimeStepWarning)
            rep = run_diagnose(*run, g=gv, preset=preset, **kw)
    except CalibrationError as e:
        raise type(e)(cli_words(str(e), {"check_g=False": "--no-check-g",
                                         'model "diag"': "--model diag"})) from None
    notes = ([] if rec is None else rec.notes()) + extra
    if plot_path:
        if "tau" not in rep.noise_curves and not tabled and file != "-":
            rep = _with_allan_curve(rep, d, file, columns, fs, time_column)
        _save_fig(rep.plot(), plot_path)
    if as_json:
        out = rep.to_dict()
        out["notes"] = cli_notes(notes)
        emit_json(out)
        return
    echo_notes(notes)
    click.echo(f"{src}, g = {gv:.6f} {unit_label(gv)}")
    click.echo(rep.summary())
    if plot_path:
        click.echo(f"wrote {plot_path}")


def _with_allan_curve(rep: Any, d: Any, file: str, columns: str | None, fs: float | None,
                      time_column: str | None) -> Any:
    """The report with the noise panel's Allan curve (the longest dwell's samples, read
    again: the streaming pass kept the dwells' statistics, not their samples)."""
    from dataclasses import replace

    from ..gap import _noise_curves
    from ..io import read_stream

    if getattr(d, "start", None) is None or getattr(d, "stop", None) is None or len(d) == 0:
        return rep
    try:
        st = read_stream(file, columns=columns, fs=fs, time_column=time_column, progress=False)
    except (CalibrationError, OSError):
        return rep  # the figure without the curve, as before
    if st.fs is None or int(max(d.stop)) > len(st.samples):
        return rep
    curves = _noise_curves(st.samples, d, st.fs, None, None, None, None)
    if "tau" not in curves:
        return rep
    return replace(rep, noise_curves={**rep.noise_curves, "tau": curves["tau"],
                                      "adev": curves["adev"]})


def _same_file(source: Any, file: str) -> bool:
    """Whether a calibration's recorded source names ``file`` (standard input never does)."""
    import os

    if not isinstance(source, str) or file == "-" or source == "-":
        return False
    try:
        return os.path.samefile(source, file)
    except OSError:
        return False
