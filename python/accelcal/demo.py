"""``accelcal demo``: the main job on built-in simulated data.

Field session -> dwells -> calibration (-> gap diagnosis), then the centrifuge and
gradiometer sections. Each section is a function returning printable text.
"""

from __future__ import annotations

import time

import numpy as np

from .dwell import detect_dwells
from .sim_field import field_session


def field_section(*, quick: bool = False, seed: int = 0) -> str:
    """Simulate a seed-000-like session at 5 kHz, detect its dwells, calibrate it."""
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
    ok = sum(
        1
        for a, b in zip(d.start if d.start is not None else [], d.stop if d.stop is not None else [])
        if np.any((s.bounds[:, 0] <= a) & (b <= s.bounds[:, 1]))
    )
    lines.append(f"{ok}/{len(d)} detected dwells lie inside a true static interval")
    try:
        from .demo_static import demo_section as static_demo
    except ImportError:
        pass
    else:
        lines.append("")
        lines.append(static_demo(d, s.g, truth=s.truth))
    return "\n".join(lines)


def run_demo(*, quick: bool = False, out: str | None = None, seed: int = 0) -> str:
    """All demo sections as one text."""
    parts = [field_section(quick=quick, seed=seed)]
    for mod in ("demo_gap", "demo_centrifuge", "demo_gradiometer"):
        try:
            m = __import__(f"accelcal.{mod}", fromlist=["demo_section"])
        except ImportError:
            continue
        parts.append("")
        parts.append(m.demo_section(rng_seed=seed))
    return "\n".join(parts)
