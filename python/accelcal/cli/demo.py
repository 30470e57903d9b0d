"""``accelcal demo``: the main job on built-in simulated data."""

from __future__ import annotations

import click

from ._common import friendly, main


@main.command()
@click.option("--quick", is_flag=True, help="Shorter simulated session (for a fast look).")
@click.option("--out", type=click.Path(file_okay=False), default="accelcal-demo", show_default=True,
              help="Folder for the figures.")
@click.option("--no-figures", is_flag=True, help="Print only; write no figures.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@friendly
def demo(quick: bool, out: str, no_figures: bool, seed: int) -> None:
    """Run the main job on built-in simulated data and print what it finds."""
    from ..demo import run_demo

    click.echo(run_demo(quick=quick, out=None if no_figures else out, seed=seed))
