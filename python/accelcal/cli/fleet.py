"""Fleet calibration on the command line: ``calibrate static`` with several recordings (or
``--summary``/``--out``/``--scheduler``/``--manifest``), and ``fleet report``."""

from __future__ import annotations

import sys
import time
from typing import Any

import click

from .._core import CalibrationError
from ._common import F, _need_plot, _save_fig, cli_words, emit_json, friendly, main

#: The options ``calibrate static`` takes for a fleet run (all default to "not given").
FLEET_OPTIONS = ("summary", "out_dir", "scheduler", "workers", "manifest", "diagnose_gap")


def fleet_options(fn: F) -> F:
    """Options of ``calibrate static`` that turn it into a fleet run."""
    opts = [
        click.option("--summary", type=click.Path(dir_okay=False), default=None,
                     help="Fleet run: write the table of all recordings (Parquet, and CSV "
                          "beside it).", ),
        click.option("--out", "out_dir", type=click.Path(file_okay=False), default=None,
                     help="Fleet run: folder for one calibration file per sensor (and the "
                          "table, unless --summary says where)."),
        click.option("--scheduler", default=None,
                     help="Fleet run on a Dask cluster: scheduler address, e.g. "
                          "tcp://host:8786 (default: all local cores)."),
        click.option("--workers", type=click.IntRange(min=1), default=None,
                     help="Fleet run: local processes (default: all cores)."),
        click.option("--manifest", type=click.Path(dir_okay=False), default=None,
                     help="Fleet run: CSV/Parquet table with a path column and optional "
                          "sensor_id, g, lat, height, fs, columns, date."),
        click.option("--diagnose", "diagnose_gap", is_flag=True, default=False,
                     help="Fleet run: add the gap diagnosis verdict per recording."),
    ]
    for o in reversed(opts):
        fn = o(fn)
    return fn


def is_fleet_run(files: tuple[str, ...], fleet: dict[str, Any]) -> bool:
    """Several recordings, or any fleet option given."""
    return len(files) != 1 or any(fleet.get(k) for k in FLEET_OPTIONS)


def run_static_fleet(
    files: tuple[str, ...], *, g: float | None, lat: float | None, height: float,
    fs: float | None, columns: str | None, time_column: str | None, quiet: bool, model: str,
    method: str, window_s: float,
    k_thr: float, min_dwell_s: float, trim_s: float, sensor_id: str, output: str | None,
    dwells_out: str | None, plot_path: str | None, as_json: bool, summary: str | None,
    out_dir: str | None, scheduler: str | None, workers: int | None, manifest: str | None,
    diagnose_gap: bool, check_g: bool = True, nominal_path: str | None = None,
    means: bool = False, sigma_g: float | None = None, overwrite: bool = False,
) -> None:
    """``calibrate static`` over many recordings (see :func:`accelcal.calibrate_many`)."""
    from ..dwell import DetectorSettings
    from ..fleet import STATUSES, calibrate_many
    from .static import _command_line  # the command as parsed (`calibrate static` runs this)

    for flag, val in (("-o/--output", output), ("--dwells-out", dwells_out),
                      ("--plot", plot_path), ("--nominal", nominal_path)):
        if val:
            raise CalibrationError(
                f"{flag} takes one recording; for several use --out FOLDER (one calibration "
                "file per sensor) and --summary TABLE"
            )
    if sensor_id:
        raise CalibrationError(
            "--sensor-id names one recording; for several give sensor ids in a --manifest "
            "(the file stem is used otherwise)"
        )
    if manifest and files:
        raise CalibrationError("give the recordings either as FILE ... or in --manifest, not both")
    if not manifest and not files:
        raise CalibrationError("give the recordings (FILE ..., a glob such as 'rec/*.csv') "
                               "or --manifest")
    if manifest:
        import os

        from ..fleet import _is_manifest_file

        if not os.path.isfile(manifest):
            raise CalibrationError(f"--manifest: file not found: {manifest}")
        if not _is_manifest_file(manifest):
            raise CalibrationError(f"--manifest {manifest}: the table needs a 'path' column "
                                   "(one recording per row)")
    sources: Any = manifest if manifest else (files[0] if len(files) == 1 else list(files))
    if len(files) == 1 and not any(c in files[0] for c in "*?["):
        sources = [files[0]]  # one recording, not a manifest or a glob
    detector = DetectorSettings(window_s=window_s, k=k_thr, min_dwell_s=min_dwell_s,
                                trim_s=trim_s)
    t0 = time.perf_counter()
    try:
        df = calibrate_many(
            sources, g=g, lat=lat, height=height, fs=fs, columns=columns,
            time_column=time_column, model=model,
            method=method, detector=detector, diagnose=diagnose_gap, client=scheduler,
            workers=workers, out=out_dir, summary=summary, progress=False if quiet else None,
            check_g=check_g, means=means, sigma_g=sigma_g, overwrite=overwrite, _cli=True,
            _command=_command_line(),
        )
    except KeyboardInterrupt as e:  # say what was kept ("interrupted after 12 of 110 ...")
        if e.args:
            click.echo(f"accelcal: {e.args[0]}", err=True)
        raise
    dt = time.perf_counter() - t0
    from .static import _PHRASES  # the fit's own words ('model "diag"'), as one file's

    df["message"] = [cli_words(m, _PHRASES) for m in df["message"]]
    calibrated = int(df["status"].isin(["ok", "weak"]).sum())
    if as_json:
        # Full precision (DataFrame.to_json keeps 10 digits); missing values as null.
        emit_json(df.astype(object).where(df.notna(), None).to_dict(orient="records"))
        if not calibrated:
            sys.exit(1)
        return
    counts = {s: int((df["status"] == s).sum()) for s in STATUSES}
    where = f"the Dask cluster at {scheduler}" if scheduler else "local processes"
    # a recording listed again (overlapping globs, a link to it) is calibrated once; its row
    # names every entry
    n_dup = sum(len(v) for v in df.attrs.get("duplicates", {}).values())
    dup = (f" ({n_dup} duplicate entr{'y' if n_dup == 1 else 'ies'} skipped)" if n_dup
           else "")
    click.echo(f"calibrated {len(df)} recordings{dup} on {where} in {dt:.1f} s: "
               + ", ".join(f"{counts[s]} {s}" for s in STATUSES))
    if not summary and not out_dir:
        cols = ["sensor_id", "status", "n_dwells", "rms_mps2", "chi2_dof"]
        if diagnose_gap:
            cols += ["gap_best", "gap_structure", "gap_chi2_dof"]
        click.echo(df[cols].to_string(index=False, na_rep="-"))
    # every recording that failed or is weak, and every ok one with a note (dropouts, dwells
    # left out)
    bad = df[(df["status"] != "ok") | (df["message"] != "")]
    for r in bad.itertuples():
        click.echo(f"  {r.sensor_id} ({r.path}): {r.status}: {r.message}")
    if out_dir:
        n_kept = len(df.attrs.get("cal_files_kept", []))
        n_cal = int((df["cal_file"] != "").sum()) - n_kept
        kept = (f" ({n_kept} identical one{'' if n_kept == 1 else 's'} already there, left as "
                f"{'it was' if n_kept == 1 else 'they were'})" if n_kept else "")
        click.echo(f"wrote {n_cal} calibration files to {out_dir}{kept}")
    if summary or out_dir:
        from ..fleet import _summary_paths

        pq, csv = _summary_paths(summary or f"{out_dir}/fleet.parquet")
        click.echo(f"wrote {pq} and {csv}; see `accelcal fleet report {pq}`")
    if not calibrated:
        click.echo(f"accelcal: no recording was calibrated{_one_pose_each(df)}", err=True)
        sys.exit(1)


def _one_pose_each(df: Any) -> str:
    """For a fleet run in which no recording holds enough poses (each at most 3 dwells, or
    none found): the likely mistake, several files of one sensor, one pose in each."""
    n = df["n_dwells"].fillna(0)
    if len(df) < 2 or not bool((n <= 3).all() and (df["status"] == "degenerate").all()):
        return ""
    return (f"; {_dwells_each(df['sensor_id'], n)}: if they are poses of one sensor, one "
            "file per pose, join them into one recording (one clock), or write one row of "
            "means per pose into a table read with --means; several files are calibrated as "
            "several sensors")


def _dwells_each(ids: Any, n: Any) -> str:
    """How many dwells the recordings hold, exactly: ``each recording holds 1 dwell``, or
    the most common count with the exceptions named (``the recordings hold 1 dwell each,
    except right (none)``)."""
    counts = [int(x) for x in n]

    def held(k: int) -> str:
        return "none" if k == 0 else f"{k} dwell{'' if k == 1 else 's'}"

    common = max(sorted(set(counts)), key=counts.count)  # the fewer on a tie
    others = [(str(i), k) for i, k in zip(ids, counts, strict=True) if k != common]
    if not others:
        return "no recording holds a dwell" if common == 0 else (
            f"each recording holds {held(common)}")
    named = ", ".join(f"{i} ({held(k)})" for i, k in others[:4])
    more = f" and {len(others) - 4} more" if len(others) > 4 else ""
    each = "no dwell" if common == 0 else f"{held(common)} each"
    return f"the recordings hold {each}, except {named}{more}"


@main.group()
def fleet() -> None:
    """Fleet summaries of tables written by `calibrate static FILE ... --summary`."""


@fleet.command("report")
@click.argument("table", type=click.Path())
@click.option("--z", "z_limit", type=float, default=5.0, show_default=True,
              help="Outlier limit on the robust z (median and 1.4826 x MAD).")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None,
              help="Histogram per parameter with the outliers marked (PNG/PDF/SVG).")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@friendly
def report(table: str, z_limit: float, plot_path: str | None, as_json: bool) -> None:
    """Parameter distributions, outlier sensors and failed recordings of a fleet table."""
    import math

    from ..fleet import fleet_report

    _need_plot(plot_path)
    if not (math.isfinite(z_limit) and z_limit > 0):
        raise CalibrationError(f"--z must be a positive number; got {z_limit}")
    rep = fleet_report(table, z=z_limit)
    if plot_path:
        _save_fig(rep.plot(), plot_path)
    if as_json:
        emit_json(rep.to_dict())
        return
    click.echo(rep.summary())
    if plot_path:
        click.echo(f"wrote {plot_path}")
