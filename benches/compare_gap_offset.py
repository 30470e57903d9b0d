"""The per-dwell variance-component model (``diagnose(random_offset=True)``) against the
default, on the semi-synthetic sessions built on the real xsens recording and on null sessions.

    .venv/bin/python benches/compare_gap_offset.py [--n 100]

Same sessions as the real-noise section of benches/validate_gap.py (a random subset of 32 real
dwells, synthetic heat-then-cool temperature, one dictionary effect added to the samples at
lambda_emp = 30 or 100), generated once per seed and diagnosed with both settings; plus the
xsens and MPU-9150 null sessions (no effect) and the simulated designed/naive null sessions.
Prints top-1 and false-alarm counts per setting.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import accelcal
import numpy as np
from accelcal.sim.gap import DICTIONARY_EFFECTS, gap_session

sys.path.insert(0, str(Path(__file__).resolve().parent))
import validate_gap as V  # noqa: E402

SETTINGS = (False, True)


def _pct(k: int, n: int) -> str:
    p = k / n
    return f"{100 * p:.0f} +- {100 * math.sqrt(p * (1 - p) / n):.0f} % ({k}/{n})"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=100)
    n = ap.parse_args().n
    base = V._xsens_base()
    gen = np.random.default_rng(2024)
    fa = dict.fromkeys(SETTINGS, 0)
    for _ in range(2 * n):
        d, _ = V._xsens_session(base, gen, None, 0.0)
        for ro in SETTINGS:
            fa[ro] += accelcal.diagnose(d, g=V.XS_G, random_offset=ro).best != "none"
    for ro in SETTINGS:
        print(f"random_offset={ro}: xsens null false alarms {_pct(fa[ro], 2 * n)}")
    gen = np.random.default_rng(2025)
    for eff in DICTIONARY_EFFECTS:
        for lam in (30.0, 100.0):
            ok = dict.fromkeys(SETTINGS, 0)
            for _ in range(n):
                d, _ = V._xsens_session(base, gen, eff, lam)
                for ro in SETTINGS:
                    ok[ro] += accelcal.diagnose(d, g=V.XS_G, random_offset=ro).best == eff
            print(f"{eff} lambda_emp {lam:g}: "
                  + ", ".join(f"random_offset={ro} top-1 {_pct(ok[ro], n)}" for ro in SETTINGS))
    recs = [r for r in V._load_recordings() if r["key"].startswith("mpu9150")]
    ctrl = dict.fromkeys(SETTINGS, 0)
    gen = np.random.default_rng(7)
    for i in range(2 * n):
        rec = recs[i % len(recs)]
        dd = accelcal.detect_dwells(rec["samples"], rec["fs"], t=rec["t"])
        keep = np.sort(gen.choice(len(dd), size=min(18, len(dd)), replace=False))
        t = rec["t"]
        t0, t1 = t[dd.start[keep[0]]], t[dd.stop[keep[-1]] - 1]
        peak = t0 + gen.uniform(0.35, 0.65) * (t1 - t0)
        T = 20.0 + gen.uniform(5.0, 15.0) * np.where(t < peak, (t - t0) / (peak - t0),
                                                     (t1 - t) / (t1 - peak))
        d = accelcal.dwell_stats(rec["samples"], np.column_stack([dd.start[keep],
                                                                   dd.stop[keep]]),
                                 t=t, temperature=T)
        for ro in SETTINGS:
            ctrl[ro] += accelcal.diagnose(d, g=rec["g"], random_offset=ro).best != "none"
    for ro in SETTINGS:
        print(f"random_offset={ro}: MPU-9150 null false alarms {_pct(ctrl[ro], 2 * n)}")
    for sched in ("designed", "naive"):
        sim = dict.fromkeys(SETTINGS, 0)
        for i in range(4 * n):
            s = gap_session((), schedule=sched, rng=1000 + i)
            for ro in SETTINGS:
                sim[ro] += accelcal.diagnose(s.dwells, g=s.g, random_offset=ro).best != "none"
        for ro in SETTINGS:
            print(f"random_offset={ro}: simulated {sched} null false alarms "
                  f"{_pct(sim[ro], 4 * n)}")


if __name__ == "__main__":
    main()
