"""Withheld-effect session generator for checking the gap diagnosis (dwell-mean level).

A session has a random nuisance calibration (scale, bias, non-orthogonality), a pose set and
order, a temperature profile, dwell-mean noise, and 0, 1 or 2 hidden effects of random
magnitude, plus optional effects outside the dictionary (bias random walk) and blind-spot
effects (wrong g, upper-triangular coupling). The diagnoser is given only ``dwells`` and ``g``.
Effect terms follow exactly the definitions of the diagnosis (rust/src/gap.rs), so the hidden
parameters are in the same physical units (ug/K, ppm/K, ug/h, ug/g^2, ug/g^3, ppm of step).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .. import _core
from .._core import CalibrationError
from .._triad import fibonacci_sphere
from ..dwell import DwellSet

__all__ = ["DICTIONARY_EFFECTS", "GapSession", "OTHER_EFFECTS", "gap_session", "signal_strength"]

DICTIONARY_EFFECTS = ("temperature_bias", "temperature_scale", "drift", "k2", "k3", "settling")
#: Effects outside the dictionary (random walk) or invisible to any static norm fit.
OTHER_EFFECTS = ("bias_random_walk", "wrong_g", "upper_coupling")


@dataclass
class GapSession:
    """A simulated static session with hidden effects.

    dwells : DwellSet (raw units = m/s^2 through K ~ I; var/count give the reported noise).
    g : gravity given to the diagnoser, m/s^2.
    effects : hidden effects, name -> per-axis parameters in physical units (dictionary
        effects) or a description (others).
    amplitude_sigma : name -> RMS of the effect's output term over the dwells, in sigma.
    lam : signal strength: chi2 that all hidden effects leave after a baseline fit (noise free).
    lam_each : the same for each effect alone.
    schedule : "designed" or "naive".  poses : "sphere" or "faces".
    nuisance : [sx,sy,sz,bx,by,bz,m1,m2,m3] of the session.
    sigma : reported std of each dwell mean per axis; noise_scale : true / reported.
    """

    dwells: DwellSet
    g: float
    effects: dict[str, Any]
    amplitude_sigma: dict[str, float]
    lam: float
    lam_each: dict[str, float]
    schedule: str
    poses: str
    nuisance: NDArray[np.float64]
    sigma: float
    noise_scale: float
    meta: dict[str, Any] = field(default_factory=dict)



def _random_rotation(gen: np.random.Generator) -> NDArray[np.float64]:
    q = gen.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _terms(name: str, p: NDArray[np.float64], z: NDArray[np.float64], c: NDArray[np.float64],
           dT: NDArray[np.float64], th: NDArray[np.float64],
           step: NDArray[np.float64]) -> NDArray[np.float64]:
    """Output term (k, 3) of a dictionary effect, raw units (same definitions as gap.rs)."""
    u = 1e-6 * p[None, :]
    if name == "temperature_bias":
        return u * c[None, :] * dT[:, None]
    if name == "temperature_scale":
        return u * z * dT[:, None]
    if name == "drift":
        return u * c[None, :] * th[:, None]
    if name == "k2":
        return u * z**2 / c[None, :]
    if name == "k3":
        return u * z**3 / c[None, :] ** 2
    if name == "settling":
        return u * step
    raise CalibrationError(f"unknown effect {name!r}")


def signal_strength(mean: NDArray[np.float64], sigma: NDArray[np.float64], g: float,
                    t: NDArray[np.float64] | None,
                    temperature: NDArray[np.float64] | None) -> float:
    """lambda: chi2 a baseline fit leaves on noise-free dwell means (whitened by ``sigma``)."""
    try:
        r = _core.gap_diagnose_raw(np.ascontiguousarray(mean), np.ascontiguousarray(sigma), t,
                                   temperature, float(g), [], loo=False)
    except CalibrationError:
        return float("nan")
    return float(r["chi2"])


def gap_session(
    effects: Sequence[str] | str = (),
    *,
    schedule: str = "designed",
    n_dwells: int = 24,
    sigma: float = 1e-4,
    rng: int | np.random.Generator | None = None,
    amplitudes: Sequence[float] | None = None,
    amp_range: tuple[float, float] = (0.5, 50.0),
    poses: str = "sphere",
    noise_scale: float = 1.0,
    temperature: bool = True,
    g: float = 9.80665,
    dwell_s: float = 60.0,
    move_s: float = 30.0,
    fs: float = 100.0,
) -> GapSession:
    """Simulate dwell means of a static session with hidden effects.

    Parameters
    ----------
    effects : names from :data:`DICTIONARY_EFFECTS` or :data:`OTHER_EFFECTS` (0, 1 or more).
    schedule : "designed" (random pose order, heat-then-cool temperature) or "naive" (swept
        pose order along a spiral, monotone warm-up).
    n_dwells : number of dwells.
    sigma : std of each dwell mean per axis, m/s^2 (raw units ~ m/s^2).
    rng : seed or Generator.
    amplitudes : per effect, RMS of its output term over the dwells in units of ``sigma``
        (default: log-uniform over ``amp_range``).
    poses : "sphere" (Fibonacci points, random attitude) or "faces" (the six faces, hand
        placed with +-3 deg tilts: a blind spot for K3).
    noise_scale : the true noise is ``noise_scale * sigma`` while var/count report ``sigma``
        (a mis-scaled noise model).
    temperature : record the temperature (False: the DwellSet has none).
    g : gravity given to the diagnoser, m/s^2.
    dwell_s, move_s, fs : timing; var = sigma^2 * count with count = dwell_s * fs.
    """
    gen = np.random.default_rng(rng)
    names = [effects] if isinstance(effects, str) else list(effects)
    for nm in names:
        if nm not in DICTIONARY_EFFECTS and nm not in OTHER_EFFECTS:
            raise CalibrationError(f"unknown effect {nm!r}")
    if schedule not in ("designed", "naive"):
        raise CalibrationError("schedule must be 'designed' or 'naive'")
    if n_dwells < 10:
        raise CalibrationError("n_dwells must be >= 10")
    n = n_dwells
    # Poses.
    if poses == "sphere":
        dirs = fibonacci_sphere(n) @ _random_rotation(gen).T
    elif poses == "faces":
        faces = np.vstack([np.eye(3), -np.eye(3)])
        dirs = faces[np.arange(n) % 6]
        tilt = np.radians(3.0) * gen.uniform(-1, 1, size=(n, 3))
        dirs = dirs + np.cross(tilt, dirs)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    else:
        raise CalibrationError("poses must be 'sphere' or 'faces'")
    if schedule == "designed":
        dirs = dirs[gen.permutation(n)]
    # Time and temperature.
    t = (np.arange(n) * (dwell_s + move_s) + dwell_s / 2).astype(np.float64)
    dur = n * (dwell_s + move_s)
    dTmax = gen.uniform(5.0, 15.0)
    if schedule == "naive":
        tau = gen.uniform(0.3, 0.8) * dur
        T = 20.0 + dTmax * (1.0 - np.exp(-t / tau))
    else:
        peak = gen.uniform(0.4, 0.6) * dur
        T = 20.0 + dTmax * np.where(t < peak, t / peak, (dur - t) / (dur - peak))
    T = T + gen.normal(scale=0.01, size=n)
    dT = T - T.mean()
    th = (t - t.mean()) / 3600.0
    # Nuisance calibration.
    s = 1.0 + gen.normal(scale=0.02, size=3)
    m = gen.normal(scale=2e-3, size=3)
    b = gen.normal(scale=0.05, size=3)
    K = np.array([[s[0], 0, 0], [m[0], s[1], 0], [m[1], m[2], s[2]]])
    g_true = g
    hidden: dict[str, Any] = {}
    if "upper_coupling" in names:
        up = gen.normal(scale=2e-3, size=3)
        K = K + np.array([[0, up[0], up[1]], [0, 0, up[2]], [0, 0, 0]])
        hidden["upper_coupling"] = up
    a = g_true * dirs
    z = a @ K.T
    clean = z + b
    c = s * g
    step = np.zeros((n, 3))
    step[1:] = clean[:-1] - clean[1:]
    amps = list(amplitudes) if amplitudes is not None else [
        float(np.exp(gen.uniform(np.log(amp_range[0]), np.log(amp_range[1])))) for _ in names]
    if len(amps) != len(names):
        raise CalibrationError("amplitudes must have one value per effect")
    total = np.zeros((n, 3))
    each: dict[str, NDArray[np.float64]] = {}
    amp_out: dict[str, float] = {}
    for nm, A in zip(names, amps, strict=True):
        amp_out[nm] = float(A)
        if nm in DICTIONARY_EFFECTS:
            p = gen.normal(size=3)
            p /= np.linalg.norm(p)
            term = _terms(nm, p, z, c, dT, th, step)
            rms = np.sqrt(np.mean(np.sum(term**2, axis=1)))
            p = p * (A * sigma / rms)
            hidden[nm] = p
            each[nm] = _terms(nm, p, z, c, dT, th, step)
        elif nm == "bias_random_walk":
            w = np.cumsum(gen.normal(size=(n, 3)), axis=0)
            w -= w.mean(axis=0)
            w *= A * sigma / np.sqrt(np.mean(np.sum(w**2, axis=1)))
            hidden[nm] = "random walk"
            each[nm] = w
        elif nm == "wrong_g":
            hidden[nm] = A * sigma / g
            each[nm] = z * (A * sigma / g)
    for v in each.values():
        total += v
    clean_eff = clean + total
    count = np.full(n, int(round(dwell_s * fs)), dtype=np.int64)
    var = np.full((n, 3), sigma**2 * count[0])
    mean = clean_eff + gen.normal(scale=sigma * noise_scale, size=(n, 3))
    sig = np.full((n, 3), sigma)
    tmp = T if temperature else None
    lam = signal_strength(clean_eff, sig, g, t, tmp) if names else 0.0
    lam_each = ({nm: signal_strength(clean + v, sig, g, t, tmp) for nm, v in each.items()}
                if len(each) > 1 else ({names[0]: lam} if names else {}))
    d = DwellSet(mean, var, count, t, tmp, fs=fs, units="m/s^2")
    return GapSession(
        dwells=d, g=g, effects=hidden, amplitude_sigma=amp_out, lam=lam, lam_each=lam_each,
        schedule=schedule, poses=poses, nuisance=np.concatenate([s, b, m]), sigma=sigma,
        noise_scale=noise_scale, meta={"T": T, "dirs": dirs},
    )
