"""Example acquisition script: stream chunks into DwellAccumulator and calibrate online.

A real script would read chunks from its DAQ callback; here a simulated 5 kHz field session
(the simulator's truth, ``accelcal.sim.FIELD_TRUTH``: the simulation truth of Huang et al.'s
norm-observation paper) is cut into 0.1 s chunks. After every new dwell the calibration is refitted
on all dwells so far, and the operator sees the predicted accuracy improve.

    python examples/acquisition.py [--dwell-s 20] [--n-dwells 20]

A session the calibration cannot come from (fewer than 9 dwells, or rests too short for the
dwell detector to see) ends with the reason and exit status 2.
"""

from __future__ import annotations

import argparse
import sys
import warnings

import accelcal as ac
import numpy as np
from accelcal.sim import field_session


def run(n_dwells: int = 20, dwell_s: float = 20.0, chunk_s: float = 0.1, seed: int = 0,
        verbose: bool = True) -> ac.StaticFit | None:
    s = field_session(fs=5000.0, n_dwells=n_dwells, dwell_s=dwell_s, move_s=4.0, rng=seed)
    acc = ac.DwellAccumulator(fs=s.fs, units="m/s^2")
    step = int(chunk_s * s.fs)
    seen = 0
    fit = None
    for i in range(0, len(s.samples), step):
        acc.push(s.samples[i : i + step], t=s.t[i : i + step])  # the DAQ callback's chunk
        if (i // step) % int(2.0 / chunk_s):  # look every 2 s of data
            continue
        try:
            d = acc.finish()  # the dwells so far (the accumulator keeps going)
        except ac.CalibrationError:
            continue  # not enough data for detection yet
        if len(d) <= seen or len(d) < 10:
            continue
        seen = len(d)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ac.WeakDesignWarning)
            try:
                fit = ac.fit_static(d, s.g)
            except ac.DegenerateDataError as e:
                if verbose:
                    print(f"{len(d):>3} dwells: not yet determined ({e})")
                continue
        if verbose:
            worst = fit.names[int(np.argmax(fit.std))]
            print(f"{len(d):>3} dwells: rms {fit.rms:.2e} m/s^2, largest std {worst} "
                  f"+-{fit.std.max():.2e}")
    d = acc.finish()
    fit = ac.fit_static(d, s.g)
    if verbose:
        print(fit.summary(truth=s.truth))
    return fit


N_PARAMS = 9  # the default model "lower": 3 scale factors, 3 biases, 3 couplings


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-dwells", type=int, default=20,
                    help=f"attitudes held (at least {N_PARAMS}: the model has {N_PARAMS} "
                         "parameters)")
    ap.add_argument("--dwell-s", type=float, default=20.0,
                    help="seconds each attitude is held (the dwell detector needs rests of "
                         "about 2 s or more)")
    a = ap.parse_args(argv)
    if a.n_dwells < N_PARAMS:
        ap.error(f"--n-dwells {a.n_dwells}: the {N_PARAMS}-parameter calibration needs at least "
                 f"{N_PARAMS} dwells (more to estimate the noise)")
    if not a.dwell_s > 0:
        ap.error(f"--dwell-s {a.dwell_s}: must be a positive number of seconds")
    try:
        run(a.n_dwells, a.dwell_s)
    except ac.CalibrationError as e:  # DegenerateDataError too: no dwells seen, too few ...
        print(f"acquisition.py: no calibration from this session: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
