"""Simulated fleet: many static-session recordings as text files, a few of them corrupted.

Each recording is a :func:`~accelcal.sim.field_session` stream (``t, ax, ay, az`` in m/s^2,
with an ``# fs: ...`` metadata line) of a sensor with its own random calibration. A chosen
fraction is corrupted the ways real files go wrong, and the truth says which and how:

- ``"garbled"``: one row in ten has a field that is not a number (a logger that wrote
  error codes; too many to leave out, so the file is refused);
- ``"truncated"``: the file is cut mid-line part-way through (a copy that never finished);
- ``"nan_rows"``: a few rows inside dwells read ``nan`` (a logger's dropouts);
- ``"wrong_columns"``: one row has an extra field (a line from another logger mixed in);
- ``"few_poses"``: the session stopped after a few attitudes (too few to calibrate).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from .._core import CalibrationError
from .field import field_session
from .static import G0

__all__ = ["CORRUPTIONS", "FleetRecording", "fleet_recordings", "random_calibration"]

CORRUPTIONS = ("garbled", "truncated", "nan_rows", "wrong_columns", "few_poses")


@dataclass(frozen=True)
class FleetRecording:
    """One simulated recording and its truth.

    path : the text file.  sensor_id : the sensor's name (also the file stem).
    truth : (9,) [sx, sy, sz, bx, by, bz, m1, m2, m3] (K dimensionless, b in m/s^2).
    corruption : "" for a good file, else one of :data:`CORRUPTIONS`.
    n_dwells : attitudes held in the file as written (before any corruption).
    """

    path: str
    sensor_id: str
    truth: NDArray[np.float64]
    corruption: str
    n_dwells: int


def random_calibration(rng: np.random.Generator) -> NDArray[np.float64]:
    """A plausible MEMS calibration: scale 1 +- 2 %, bias +- 0.1 m/s^2, coupling +- 1 %."""
    return np.concatenate([
        1.0 + rng.normal(0.0, 0.02, 3),
        rng.normal(0.0, 0.1, 3),
        rng.normal(0.0, 0.01, 3),
    ])


def _text(t: NDArray[np.float64], x: NDArray[np.float64], fs: float) -> str:
    rows = np.column_stack([t, x])
    lines = [f"# fs: {fs:g}", "t,ax,ay,az"]
    lines += [f"{a:.4f},{b:.6f},{c:.6f},{d:.6f}" for a, b, c, d in rows.tolist()]
    return "\n".join(lines) + "\n"


def fleet_recordings(
    folder: str | os.PathLike[str],
    n: int,
    *,
    n_dwells: int = 24,
    fs: float = 50.0,
    dwell_s: float = 3.0,
    move_s: float = 1.0,
    sigma: float = 2e-3,
    g: float = G0,
    corrupt: float = 0.02,
    truths: NDArray[np.float64] | None = None,
    seed: int = 0,
) -> list[FleetRecording]:
    """Write ``n`` simulated recordings ``folder/S00000.csv`` ... and return their truth.

    Every sensor gets :func:`random_calibration` (or row i of ``truths`` (n, 9)); attitudes are
    uniform within +-60 deg of level, which determines all 9 parameters. ``round(corrupt * n)``
    files (at least one when ``corrupt > 0``), spread evenly through the list, are corrupted,
    cycling through :data:`CORRUPTIONS`. Deterministic for a given ``seed``.
    """
    if n < 1:
        raise CalibrationError(f"n must be >= 1 (number of recordings); got {n}")
    if not 0.0 <= corrupt <= 1.0:
        raise CalibrationError(f"corrupt must be a fraction in [0, 1]; got {corrupt}")
    if truths is not None and np.shape(truths) != (n, 9):
        raise CalibrationError(f"truths must have shape ({n}, 9); got {np.shape(truths)}")
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    n_bad = 0 if corrupt == 0 else max(1, int(round(corrupt * n)))
    bad_at = {int(i): CORRUPTIONS[j % len(CORRUPTIONS)]
              for j, i in enumerate(np.linspace(0, n - 1, n_bad + 2)[1:-1].round())}
    recs = []
    for i in range(n):
        rng = np.random.default_rng([seed, i])
        truth = random_calibration(rng) if truths is None else np.asarray(truths[i], float)
        kind = bad_at.get(i, "")
        nd = 5 if kind == "few_poses" else n_dwells
        s = field_session(fs=fs, n_dwells=nd, dwell_s=dwell_s, move_s=move_s, max_tilt_deg=60.0,
                          truth=truth, g=g, sigma=sigma, rng=rng)
        text = _text(s.t, s.samples, fs)
        lines = text.splitlines(keepends=True)
        if kind == "garbled":
            for r in range(2, len(lines), 10):  # two lines before the data
                lines[r] = f"{s.t[r - 2]:.4f},ERR,0.0,0.0\n"
            text = "".join(lines)
        elif kind == "truncated":
            cut = sum(len(ln) for ln in lines[: len(lines) // 2]) + 9
            text = text[:cut]
        elif kind == "nan_rows":
            for b in s.bounds[[1, len(s.bounds) // 2, -2]]:
                r = 2 + int(b[0] + b[1]) // 2  # two lines before the data
                lines[r] = f"{s.t[r - 2]:.4f},nan,nan,nan\n"
            text = "".join(lines)
        elif kind == "wrong_columns":
            r = 2 + int(s.bounds[len(s.bounds) // 2, 0])
            lines[r] = lines[r].rstrip("\n") + ",0.0\n"
            text = "".join(lines)
        sid = f"S{i:05d}"
        p = out / f"{sid}.csv"
        p.write_text(text)
        recs.append(FleetRecording(str(p), sid, truth, kind, nd))
    return recs
