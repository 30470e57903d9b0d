"""The ``accelcal`` command line.

Every command prints a readable table by default and JSON with ``--json``; bad input gives
one line on stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import functools
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click
import numpy as np

from ._core import CalibrationError
from ._files import atomic_open, atomic_write

F = TypeVar("F", bound=Callable[..., Any])


def _fail(msg: str) -> None:
    click.echo(f"accelcal: error: {msg}", err=True)
    sys.exit(2)


def friendly(fn: F) -> F:
    """Turn user-facing failures into one clear line and exit status 2."""

    @functools.wraps(fn)
    def wrapper(*a: Any, **kw: Any) -> Any:
        try:
            return fn(*a, **kw)
        except CalibrationError as e:
            _fail(str(e))
        except BrokenPipeError:  # output piped into `head`: not an error
            sys.exit(0)
        except FileNotFoundError as e:
            _fail(f"file not found: {e.filename or e}")
        except (OSError, ValueError) as e:
            _fail(str(e))
        except Exception as e:  # an internal bug: still one line, the traceback on request
            if os.environ.get("ACCELCAL_DEBUG"):
                raise
            click.echo(
                f"accelcal: internal error: {type(e).__name__}: {e} "
                "(set ACCELCAL_DEBUG=1 for the traceback and please report it)",
                err=True,
            )
            sys.exit(3)

    return wrapper  # type: ignore[return-value]


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if np.isfinite(v) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def emit_json(obj: Any) -> None:
    click.echo(json.dumps(_jsonable(obj), indent=2))


def recording_options(fn: F) -> F:
    """``--fs`` and ``--columns``: how to read a recording."""
    fn = click.option("--columns", default=None,
                      help="Accelerometer columns, e.g. ax,ay,az or 1,2,3.")(fn)
    return click.option("--fs", type=float, default=None,
                        help="Sample rate, Hz (else from the file).")(fn)  # type: ignore[no-any-return]


def gravity_options(fn: F) -> F:
    """``--g`` or ``--lat``/``--height``: the reference gravity."""
    fn = click.option("--height", type=float, default=0.0, show_default=True, help="Height, m.")(fn)
    fn = click.option("--lat", type=float, default=None,
                      help="Latitude, deg (when --g is not known).")(fn)
    return click.option("--g", "g", type=float, default=None,
                        help="Reference gravity, m/s^2.")(fn)  # type: ignore[no-any-return]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="accelcal")
def main() -> None:
    """Calibrate accelerometers from the norm of what they measure."""


@main.command()
@click.option("--quick", is_flag=True, help="Shorter simulated session (for a fast look).")
@click.option("--out", type=click.Path(file_okay=False), default="accelcal-demo", show_default=True,
              help="Folder for the figures.")
@click.option("--no-figures", is_flag=True, help="Print only; write no figures.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@friendly
def demo(quick: bool, out: str, no_figures: bool, seed: int) -> None:
    """Run the main job on built-in simulated data and print what it finds."""
    from .demo import run_demo

    click.echo(run_demo(quick=quick, out=None if no_figures else out, seed=seed))


@main.command()
@click.argument("file", type=click.Path())
@recording_options
@click.option("--window", "window_s", type=float, default=1.0, show_default=True, help="s")
@click.option("--k", type=float, default=6.0, show_default=True, help="Threshold factor.")
@click.option("--min-dwell", "min_dwell_s", type=float, default=1.0, show_default=True, help="s")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Write the dwell table as CSV.")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
@friendly
def dwells(
    file: str,
    fs: float | None,
    columns: str | None,
    window_s: float,
    k: float,
    min_dwell_s: float,
    output: str | None,
    as_json: bool,
    quiet: bool,
) -> None:
    """Detect the static dwells of a recording and print their statistics."""
    from .io import stream_dwells

    d = stream_dwells(file, fs=fs, columns=columns, window_s=window_s, k=k,
                      min_dwell_s=min_dwell_s, progress=False if quiet else None)
    if output:
        d.to_csv(output)
    if as_json:
        emit_json(d.to_dict())
        return
    click.echo(f"{file}: {len(d)} dwells at {d.fs:.6g} Hz")
    if d.noise_std is not None and d.threshold is not None:
        click.echo(
            "noise std per axis (from the data): "
            + " ".join(f"{v:.4g}" for v in d.noise_std)
            + f"; threshold = {k:g} x noise variance"
        )
    click.echo(d.table())
    if output:
        click.echo(f"wrote {output}")



def _tqdm_disable(quiet: bool) -> bool | None:
    # tqdm: None disables the bar when stderr is not a terminal.
    return True if quiet else None


def _plot_available() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def _need_plot(path: str | None) -> None:
    if path and not _plot_available():
        raise CalibrationError("plots need matplotlib: pip install 'accelcal[plot]'")


def _save_fig(fig: Any, path: str) -> None:
    from .plots import save_figure

    save_figure(fig, path)


def _load_stream(file: str, fs: float | None, columns: str | None) -> Any:
    from .io import read_stream

    st = read_stream(file, columns=columns, fs=fs)
    if st.fs is None:
        raise CalibrationError(
            f"{file}: the sample rate is not in the file; give it with --fs (Hz)"
        )
    return st


def _resolve_g(g: float | None, lat: float | None, height: float) -> tuple[float, str]:
    from .static import local_gravity

    if g is not None:
        return g, "given"
    if lat is not None:
        return local_gravity(lat, height), f"WGS84 normal gravity at {lat:g} deg, {height:g} m"
    raise CalibrationError("give the reference gravity with --g (m/s^2) or --lat/--height")


@main.group()
def calibrate() -> None:
    """Calibrate from a recording (static), a centrifuge table or a gradiometer table."""


@calibrate.command("static")
@click.argument("file", type=click.Path())
@gravity_options
@recording_options
@click.option("--model", type=click.Choice(["lower", "diag", "upper"]), default="lower",
              show_default=True, help="9-parameter triangle or 6-parameter bias + scale.")
@click.option("--method", type=click.Choice(["lm", "gauss-newton", "quadric", "linear-paper"]),
              default="lm", show_default=True, help="Fit method (lm = maximum likelihood).")
@click.option("--window", "window_s", type=float, default=1.0, show_default=True,
              help="Dwell detector window, s.")
@click.option("--k", "k_thr", type=float, default=6.0, show_default=True,
              help="Dwell detector threshold factor (x noise variance).")
@click.option("--min-dwell", "min_dwell_s", type=float, default=1.0, show_default=True,
              help="Shortest dwell kept, s.")
@click.option("--sensor-id", default="", help="Stored in the calibration file.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Write the calibration (versioned JSON).")
@click.option("--dwells-out", type=click.Path(dir_okay=False), default=None,
              help="Write the dwell table (CSV).")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None,
              help="Norm before/after and per-dwell residuals (PNG/PDF/SVG).")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@friendly
def calibrate_static(
    file: str, g: float | None, lat: float | None, height: float, fs: float | None,
    columns: str | None, model: str, method: str, window_s: float, k_thr: float,
    min_dwell_s: float, sensor_id: str, output: str | None,
    dwells_out: str | None, plot_path: str | None, as_json: bool,
) -> None:
    """Static field calibration: detect dwells, fit scale, bias and non-orthogonality."""
    import datetime
    import warnings

    from ._core import DegenerateDataError
    from .dwell import detect_dwells
    from .static import fit_static

    _need_plot(plot_path)
    gv, g_src = _resolve_g(g, lat, height)
    st = _load_stream(file, fs, columns)
    d = detect_dwells(st.samples, st.fs, t=st.t, temperature=st.temperature, window_s=window_s,
                      k=k_thr, min_dwell_s=min_dwell_s)
    if dwells_out:
        d.to_csv(dwells_out)
    notes: list[str] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            fit = fit_static(d, gv, model=model, method=method)
        except DegenerateDataError as e:
            hint = ""
            if model != "diag" and "diag" not in str(e):
                hint = " Try --model diag (bias + scale: 6 parameters) or add attitudes."
            raise CalibrationError(
                f"{len(d)} dwells found in {file}, but they cannot determine the {model!r} "
                f"model: {e}.{hint}"
            ) from None
    for w in caught:
        notes.append(str(w.message))
    if output:
        temp = None if d.temperature is None else float(np.mean(d.temperature))
        meta = {"source": str(file), "n_dwells": len(d)}
        fit.to_model(sensor_id=sensor_id, date=datetime.date.today().isoformat(),
                     temperature=temp, metadata=meta).save(output)
    if plot_path:
        from .plots import static_norm_figure

        _save_fig(static_norm_figure(fit, d), plot_path)
    if as_json:
        out = fit.to_dict()
        out.update(n_dwells=len(d), g_source=g_src, warnings=notes, file=str(file))
        emit_json(out)
        return
    click.echo(f"{file}: {len(st.samples)} samples at {st.fs:g} Hz -> {len(d)} dwells")
    click.echo(f"reference gravity g = {gv:.6f} m/s^2 ({g_src})")
    click.echo(fit.summary())
    for n in notes:
        click.echo(f"warning: {n}")
    if output:
        click.echo(f"wrote {output}")
    if plot_path:
        click.echo(f"wrote {plot_path}")


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

    from .centrifuge import calibrate_centrifuge_table

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
    from .gradiometer import calibrate_gradiometer_table

    sb = calibrate_gradiometer_table(table, drift=drift, sigma=sigma)
    if output:
        write_json_file(output, sb.to_dict())
    if as_json:
        emit_json(sb.to_dict())
        return
    click.echo(sb.summary())
    if output:
        click.echo(f"wrote {output}")


@main.command()
@click.argument("cal", type=click.Path())
@click.argument("file", type=click.Path())
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True,
              help="Calibrated stream: .csv (t_s, ax, ay, az in m/s^2) or .npy.")
@recording_options
@click.option("--chunk-rows", type=int, default=500_000, show_default=True)
@click.option("--quiet", is_flag=True, help="No progress bar.")
@friendly
def apply(cal: str, file: str, output: str, fs: float | None, columns: str | None,
          chunk_rows: int, quiet: bool) -> None:
    """Apply a calibration file to a recording, streaming chunk by chunk."""
    from tqdm import tqdm

    from .io import iter_stream
    from .static import TriadModel

    model = TriadModel.load(cal)
    out = Path(output)
    if out.resolve() == Path(file).resolve():
        raise CalibrationError("the output would overwrite the input recording; choose -o")
    chunks = tqdm(iter_stream(file, chunk_rows=chunk_rows, columns=columns, fs=fs),
                  unit="chunk", desc="apply", disable=_tqdm_disable(quiet))
    n = 0
    if out.suffix == ".npy":
        parts = [model.apply(chunk) for chunk, _t in chunks]
        arr = np.concatenate(parts) if parts else np.empty((0, 3))
        n = len(arr)
        with atomic_open(out, "wb") as fh:
            np.save(fh, arr)
    else:
        with atomic_open(out, "w") as fh:
            fh.write(f"# calibrated by accelcal with {cal}; units m/s^2\n")
            fh.write("t_s,ax,ay,az\n")
            for chunk, t in chunks:
                a = model.apply(chunk)
                tt = t if t is not None else np.full(len(a), np.nan)
                np.savetxt(fh, np.column_stack([tt, a]), delimiter=",", fmt="%.10g")
                n += len(a)
    click.echo(f"wrote {n} calibrated samples to {output}")


@main.command()
@click.argument("file", type=click.Path())
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
             columns: str | None, noise: str, preset: str, plot_path: str | None,
             as_json: bool) -> None:
    """Sim-to-real gap diagnosis of a static session recording."""
    from .dwell import detect_dwells
    from .gap import diagnose as run_diagnose

    _need_plot(plot_path)
    gv, _ = _resolve_g(g, lat, height)
    st = _load_stream(file, fs, columns)
    if noise == "allan":
        rep = run_diagnose(st.samples, g=gv, fs=st.fs, t=st.t, temperature=st.temperature,
                           preset=preset)
        n_dwells = rep.n
    else:
        d = detect_dwells(st.samples, st.fs, t=st.t, temperature=st.temperature)
        rep = run_diagnose(d, g=gv, preset=preset)
        n_dwells = len(d)
    if plot_path:
        _save_fig(rep.plot(), plot_path)
    if as_json:
        emit_json(rep.to_dict())
        return
    click.echo(f"{file}: {n_dwells} dwells at {st.fs:g} Hz, g = {gv:.6f} m/s^2")
    click.echo(rep.summary())
    if plot_path:
        click.echo(f"wrote {plot_path}")


@main.command()
@click.option("--n", "n", type=int, required=True, help="Number of attitudes.")
@click.option("--max-tilt", type=float, default=30.0, show_default=True,
              help="Two-axis platform tilt limit, deg (use 180 for the full sphere).")
@click.option("--sigma", type=float, default=1e-3, show_default=True,
              help="Noise std of one dwell mean, m/s^2.")
@click.option("--model", type=click.Choice(["lower", "diag", "upper"]), default="lower",
              show_default=True)
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None,
              help="Planned attitudes on the sphere.")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@friendly
def plan(n: int, max_tilt: float, sigma: float, model: str, plot_path: str | None,
         as_json: bool) -> None:
    """Plan n attitudes (D-optimal) and print the accuracy they predict."""
    from .static import plan_poses

    _need_plot(plot_path)
    mt = None if max_tilt >= 180 else max_tilt
    p = plan_poses(n, mt, sigma=sigma, model=model)
    if plot_path:
        from .plots import poses_figure

        _save_fig(poses_figure(p), plot_path)
    if as_json:
        emit_json(_plan_dict(p, sigma, model))
        return
    click.echo(_plan_text(p, sigma, model))
    if plot_path:
        click.echo(f"wrote {plot_path}")


def _plan_dict(p: Any, sigma: float, model: str) -> dict[str, Any]:
    pred = p.prediction
    return {
        "n": int(len(p.directions)),
        "model": model,
        "sigma_mps2": sigma,
        "tilts_deg": None if p.tilts_deg is None else p.tilts_deg,
        "directions": p.directions,
        "predicted_std": dict(zip(pred.names, pred.std, strict=True)),
        "singular": bool(pred.singular),
        "condition": pred.condition,
    }


def _plan_text(p: Any, sigma: float, model: str) -> str:
    pred = p.prediction
    lines = [f"{len(p.directions)} attitudes (D-optimal), model {model!r}, "
             f"dwell-mean noise {sigma:g} m/s^2"]
    if p.tilts_deg is not None:
        lines.append(f"{'#':>3} {'tilt_x_deg':>11} {'tilt_y_deg':>11}")
        lines += [f"{i:>3} {a:>11.2f} {b:>11.2f}" for i, (a, b) in enumerate(p.tilts_deg)]
    else:
        lines.append(f"{'#':>3} {'gx':>8} {'gy':>8} {'gz':>8}  (unit gravity direction)")
        lines += [f"{i:>3} {a:>8.4f} {b:>8.4f} {c:>8.4f}" for i, (a, b, c) in
                  enumerate(p.directions)]
    lines.append("predicted std (Cramer-Rao bound, 1 sigma):")
    lines.append(pred.table())
    if pred.singular:
        lines.append(f"SINGULAR design: {pred.combination}")
    return "\n".join(lines)


def write_json_file(path: str | Path, obj: Any) -> None:
    atomic_write(path, json.dumps(_jsonable(obj), indent=2) + "\n")


if __name__ == "__main__":  # pragma: no cover
    main()
