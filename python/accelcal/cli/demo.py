"""``accelcal demo``: the main job on built-in simulated data."""

from __future__ import annotations

import click

from ._common import emit_json, friendly, main


@main.command()
@click.option("--quick", is_flag=True, help="Shorter simulated session (for a fast look).")
@click.option("--out", type=click.Path(file_okay=False), default="accelcal-demo", show_default=True,
              help="Folder for the figures.")
@click.option("--no-figures", is_flag=True, help="Print only; write no figures.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@friendly
def demo(quick: bool, out: str, no_figures: bool, seed: int, as_json: bool) -> None:
    """Run the main job on built-in simulated data and print what it finds."""
    from ..demo import demo_result

    res = demo_result(quick=quick, out=None if no_figures else out, seed=seed)
    if as_json:
        emit_json(res.to_dict())
        return
    click.echo(res.text)
