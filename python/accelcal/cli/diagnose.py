"""``diagnose``: the sim-to-real gap of a static session recording."""

from __future__ import annotations

import click

from ._common import (
    _load_stream,
    _need_plot,
    _resolve_g,
    _save_fig,
    emit_json,
    friendly,
    gravity_options,
    main,
    recording_options,
)


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
    from ..dwell import detect_dwells
    from ..gap import diagnose as run_diagnose

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
