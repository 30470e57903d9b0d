"""Withheld-effect session generator for checking the gap diagnosis (dwell-mean level).

:func:`gap_session`: a random nuisance calibration (scale, bias, non-orthogonality), a pose
set and order, a temperature profile, dwell-mean noise, and 0, 1 or 2 hidden effects of random
magnitude, plus optional effects outside the dictionary (bias random walk) and blind-spot
effects (wrong g, upper-triangular coupling). Effect terms follow exactly the definitions of
the static dictionary, so the hidden parameters are in the same physical units (ug/K, ppm/K,
ug/h, ug/g^2, ug/g^3, ppm of step).

:func:`structure_session`: sessions whose gap has a known structure (per-dwell offsets,
correlated noise, attitude pattern, hysteresis, quantisation, time and temperature trends),
with half-dwell means. The diagnoser is given only ``dwells`` and ``g``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .. import _core
from .._core import CalibrationError
from .._triad import fibonacci_sphere
from ..dwell import DwellSet

__all__ = [
    "DICTIONARY_EFFECTS",
    "GapSession",
    "OTHER_EFFECTS",
    "STRUCTURE_CLASSES",
    "gap_session",
    "signal_strength",
    "structure_session",
]

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
    """Output term (k, 3) of a dictionary effect, raw units (the static dictionary's terms)."""
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
        r = _core.gap_diagnose_static(
            np.ascontiguousarray(mean), np.ascontiguousarray(np.asarray(sigma) ** 2), t,
            temperature, float(g), [], _core.GapSettings(loo=False, max_effects=0))
    except CalibrationError:
        return float("nan")
    return float(r.chi2)


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


# ----------------------------------------------------------------------------------------------
# Sessions whose gap has a known structure (for the structure verdict).

#: Simulated structure class -> the verdict the diagnosis should give.
STRUCTURE_CLASSES: dict[str, str] = {
    "per_dwell": "per_dwell",
    "correlated_noise": "noise_model",
    "attitude": "attitude",
    "hysteresis": "pose_history",
    "quantization": "quantization",
    "time": "time",
    "temperature": "temperature",
}


def _monomials34(u: NDArray[np.float64]) -> NDArray[np.float64]:
    """The mixed monomials of degree 3 and 4 of the unit vectors u (n, 19): the pure powers
    u_i^3 and u_i^4 are what the K2 and K3 effects of the dictionary produce."""
    cols = []
    for deg in (3, 4):
        for a in range(deg + 1):
            for b in range(deg + 1 - a):
                c = deg - a - b
                if max(a, b, c) < deg:
                    cols.append(u[:, 0] ** a * u[:, 1] ** b * u[:, 2] ** c)
    return np.column_stack(cols)


def _correlated(gen: np.random.Generator, n_sub: int) -> NDArray[np.float64]:
    """(n_sub,) noise correlated over a fraction of a dwell: an AR(1) ("random-walk bias"
    with a correlation time of 1/32 dwell) plus pink (1/f) noise above 8 cycles per dwell,
    unit RMS."""
    rho = math.exp(-32.0 / n_sub)
    w = gen.normal(size=n_sub)
    ar = np.empty(n_sub)
    ar[0] = w[0]
    for i in range(1, n_sub):
        ar[i] = rho * ar[i - 1] + math.sqrt(1 - rho * rho) * w[i]
    f = np.fft.rfftfreq(n_sub)
    spec = (gen.normal(size=f.size) + 1j * gen.normal(size=f.size))
    spec[f < 8.0 / n_sub] = 0.0
    spec[f > 0] /= np.sqrt(f[f > 0])
    pink = np.fft.irfft(spec, n_sub)
    x = ar / ar.std() + pink / max(pink.std(), 1e-300)
    return x / x.std()


def _structure_terms(kind: str, gen: np.random.Generator, u: NDArray[np.float64],
                     ku: NDArray[np.float64], s_t: NDArray[np.float64],
                     s_T: NDArray[np.float64] | None) -> tuple[NDArray[np.float64],
                                                               NDArray[np.float64]]:
    """Unit-amplitude structure terms in the output (k, 3) for each half (k, 2, 3)."""
    n = u.shape[0]
    if kind == "per_dwell":
        d = gen.normal(size=(n, 3))
        return d, np.stack([d, d], axis=1)
    if kind == "correlated_noise":
        h = np.empty((n, 2, 3))
        for k in range(n):
            for i in range(3):
                x = _correlated(gen, 128)
                h[k, 0, i], h[k, 1, i] = x[:64].mean(), x[64:].mean()
        return h.mean(axis=1), h
    if kind == "attitude":
        f = _monomials34(u) @ gen.normal(size=19)
    elif kind == "hysteresis":
        prev = np.vstack([np.zeros((1, 3)), u[:-1]])
        f = prev @ gen.normal(size=3)
    elif kind in ("time", "temperature"):
        s = s_t if kind == "time" else s_T
        assert s is not None
        v = gen.normal(size=3)
        term = np.outer(1.5 * s * s - 0.5, v / np.linalg.norm(v))
        return term, np.stack([term, term], axis=1)
    else:
        raise CalibrationError(f"unknown structure class {kind!r}; known: "
                               f"{', '.join(STRUCTURE_CLASSES)}")
    term = f[:, None] * ku  # a norm offset f (m/s^2 per unit) along the gravity direction
    return term, np.stack([term, term], axis=1)


def structure_session(
    kind: str,
    *,
    lam: float | None = None,
    lam_range: tuple[float, float] = (30.0, 300.0),
    n_dwells: int = 60,
    sigma: float = 1e-4,
    rng: int | np.random.Generator | None = None,
    g: float = 9.80665,
    dwell_s: float = 60.0,
    move_s: float = 30.0,
    fs: float = 10.0,
) -> GapSession:
    """A static session whose gap has a known structure, with half-dwell means.

    Parameters
    ----------
    kind : a class of :data:`STRUCTURE_CLASSES`: "per_dwell" (persistent random per-axis
        offsets per dwell, as from handling or mounting), "correlated_noise" (noise correlated
        within the dwells: a short-memory random-walk bias and 1/f noise, not in the reported
        white variance), "attitude" (a norm error that is a random polynomial of degree 3-4 of
        the gravity direction), "hysteresis" (a norm error linear in the previous dwell's
        gravity direction), "quantization" (outputs quantised with noise of 0.3 LSB; the dwell
        length sets the strength), "time" (a per-axis bias quadratic in time; no temperature
        recorded), "temperature" (a per-axis bias quadratic in the temperature, which goes
        through two heat-cool cycles).
    lam : signal strength: chi2 the structure leaves after a baseline fit, noise free, in units
        of the reported dwell-mean noise (default: log-uniform over ``lam_range``).
    n_dwells, sigma, rng, g, dwell_s, move_s, fs : as in :func:`gap_session` (random poses in
        random order; reported white noise ``sigma`` per dwell-mean axis).

    Returns
    -------
    GapSession (``effects = {"structure": kind}``, ``meta["verdict"]`` the expected verdict).
    The DwellSet carries ``half_mean`` (k, 2, 3) and, for "quantization", ``lsb`` (3,).
    """
    gen = np.random.default_rng(rng)
    if kind not in STRUCTURE_CLASSES:
        raise CalibrationError(f"unknown structure class {kind!r}; known: "
                               f"{', '.join(STRUCTURE_CLASSES)}")
    n = int(n_dwells)
    target = float(lam) if lam is not None else float(np.exp(gen.uniform(*np.log(lam_range))))
    u = fibonacci_sphere(n) @ _random_rotation(gen).T
    u = u[gen.permutation(n)]
    t = (np.arange(n) * (dwell_s + move_s) + dwell_s / 2).astype(np.float64)
    s_t = 2.0 * (t - t[0]) / (t[-1] - t[0]) - 1.0
    temp = None
    s_T = None
    if kind != "time":
        phase = (t - t[0]) / (t[-1] - t[0]) * (4.0 if kind == "temperature" else 2.0)
        tri = 1.0 - np.abs((phase % 2.0) - 1.0)
        temp = 20.0 + gen.uniform(5.0, 15.0) * tri + gen.normal(scale=0.05, size=n)
        s_T = 2.0 * (temp - temp.min()) / np.ptp(temp) - 1.0
    s = 1.0 + gen.normal(scale=0.02, size=3)
    m = gen.normal(scale=2e-3, size=3)
    b = gen.normal(scale=0.05, size=3)
    K = np.array([[s[0], 0, 0], [m[0], s[1], 0], [m[1], m[2], s[2]]])
    clean = (g * u) @ K.T + b
    ku = u @ K.T
    if kind == "quantization":
        return _quantized_session(gen, u, clean, t, temp, K, b, s, m, g, sigma, target, n, fs)
    term, half_term = _structure_terms(kind, gen, u, ku, s_t, s_T)
    sig = np.full((n, 3), sigma)
    lam1 = signal_strength(clean + term, sig, g, t, temp)
    amp = math.sqrt(target / lam1) if lam1 > 0 else 0.0
    count = int(round(dwell_s * fs))
    halves = clean[:, None, :] + amp * half_term + gen.normal(
        scale=sigma * math.sqrt(2.0), size=(n, 2, 3))
    mean = halves.mean(axis=1)
    d = DwellSet(mean, np.full((n, 3), sigma**2 * count), np.full(n, count), t, temp, fs=fs,
                 units="m/s^2", half_mean=halves)
    lam_real = signal_strength(clean + amp * term, sig, g, t, temp)
    return GapSession(dwells=d, g=g, effects={"structure": kind},
                      amplitude_sigma={kind: amp / sigma}, lam=lam_real,
                      lam_each={kind: lam_real}, schedule="designed", poses="sphere",
                      nuisance=np.concatenate([s, b, m]), sigma=sigma, noise_scale=1.0,
                      meta={"T": temp, "dirs": u, "verdict": STRUCTURE_CLASSES[kind]})


def _quantizer_bias(mu: NDArray[np.float64], sd: float, lsb: float) -> NDArray[np.float64]:
    """Deterministic bias E[round(x / lsb) lsb] - mu of quantised Gaussian samples."""
    from statistics import NormalDist

    nd = NormalDist()
    out = np.empty(mu.size)
    for i, m in enumerate(np.asarray(mu, dtype=np.float64).reshape(-1)):
        k0, k1 = math.floor((m - 8 * sd) / lsb), math.ceil((m + 8 * sd) / lsb)
        e = 0.0
        for k in range(k0, k1 + 1):
            lo, hi = (k - 0.5) * lsb, (k + 0.5) * lsb
            e += k * lsb * (nd.cdf((hi - m) / sd) - nd.cdf((lo - m) / sd))
        out[i] = e - m
    return out


def _quantized_dwells(gen: np.random.Generator, clean: NDArray[np.float64],
                      t: NDArray[np.float64], temp: NDArray[np.float64] | None, g: float,
                      sigma: float, count: int, fs: float) -> tuple[DwellSet, float, float]:
    """Dwells of ``count`` samples with noise 0.3 LSB, quantised; lambda against the reported
    white noise of the mean."""
    n = clean.shape[0]
    sd = sigma * math.sqrt(count)  # per-sample noise so that the dwell-mean noise is sigma
    lsb = sd / 0.3
    mean = np.empty((n, 3))
    var = np.empty((n, 3))
    halves = np.empty((n, 2, 3))
    bias = np.empty((n, 3))
    for k in range(n):
        x = clean[k] + gen.normal(scale=sd, size=(count, 3))
        q = np.round(x / lsb) * lsb
        mean[k] = q.mean(axis=0)
        var[k] = q.var(axis=0, ddof=1)
        halves[k, 0] = q[: count // 2].mean(axis=0)
        halves[k, 1] = q[count // 2 :].mean(axis=0)
        bias[k] = _quantizer_bias(clean[k], sd, lsb)
    # The noise model the diagnosis will use: reported var / count, floored at the
    # quantisation noise LSB^2 / 12 (a dwell whose samples never change has var = 0).
    sig = np.sqrt(np.maximum(var, lsb * lsb / 12.0) / count)
    lam = signal_strength(clean + bias, sig, g, t, temp)
    d = DwellSet(mean, var, np.full(n, count), t, temp, fs=fs, units="m/s^2", half_mean=halves,
                 lsb=np.full(3, lsb))
    return d, lam, lsb


def _quantized_session(gen: np.random.Generator, u: NDArray[np.float64],
                       clean: NDArray[np.float64], t: NDArray[np.float64],
                       temp: NDArray[np.float64] | None, K: NDArray[np.float64],
                       b: NDArray[np.float64], s: NDArray[np.float64], m: NDArray[np.float64],
                       g: float, sigma: float, target: float, n: int, fs: float) -> GapSession:
    """Outputs quantised to steps of LSB with sample noise 0.3 LSB; the number of samples per
    dwell sets the strength (the bias of a dwell mean is fixed, its noise falls as 1/sqrt N).
    The count is set from a first trial so that lambda is near the target."""
    # Bias variance per axis ~ 0.00147 LSB^2 at 0.3 LSB noise; the reported variance of the
    # quantised samples is ~0.173 LSB^2, so lambda is about n N 0.0085.
    count = int(np.clip(round(target / (n * 0.0085)), 16, 20000))
    trial = np.random.default_rng(gen.integers(2**32))
    _, lam1, _ = _quantized_dwells(trial, clean, t, temp, g, sigma, count, fs)
    if math.isfinite(lam1) and lam1 > 0:
        count = int(np.clip(round(count * target / lam1), 16, 20000))
    d, lam, lsb = _quantized_dwells(gen, clean, t, temp, g, sigma, count, fs)
    return GapSession(dwells=d, g=g, effects={"structure": "quantization"},
                      amplitude_sigma={"quantization": lsb / sigma}, lam=lam,
                      lam_each={"quantization": lam}, schedule="designed",
                      poses="sphere", nuisance=np.concatenate([s, b, m]), sigma=sigma,
                      noise_scale=1.0, meta={"T": temp, "dirs": u, "verdict": "quantization",
                                             "lsb": lsb, "count": count})
