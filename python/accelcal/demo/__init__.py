"""``accelcal demo``: the main job on built-in simulated data.

Field session -> dwells -> calibration (-> gap diagnosis), then the centrifuge and
gradiometer sections. Each section is a function returning printable text.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..dwell import detect_dwells
from ..sim.field import field_session
from .centrifuge import demo_section as centrifuge_demo
from .gap import demo_report as gap_demo_report
from .gradiometer import demo_section as gradiometer_demo
from .static import fit_section as static_fit_section


def field_section(*, quick: bool = False, seed: int = 0) -> str:
    """Simulate a field session at 5 kHz, detect its dwells, calibrate it."""
    return _field(quick=quick, seed=seed)[0]


def _field(*, quick: bool, seed: int) -> tuple[str, Any, Any]:
    n, dwell_s = (20, 20.0) if not quick else (20, 4.0)
    t0 = time.perf_counter()
    s = field_session(fs=5000.0, n_dwells=n, dwell_s=dwell_s, move_s=4.0, max_tilt_deg=30.0,
                      rng=seed)
    t1 = time.perf_counter()
    d = detect_dwells(s.samples, s.fs, units="m/s^2")
    t2 = time.perf_counter()
    nbytes = s.samples.nbytes
    lines = [
        "== Static field calibration (norm observation, two-axis platform) ==",
        f"simulated {n} dwells x {dwell_s:g} s at {s.fs:g} Hz, tilts within +-30 deg, "
        f"noise {s.sigma:g} m/s^2 per sample ({nbytes / 1e6:.0f} MB, {t1 - t0:.2f} s to simulate)",
        f"detected {len(d)} dwells in {1e3 * (t2 - t1):.1f} ms "
        f"({nbytes / (t2 - t1) / 1e9:.1f} GB/s); noise std from the data "
        + " ".join(f"{v:.3g}" for v in (d.noise_std if d.noise_std is not None else []))
        + " m/s^2",
        d.table(),
    ]
    starts = d.start if d.start is not None else np.zeros(0, dtype=np.int64)
    stops = d.stop if d.stop is not None else np.zeros(0, dtype=np.int64)
    ok = sum(
        1
        for a, b in zip(starts, stops, strict=True)
        if np.any((s.bounds[:, 0] <= a) & (b <= s.bounds[:, 1]))
    )
    lines.append(f"{ok}/{len(d)} detected dwells lie inside a true static interval")
    lines.append("")
    text, fit = static_fit_section(d, s.g, truth=s.truth)
    lines.append(text)
    return "\n".join(lines), d, fit


@dataclass
class DemoResult:
    """What ``accelcal demo`` found: the printable text of each section, the field
    calibration and the gap report behind them, and the figures written."""

    sections: dict[str, str]
    fit: Any
    n_dwells: int
    gap: Any
    figures: str | None = None
    seed: int = 0  # the random seed of every simulated session

    @property
    def text(self) -> str:
        parts = [f"seed {self.seed} (accelcal demo --seed N simulates other sessions)",
                 *self.sections.values()]
        if self.figures is not None:
            parts.append(self.figures)
        return "\n\n".join(parts)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (``accelcal demo --json``)."""
        return {
            "seed": self.seed,
            "sections": dict(self.sections),
            "field": {
                "n_dwells": self.n_dwells,
                "fit": None if self.fit is None else self.fit.to_dict(),
            },
            "gap": self.gap.to_dict(),
            "figures": self.figures,
        }


def demo_result(*, quick: bool = False, out: str | None = None, seed: int = 0) -> DemoResult:
    """Run every demo section; figures go to ``out`` when it is given."""
    text, dwells, fit = _field(quick=quick, seed=seed)
    gap_text, gap_rep = gap_demo_report(rng_seed=seed)
    sections = {
        "field": text,
        "gap": gap_text,
        "centrifuge": centrifuge_demo(rng_seed=seed),
        "gradiometer": gradiometer_demo(rng_seed=seed),
    }
    figures = None if out is None else _figures(out, dwells, fit, gap_rep)
    return DemoResult(sections, fit, len(dwells), gap_rep, figures, seed=seed)


def run_demo(*, quick: bool = False, out: str | None = None, seed: int = 0) -> str:
    """All demo sections as one text."""
    return demo_result(quick=quick, out=out, seed=seed).text


def _figures(out: str, dwells: Any, fit: Any, gap_rep: Any) -> str:
    """Write the demo's figures into ``out``; a note instead when matplotlib is missing."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return "figures skipped: install the plot extra (pip install 'accelcal[plot]')"
    import matplotlib.pyplot as plt

    from ..design import plan_poses
    from ..plots import poses_figure, save_figure, static_norm_figure

    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    if fit is not None:
        fig = static_norm_figure(fit, dwells)
        save_figure(fig, str(folder / "field_norm.png"))
        written.append("field_norm.png (norm per dwell before/after, residuals)")
        plt.close(fig)
    fig = poses_figure(plan_poses(20, 30.0))
    save_figure(fig, str(folder / "planned_poses.png"))
    written.append("planned_poses.png (20 D-optimal attitudes within +-30 deg)")
    plt.close(fig)
    fig = gap_rep.plot()
    save_figure(fig, str(folder / "gap.png"))
    written.append(f"gap.png (the gap section's session: residuals vs time, temperature, pose "
                   f"and the noise panel; best = {gap_rep.best})")
    plt.close(fig)
    return "figures written to " + str(folder) + ":\n" + "\n".join("  " + w for w in written)
