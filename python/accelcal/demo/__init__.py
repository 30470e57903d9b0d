"""``accelcal demo``: the main job on built-in simulated data.

Field session -> dwells -> calibration (-> gap diagnosis), then the centrifuge and
gradiometer sections. Each section is a function returning printable text.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from ..dwell import detect_dwells
from ..sim.field import field_session
from .centrifuge import demo_section as centrifuge_demo
from .gap import demo_section as gap_demo
from .gradiometer import demo_section as gradiometer_demo
from .static import fit_section as static_fit_section


def field_section(*, quick: bool = False, seed: int = 0) -> str:
    """Simulate a seed-000-like session at 5 kHz, detect its dwells, calibrate it."""
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
        "== Static field calibration (seed 000) ==",
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


def run_demo(*, quick: bool = False, out: str | None = None, seed: int = 0) -> str:
    """All demo sections as one text."""
    text, dwells, fit = _field(quick=quick, seed=seed)
    parts = [text]
    for section in (gap_demo, centrifuge_demo, gradiometer_demo):
        parts.append("")
        parts.append(section(rng_seed=seed))
    if out is not None:
        parts.append("")
        parts.append(_figures(out, dwells, fit, seed))
    return "\n".join(parts)


def _figures(out: str, dwells: Any, fit: Any, seed: int) -> str:
    """Write the demo's figures into ``out``; a note instead when matplotlib is missing."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return "figures skipped: install the plot extra (pip install 'accelcal[plot]')"
    import matplotlib.pyplot as plt

    from ..design import plan_poses
    from ..gap import diagnose
    from ..plots import poses_figure, save_figure, static_norm_figure
    from ..sim.gap import gap_session

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
    s = gap_session(("drift",), rng=seed, amplitudes=[25.0])
    fig = diagnose(s.dwells, g=s.g).plot()
    save_figure(fig, str(folder / "gap_drift.png"))
    written.append("gap_drift.png (residuals vs time/temperature/pose before and after)")
    plt.close(fig)
    return "figures written to " + str(folder) + ":\n" + "\n".join("  " + w for w in written)
