"""``calibrate static`` (static field calibration of a recording) and ``plan`` (pose design)."""

from __future__ import annotations

import os
import re
import shlex
from typing import Any

import click
import numpy as np

from .._core import CalibrationError
from .._files import file_record
from ._common import (
    _need_plot,
    _resolve_g,
    _save_fig,
    bounds_option,
    calibrate,
    cli_notes,
    cli_words,
    count_of,
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
from .fleet import fleet_options, is_fleet_run, run_static_fleet

#: Python keywords in the static fit's messages, as the command line spells them.
_PHRASES = {
    "check_g=False": "--no-check-g",
    "sigma_g = ": "--sigma-g = ",
    'model "diag"': "--model diag",
    "model='diag'": "--model diag",
    'model="diag"': "--model diag",
    "max_tilt_deg": "--max-tilt",
    "check their attitudes (fit observability()), or give more iterations (max_iter=)":
        "check their attitudes (accelcal dwells FILE --plot shows them), and any dwell "
        "recorded while the sensor moved",
}


def _cli(msg: str) -> str:
    return cli_words(msg, _PHRASES)



#: What a calibration file records of an input file (absolute path, size, SHA-256).
_file_record = file_record


def _command_line() -> str:
    """The command line as parsed: ``accelcal calibrate static``, the arguments and the
    options given on it (long names, in the command's order; defaults left out)."""
    from click.core import ParameterSource

    ctx = click.get_current_context()
    words = ["accelcal", "calibrate", "static"]
    for p in ctx.command.params:
        name = p.name or ""
        if ctx.get_parameter_source(name) is not ParameterSource.COMMANDLINE:
            continue
        v = ctx.params.get(name)
        vals = list(v) if isinstance(v, (tuple, list)) else [v]
        if isinstance(p, click.Argument):
            words += [str(x) for x in vals]
            continue
        opt = max(p.opts, key=len)
        if getattr(p, "is_flag", False):
            if v:
                words.append(opt)
            elif p.secondary_opts:
                words.append(max(p.secondary_opts, key=len))
            continue
        for x in vals:
            words += [opt, str(x)]
    return " ".join(shlex.quote(w) for w in words)


def _unit_key(unit: str) -> str:
    """A unit's spelling compared: case and spaces aside, m/s2 as m/s^2."""
    u = unit.strip().lower().replace(" ", "").replace("²", "^2")
    return {"m/s2": "m/s^2", "mps2": "m/s^2", "ms2": "m/s^2", "ms^-2": "m/s^2"}.get(u, u)


def _input_units(given: str | None, rec: Any, d: Any) -> str | None:
    """The raw (input) unit the calibration records: ``--input-units``, else the unit the
    recording's three accelerometer columns declare alike (``ax [mg]``) or a dwell table's
    ``# units:`` line; None when none is known. A --input-units that disagrees with the file
    is refused, naming both."""
    from ..io import _names_of, declared_unit

    said, where = "", ""
    if rec is not None:
        said, where = declared_unit(_names_of(rec.lay)), "its accelerometer columns' names"
    table_units = str(getattr(d, "units", None) or "")
    if not said and table_units:
        said, where = table_units, "its units line"
    if given is None:
        return said or None
    if not given.strip():
        raise CalibrationError("--input-units must name a unit (counts, mg, g, m/s^2 ...)")
    if said and _unit_key(said) != _unit_key(given):
        names = f" ({', '.join(_names_of(rec.lay))})" if rec is not None and where.startswith(
            "its accelerometer") else ""
        raise CalibrationError(
            f"--input-units {given} disagrees with the file: {where}{names} say {said}. Give "
            "the unit the recording's values are in (or leave --input-units out to take the "
            "file's)")
    return said if said and _unit_key(said) == _unit_key(given) else given.strip()


def _diag_fits(d: Any, g: float) -> bool:
    """Whether the bias + scale model fits the dwells ``d`` (any design warning aside)."""
    from ..static import fit_quietly

    try:
        fit_quietly(d, g, model="diag")
    except CalibrationError:
        return False
    return True


def _shorter_rests(window_s: float, min_dwell_s: float, still: float) -> str:
    """For a session mostly in motion: how much was still, and the trade-off of a shorter
    window (pauses found, but also the slow ends of moves: a simulated session with 1.4 s
    pauses gives 16 "dwells" at a 0.2 s window, most of them partly in the moves, chi2/dof
    3750, where the 1 s window gives the 8 longest pauses exactly)."""
    text = (f" Only {100 * still:.0f} % of the recording was taken as still (dwells of at "
            f"least --min-dwell {min_dwell_s:g} s, window {window_s:g} s)")
    if max(window_s, min_dwell_s) > 0.25:
        return (f"{text}: if the sensor rested in shorter pauses, a shorter --window and "
                "--min-dwell find them, but also take the slow ends of moves; check the "
                "dwells plot and the fit's chi2/dof, or hold the sensor still for a few "
                "seconds in each pose.")
    return (f"{text}: the sensor moved most of the time; hold it still for a few seconds in "
            "each pose.")


@calibrate.command("static")
@click.argument("files", metavar="FILE...", nargs=-1, type=click.Path(allow_dash=True))
@gravity_options
@recording_options
@click.option("--model", type=click.Choice(["lower", "diag", "upper"]), default="lower",
              show_default=True, help="9-parameter triangle or 6-parameter bias + scale.")
@click.option("--method", type=click.Choice(["lm", "gauss-newton", "quadric", "linear-paper"]),
              default="lm", show_default=True, help="Fit method (lm = maximum likelihood).")
@detector_options
@bounds_option
@means_option
@click.option("--no-check-g", "no_check_g", is_flag=True,
              help="Accept a --g that is not a plausible local gravity (m/s^2, g or cm/s^2).")
@click.option("--sigma-g", "sigma_g", type=float, default=None,
              help="Std of the reference gravity, in the units of --g (e.g. 1e-5 m/s^2 from "
                   "an absolute gravimeter, about 1e-3 from --lat's formula): added to every "
                   "reported std.")
@click.option("--nominal", "nominal_path", type=click.Path(dir_okay=False), default=None,
              help="Calibration file of the nominal model, for the 'before' norm statistics.")
@click.option("--sensor-id", default="", help="Stored in the calibration file.")
@click.option("--input-units", "input_units", default=None, metavar="TEXT",
              help="The raw (input) units of the recording (counts, mg, g, m/s^2 ...), stored "
                   "in the calibration file (units.input). Default: the unit the three "
                   "accelerometer columns' names declare alike (ax [mg]), else none; one that "
                   "disagrees with it is refused.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Write the calibration (versioned JSON); an existing file is kept unless "
                   "--overwrite is given.")
@click.option("--overwrite", is_flag=True,
              help="Let -o replace an existing calibration file (written atomically); in a "
                   "fleet run, let the table (--summary, or fleet.parquet/.csv in --out) "
                   "replace a file beside it that is not a fleet table.")
@click.option("--date", "rec_date", default=None,
              help="Date of the recording, ISO 8601 (e.g. 2026-11-23T10:15:00Z; a date alone "
                   "is midnight UTC): the calibration's date, from which TriadModel.find(at=) "
                   "takes it as valid. Default: now.")
@click.option("--dwells-out", type=click.Path(dir_okay=False), default=None,
              help="Write the dwell table (CSV).")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None,
              help="Norm before/after and per-dwell residuals (PNG/PDF/SVG).")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@fleet_options
@friendly
def calibrate_static(
    files: tuple[str, ...], g: float | None, lat: float | None, height: float,
    fs: float | None, columns: str | None, time_column: str | None, quiet: bool, model: str,
    method: str, window_s: float, k: float, min_dwell_s: float, trim_s: float,
    bounds: str | None,
    means: bool, count: int | None, no_check_g: bool, sigma_g: float | None,
    nominal_path: str | None, sensor_id: str, input_units: str | None, output: str | None,
    overwrite: bool,
    rec_date: str | None, dwells_out: str | None, plot_path: str | None, as_json: bool,
    **fleet: Any,
) -> None:
    """Static field calibration: detect dwells, fit scale, bias and non-orthogonality.

    FILE is a recording (read in one streaming pass) or a dwell table written by
    ``accelcal dwells -o`` / ``--dwells-out``. Several recordings (or --summary, --out,
    --scheduler, --manifest) make a fleet run: one row per recording in a summary table, one
    calibration file per sensor, on all local cores or a Dask cluster; see `accelcal fleet
    report`. One FILE that is a table of recordings (a 'path' column) is taken as
    --manifest."""
    if len(files) == 1 and not fleet.get("manifest"):
        from ..fleet import _is_manifest_file

        if os.path.isfile(files[0]) and _is_manifest_file(files[0]):
            fleet = {**fleet, "manifest": files[0]}
            files = ()
    if is_fleet_run(files, fleet):
        if bounds:
            raise CalibrationError("--bounds takes one recording (its dwells are that "
                                   "recording's rows)")
        if count:
            raise CalibrationError("--count takes one table of dwell means, not a fleet run "
                                   "(give each table's count column, or --means alone)")
        if input_units is not None:
            raise CalibrationError("--input-units takes one recording, not a fleet run (each "
                                   "recording's calibration records the unit its columns' "
                                   "names declare)")
        if rec_date:
            raise CalibrationError("--date goes with -o, for one recording, not a fleet run")
        return run_static_fleet(
            files, g=g, lat=lat, height=height, fs=fs, columns=columns, means=means,
            time_column=time_column, quiet=quiet, model=model, method=method,
            window_s=window_s, k_thr=k, min_dwell_s=min_dwell_s, trim_s=trim_s, sensor_id=sensor_id,
            output=output, dwells_out=dwells_out, plot_path=plot_path, as_json=as_json,
            check_g=not no_check_g, nominal_path=nominal_path, sigma_g=sigma_g,
            overwrite=overwrite, **fleet)
    file = files[0]
    import warnings

    from .._core import DegenerateDataError
    from ..static import LAT_FORMULA_SIGMA_G, TriadModel, WeakDesignWarning, fit_static, unit_label

    _need_plot(plot_path)
    if output and os.path.lexists(output) and not overwrite:
        raise CalibrationError(f"-o {output}: the file exists (a calibration is never replaced "
                               "silently); give --overwrite to replace it, or choose another "
                               "path; nothing was written")
    from .._triad_model import _to_datetime, iso_utc

    try:
        cal_date = iso_utc(rec_date)
    except CalibrationError as e:
        raise CalibrationError(f"--date: {e}".replace("date must be", "it must be")) from None
    if rec_date is not None and _to_datetime(rec_date) > _to_datetime(None):
        raise CalibrationError(f"--date {rec_date} is in the future (the recording's date: "
                               "TriadModel.find would not take the calibration before it)")
    gv, g_src = _resolve_g(g, lat, height, file, fs, columns, time_column)
    sigma_g_src = "--sigma-g" if sigma_g is not None else "none given"
    if g is None and lat is not None:
        # The formula's error is the larger one: without it the std of the scale factors
        # understates it about 26 times (1e-4 relative against 4e-6..2e-5 from the noise).
        g_src = f"latitude formula: {g_src}"
        if sigma_g is None:
            sigma_g = LAT_FORMULA_SIGMA_G
            sigma_g_src = ("the latitude formula's typical error against a gravimeter "
                           "(local anomalies)")
    inputs = {"input": _file_record(file)} if output else {}
    for key, path in (("bounds", bounds), ("nominal", nominal_path)):
        if output and path:
            inputs[key] = _file_record(path)
    nominal = TriadModel.load(nominal_path) if nominal_path else None
    d, rec = stream_dwells(file, fs, columns, time_column, quiet, "calibrate", bounds, means,
                           count=count,
                           window_s=window_s, k=k, min_dwell_s=min_dwell_s, trim_s=trim_s)
    read_notes = [] if rec is None else rec.notes()
    if len(d) == 0:
        raise CalibrationError(
            f"{file}: no static dwells detected; check --fs, or loosen the detector with "
            "--k, --window and --min-dwell")
    if dwells_out:
        d.to_csv(dwells_out)
    src = source_line(file, rec, d)
    undropped = d
    read_notes += dwell_notes(d, rec)
    units_in = _input_units(input_units, rec, d)
    d, fault_notes = without_faults(d)
    read_notes += fault_notes
    d, moving_notes = without_moving(d, gv)
    read_notes += moving_notes
    notes: list[str] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            fit = fit_static(d, gv, model=model, method=method,
                             check_g=not no_check_g and g is not None,  # not from --lat
                             nominal=nominal, sigma_g=sigma_g, input_units=units_in)
        except DegenerateDataError as e:
            hint = ""
            if model != "diag" and "diag" not in str(e):
                # Offered only when it fits these dwells (it fails alike at one pose, or
                # when no pose turned an axis towards gravity).
                hint = (" Add attitudes: even --model diag (bias + scale) needs 6 dwells."
                        if len(d) < 6 else " Try --model diag (bias + scale: 6 parameters; "
                        "it fits these dwells) or add attitudes." if _diag_fits(d, gv)
                        else "")
            detected = rec is not None and not rec.pose_table and not bounds and rec.rows
            still = float(np.sum(undropped.count)) / rec.rows if detected else 1.0
            if still < 0.25 and getattr(undropped, "shorter", None) is None:
                # (With shorter settings that find more, dwell_notes names them below.)
                hint += _shorter_rests(window_s, min_dwell_s, still)
            from ..static import distinct_poses

            poses = distinct_poses(d.mean) if len(d) else 0
            if detected and poses <= 2 and still >= 0.25:
                held = (f"holds {count_of(len(d))} at " if len(d) > poses else "holds ")
                hint += (f" The recording {held}{'one pose' if poses == 1 else 'two poses'}: "
                         "if the other poses are in other files (one file per pose), join "
                         "them into one recording, or write one row of means per pose into a "
                         "table read with --means.")
            hint += "".join(f" Note: {n}." for n in dwell_notes(undropped, rec))
            raise CalibrationError(_cli(
                f"{count_of(len(d))} found in {file}, but they cannot determine the {model!r} "
                f"model: {e}.{hint}"
            )) from None
        except CalibrationError as e:
            raise CalibrationError(_cli(str(e))) from None
    for w in caught:
        # The summary already lists weakly determined parameters: say it once.
        if issubclass(w.category, WeakDesignWarning) and fit.weak and not fit.degenerate:
            continue
        notes.append(_cli(str(w.message)))
    if output:
        temp = None if d.temperature is None else float(np.mean(d.temperature))
        dwells_from = ("--bounds file" if bounds else "dwell table" if rec is None
                       else "table of dwell means" if rec.pose_table else "detected")
        meta: dict[str, Any] = {
            "source": str(file), "n_dwells": len(d), **inputs,
            "g_source": g_src, "sigma_g_source": sigma_g_src,
            "model": model, "method": method, "dwells_from": dwells_from,
            "detector": ({"window_s": window_s, "k": k, "min_dwell_s": min_dwell_s,
                          "trim_s": trim_s} if dwells_from == "detected" else None),
            "command": _command_line(), "written": iso_utc(None),
        }
        if dwells_from == "dwell table":  # what the table records of its own origin
            if getattr(d, "detector", None):
                meta["detector"] = d.detector
            if getattr(d, "source", None):
                meta["dwells_source"] = d.source
        cal_model = fit.to_model(sensor_id=sensor_id, temperature=temp, date=cal_date,
                                 metadata=meta)
        cal_model.to_json()  # checked before anything is written
    if plot_path:
        # Before the calibration: a plot that cannot be written leaves no calibration file
        # behind, which a rerun would then refuse to replace.
        from ..plots import static_norm_figure

        _save_fig(static_norm_figure(fit, d), plot_path)
    if output:
        try:
            # Never replaces a file that appeared since the check above (another run writing
            # the same -o at the same time): the file is linked to its name, which fails then.
            cal_model.save(output, overwrite=overwrite)
        except FileExistsError:
            raise CalibrationError(
                f"-o {output}: the file exists, written while this calibration ran (by "
                "another run?); it was kept (a calibration is never replaced silently): give "
                "--overwrite to replace it, or choose another path; the calibration was not "
                "written") from None
    if as_json:
        out = fit.to_dict()
        out.update(n_dwells=len(d), g_source=g_src, sigma_g=float(sigma_g or 0.0),
                   sigma_g_source=sigma_g_src, warnings=notes, file=str(file),
                   samples=None if rec is None else rec.rows, notes=cli_notes(read_notes))
        emit_json(out)
        return
    echo_notes(read_notes)
    click.echo(src)
    click.echo(f"reference gravity g = {gv:.6f} {unit_label(gv)} ({g_src})")
    if sigma_g_src.startswith("the latitude"):
        click.echo(f"sigma_g = {sigma_g:g} {unit_label(gv)}: {sigma_g_src}, added to every "
                   "std (give --sigma-g to change it; a gravimeter's value is better)")
    click.echo(_cli(fit.summary()))
    for n in notes:
        click.echo(f"warning: {n}")
    if output:
        stored = (f"std stored and printed: {fit.realistic.replace('_', ' ')}"
                  if np.all(np.isfinite(fit.std_realistic)) else
                  "no std stored: the fit has none (no redundancy, noise not given)")
        click.echo(f"wrote {output} ({stored})")
    if dwells_out:
        click.echo(f"wrote {dwells_out} (the dwell table: {len(undropped)} dwells, before any "
                   "was left out)")
    if plot_path:
        click.echo(f"wrote {plot_path}")


@main.command()
@click.option("--n", "n", type=int, required=True, help="Number of poses.")
@click.option("--max-tilt", type=float, default=30.0, show_default=True,
              help="Two-axis platform tilt limit, deg, in [1, 90]; 180 for the full sphere.")
@click.option("--sigma", type=float, default=1e-3, show_default=True,
              help="Noise std of one dwell mean, m/s^2.")
@click.option("--model", type=click.Choice(["lower", "diag", "upper"]), default="lower",
              show_default=True)
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None,
              help="The numbered poses on an equal-area projection of the sphere.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Write the poses as CSV (pose, platform tilts in deg, gravity direction in "
                   "the sensor frame, placement) for a tilt table or a checklist.")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@friendly
def plan(n: int, max_tilt: float, sigma: float, model: str, plot_path: str | None,
         output: str | None, as_json: bool) -> None:
    """Plan n poses (D-optimal): a numbered checklist and the accuracy they predict."""
    from ..design import plan_poses

    _need_plot(plot_path)
    if not (1 <= max_tilt <= 90 or max_tilt == 180):
        raise CalibrationError(
            f"--max-tilt must be in [1, 90] degrees, or 180 for the full sphere; got {max_tilt:g}"
        )
    mt = None if max_tilt == 180 else max_tilt
    try:
        p = plan_poses(n, mt, sigma=sigma, model=model)
    except CalibrationError as e:
        msg = re.sub(r"^n = (\d+) poses", r"--n \1: \1 poses", str(e))
        msg = re.sub(r"^n must", "--n must", msg).replace("sigma must", "--sigma must")
        msg = msg.replace(", output units)", ", m/s^2)")
        raise CalibrationError(_cli(msg)) from None
    if plot_path:
        from ..plots import poses_figure

        _save_fig(poses_figure(p), plot_path)
    if output:
        p.to_csv(output)
    if as_json:
        emit_json(_plan_dict(p, sigma, model))
        return
    click.echo(_plan_text(p, sigma, model))
    if plot_path:
        click.echo(f"wrote {plot_path}")
    if output:
        click.echo(f"wrote {output}")


def _plan_dict(p: Any, sigma: float, model: str) -> dict[str, Any]:
    pred = p.prediction
    return {
        "n": int(len(p.directions)),
        "model": model,
        "sigma_mps2": sigma,
        "tilts_deg": None if p.tilts_deg is None else p.tilts_deg,
        "directions": p.directions,
        "poses": p.pose_names(),
        "predicted_std": dict(zip(pred.names, pred.std, strict=True)),
        "singular": bool(pred.singular),
        "condition": pred.condition,
    }


def _plan_text(p: Any, sigma: float, model: str) -> str:
    pred = p.prediction
    lines = [f"{len(p.directions)} poses (D-optimal), model {model!r}, dwell-mean noise "
             f"{sigma:g} m/s^2; place the sensor in each pose, in order:"]
    lines.append(p.checklist())
    lines.append("predicted std (Cramer-Rao bound, 1 sigma; scale factors and misalignments "
                 "relative, biases in m/s^2):")
    lines.append(pred.table())
    if pred.singular:
        lines.append(f"SINGULAR design: {pred.combination}")
    return "\n".join(lines)
