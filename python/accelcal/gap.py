"""Sim-to-real gap diagnosis of a static norm-observation session (numerics in Rust).

"Sim" is what the fitted calibration model plus its noise model predicts; "real" is the
recorded session. :func:`diagnose` measures the gap (chi2, held-out gap), locates it (dwells,
axes, time, temperature), attributes it to an effect of a dictionary (temperature bias and
scale, drift, K2, K3, settling), says which effects this session cannot see at all, and how far
the held-out gap shrinks once the chosen effect is in the model (selection redone inside every
leave-one-dwell-out fold); an effect that improves the in-sample fit but does not lower the
held-out gap is reported as "not_confirmed", not as the explanation. See GAP-DESIGN.md for the
method; :mod:`accelcal.gap_systems` applies it to the centrifuge and the gradiometer.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from statistics import NormalDist
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._core import CalibrationError
from .dwell import DwellSet, detect_dwells

__all__ = ["EFFECTS", "GapReport", "allan_deviation", "diagnose", "noise_inflation"]

#: The static effect dictionary, with the unit of each effect's per-axis parameters.
EFFECTS: dict[str, str] = {
    "temperature_bias": "ug/K",
    "temperature_scale": "ppm/K",
    "drift": "ug/h",
    "k2": "ug/g^2",
    "k3": "ug/g^3",
    "settling": "ppm of step",
}

_DESIGN_FIX = {
    "temperature_bias": "vary the temperature independently of pose and time (heat, then cool)",
    "temperature_scale": "vary the temperature while revisiting poses on both sides of each axis",
    "drift": "revisit early poses at the end of the session (time-symmetric schedule)",
    "k2": "add poses between the axes (tilts of 35-55 deg), not only axis-aligned ones",
    "k3": "add poses between the axes (tilts of 35-55 deg), not only axis-aligned ones",
    "settling": "randomise the pose order so that step sizes vary",
}

_SEPARATING = {
    frozenset({"temperature_bias", "drift"}): "a heat-then-cool temperature profile (temperature "
    "not monotone in time) separates temperature from drift",
    frozenset({"temperature_scale", "drift"}): "a heat-then-cool temperature profile separates "
    "temperature from drift",
    frozenset({"temperature_bias", "temperature_scale"}): "poses at +1 g and -1 g on each axis "
    "at each temperature separate a bias from a scale change",
    frozenset({"temperature_scale", "k3"}): "random pose order (pose not tied to temperature), or "
    "repeating the poses at constant temperature, separates temperature scale from K3",
    frozenset({"temperature_scale", "k2"}): "random pose order (pose not tied to temperature) "
    "separates temperature scale from K2",
    frozenset({"temperature_bias", "k2"}): "random pose order separates temperature bias from K2",
    frozenset({"k2", "k3"}): "poses covering both signs of every axis at intermediate tilts "
    "separate K2 (even) from K3 (odd)",
    frozenset({"drift", "settling"}): "random pose order with large and small pose changes "
    "separates settling from drift",
}
_GENERIC_SEPARATION = (
    "repeat the poses in random order with a non-monotone (heat-then-cool) temperature profile"
)


def _wilson_hilferty_sf(x: float, k: float) -> float:
    """chi2(k) survival function (Wilson-Hilferty approximation; localisation tables only)."""
    if k <= 0 or not math.isfinite(x):
        return float("nan")
    if x <= 0:
        return 1.0
    z = ((x / k) ** (1 / 3) - (1 - 2 / (9 * k))) / math.sqrt(2 / (9 * k))
    return 1.0 - NormalDist().cdf(z)


def _corr_p(x: NDArray[np.float64], y: NDArray[np.float64]) -> tuple[float, float]:
    """Pearson correlation and its two-sided p-value (Fisher z)."""
    n = x.size
    if n < 4 or np.std(x) == 0 or np.std(y) == 0:
        return float("nan"), float("nan")
    r = float(np.corrcoef(x, y)[0, 1])
    r = max(min(r, 0.999999), -0.999999)
    z = math.atanh(r) * math.sqrt(n - 3)
    return r, 2.0 * (1.0 - NormalDist().cdf(abs(z)))


# ----------------------------------------------------------------------------------------------
# Allan deviation of within-dwell samples.


def allan_deviation(
    x: ArrayLike, fs: float, m: ArrayLike | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Overlapping Allan deviation of a (N,) or (N, c) series.

    Parameters
    ----------
    x : (N,) or (N, c) samples (any unit).
    fs : sample rate, Hz.
    m : cluster sizes in samples (default: octaves 1, 2, 4, ... up to N // 3).

    Returns
    -------
    tau : (j,) averaging times, s.
    adev : (j,) or (j, c) Allan deviation, the unit of ``x``.
    """
    a = np.asarray(x, dtype=np.float64)
    one = a.ndim == 1
    a2 = a.reshape(a.shape[0], -1)
    n = a2.shape[0]
    if n < 3:
        raise CalibrationError("Allan deviation needs at least 3 samples")
    if m is None:
        mm = 2 ** np.arange(int(np.floor(np.log2(max(n // 3, 1)))) + 1)
    else:
        mm = np.asarray(m, dtype=np.int64).reshape(-1)
    mm = mm[(mm >= 1) & (2 * mm < n)]
    c = np.vstack([np.zeros((1, a2.shape[1])), np.cumsum(a2 - a2.mean(axis=0), axis=0)])
    out = np.empty((mm.size, a2.shape[1]))
    for j, k in enumerate(mm):
        avg = (c[k:] - c[:-k]) / k
        d = avg[k:] - avg[:-k]
        out[j] = np.sqrt(0.5 * np.mean(d * d, axis=0))
    tau = mm / float(fs)
    return tau, (out[:, 0] if one else out)


def noise_inflation(samples: ArrayLike, dwells: DwellSet, fs: float) -> NDArray[np.float64]:
    """Factor by which each dwell mean's noise exceeds white noise, per dwell and axis.

    For every dwell the overlapping Allan deviation of its samples at cluster sizes L/16 and
    L/4 (L = dwell length) is compared with white noise of the same per-sample deviation
    (ADEV at one sample); the ratio is extrapolated to tau = L with the log-log slope between
    those two points (clipped to [0, 1]). Per axis, the median over dwells is used for every
    dwell (a single dwell's ratio is noisy). Returns (k, 3), >= 1 where noise is correlated.
    """
    a = np.asarray(samples)
    if dwells.start is None or dwells.stop is None:
        raise CalibrationError("noise_inflation needs dwell start/stop indices")
    ratios = []
    for s0, s1 in zip(dwells.start, dwells.stop, strict=True):
        seg = a[int(s0) : int(s1)].astype(np.float64)
        L = seg.shape[0]
        if L < 64:
            continue
        m16, m4 = max(L // 16, 2), max(L // 4, 4)
        _, ad = allan_deviation(seg, fs, [1, m16, m4])
        if ad.shape[0] < 3:
            continue
        s1w = np.maximum(ad[0], 1e-300)
        r16 = ad[1] * math.sqrt(m16) / s1w
        r4 = ad[2] * math.sqrt(m4) / s1w
        slope = np.clip(np.log(np.maximum(r4, 1e-12) / np.maximum(r16, 1e-12)) / math.log(m4 / m16),
                        0.0, 1.0)
        ratios.append(r4 * (L / m4) ** slope)
    k = len(dwells)
    if not ratios:
        return np.ones((k, 3))
    f = np.maximum(np.median(np.array(ratios), axis=0), 1.0)
    return np.tile(f, (k, 1))


# ----------------------------------------------------------------------------------------------
# Report.


@dataclass
class GapReport:
    """Result of :func:`diagnose` (residuals in m/s^2 and in sigma units).

    Attributes
    ----------
    chi2, dof, chi2_per_dof, p_value : the global gap of the baseline fit (p is NaN when the
        noise model is unknown).
    noise_model : description of the per-dwell noise used.
    held_out_gap : leave-one-dwell-out gap G of the baseline (1 for an adequate model).
    dwells : per-row table (dict of (k,) arrays): index, resid and resid_after (in
        ``units``), e, t_stud, flag, e_after, z_loo_before, z_loo_after; static sessions add
        t, temperature, pose_angle_deg and the aliases resid_mps2, resid_after_mps2 (one row
        per dwell); the centrifuge adds omega (one row per position and speed); the
        gradiometer azimuth_deg and channel (two rows per azimuth dwell).
    where : localisation: flagged dwells, axes, time segments, temperature, serial correlation.
    best : "temperature_bias", "temperature_scale", "drift", "k2", "k3", "settling" or "none".
    selected : all effects added (forward stepwise), in order.
    effects : ranked candidates: effect, status ("selected", "not_confirmed" = selected
        in-sample but rejected by the held-out gate, "testable", "blind", ...), p_value (the
        attribution test, named in ``test``: "chi2" or "F"), p_f, p_chi2, bic_weight, estimate
        and std per axis (physical units), unit, sines (identifiability).
    ambiguous : aliased sets with the experiment that separates them.
    blind_spots : effects this session cannot see (never "no effect"), with the reason.
    shrink : G_after / G_before (held out, selection redone in each fold).
    held_out_gap_after, excess_remaining : held-out figures.
    rms_before, rms_after : held-out RMS of the residual before and after, in ``units``
        (m/s^2 for static sessions, g for the centrifuge, E for the gradiometer).
        ``rms_before_mps2`` / ``rms_after_mps2`` are aliases for static sessions only.
    remaining : chi2, dof and p-value after the chosen effects.
    statements : plain-language findings (bad input, not testable, unexplained remainder).
    system : "static", "centrifuge" or "gradiometer".
    """

    n: int
    g: float
    chi2: float
    dof: int
    chi2_per_dof: float
    p_value: float
    noise_model: str
    held_out_gap: float
    dwells: dict[str, NDArray[Any]]
    where: dict[str, Any]
    best: str
    selected: list[str]
    effects: list[dict[str, Any]]
    ambiguous: list[dict[str, Any]]
    blind_spots: list[dict[str, str]]
    shrink: float
    held_out_gap_after: float
    excess_remaining: float
    rms_before: float
    rms_after: float
    remaining: dict[str, float]
    statements: list[str]
    params: NDArray[np.float64]
    params_after: NDArray[np.float64]
    std_after: NDArray[np.float64]
    alpha: float
    system: str = "static"
    units: str = "m/s^2"
    raw: dict[str, Any] = field(repr=False, default_factory=dict)

    @property
    def rms_before_mps2(self) -> float:
        """Alias of ``rms_before`` for static sessions (m/s^2)."""
        return self._mps2(self.rms_before, "rms_before")

    @property
    def rms_after_mps2(self) -> float:
        """Alias of ``rms_after`` for static sessions (m/s^2)."""
        return self._mps2(self.rms_after, "rms_after")

    def _mps2(self, v: float, name: str) -> float:
        if self.units != "m/s^2":
            raise AttributeError(f"{name}_mps2 exists for static sessions only; this "
                                 f"{self.system} report holds {name} in {self.units}")
        return v

    # -- text ---------------------------------------------------------------------------------
    def summary(self) -> str:
        """A plain-text report."""
        L = []
        p = "n/a (noise unknown)" if not math.isfinite(self.p_value) else f"{self.p_value:.2g}"
        L.append(
            f"Gap: chi2/dof = {self.chi2_per_dof:.2f} ({self.chi2:.1f} on {self.dof} dof, "
            f"p = {p}); held-out gap G = {self.held_out_gap:.2f} (1 = adequate)"
        )
        L.append(f"Noise model: {self.noise_model}")
        w = self.where
        fl = w.get("flagged", [])
        row, ax_lab, seg_lab = {
            "centrifuge": ("row(s) (position x speed)", "by axis", "by speed (omega, rad/s)"),
            "gradiometer": ("residual(s) (2 per azimuth dwell: inline, cross)", "by channel",
                            "by group"),
        }.get(self.system, ("dwell(s)", "by pose axis", "by time third"))
        L.append(
            "Where: "
            + (f"{len(fl)} {row} beyond the Bonferroni limit {w['threshold']:.2f}: {fl}"
               if fl else f"no single {row.split('(s)')[0]} beyond the Bonferroni limit "
               f"{w['threshold']:.2f}")
        )
        ax = w.get("axes", [])
        if ax:
            L.append(f"  {ax_lab}: " + "; ".join(
                f"{a['axis']}: {a['n']} {'dwells' if self.system == 'static' else 'rows'}, "
                f"mean e^2 {a['mean_e2']:.2f}" for a in ax))
        seg = w.get("segments", [])
        if seg:
            L.append(f"  {seg_lab}: " + "; ".join(
                f"{s['segment']}: mean e^2 {s['mean_e2']:.2f}" for s in seg))
        sc = w.get("serial")
        if sc:
            L.append(f"  serial correlation (time order): lag-1 r = {sc['r1']:.2f} "
                     f"(p = {sc['p']:.2g}), Durbin-Watson {sc['durbin_watson']:.2f}")
        tc = w.get("temperature")
        if tc:
            L.append(f"  vs temperature: r = {tc['r_T']:.2f} (p = {tc['p_T']:.2g}); vs dT/dt: "
                     f"r = {tc['r_dTdt']:.2f} (p = {tc['p_dTdt']:.2g})")
        L.append(f"Which effect: best = {self.best}"
                 + (f" (selected in order: {', '.join(self.selected)})" if self.selected else ""))
        L.append(f"  {'effect':<18} {'status':<20} {'p':>9} {'test':>4} {'BIC w':>6}  "
                 "estimate +- std")
        for e in self.effects:
            pv = e["p_value"]
            est = e["estimate"]
            if (e["status"] in ("testable", "selected", "not_confirmed")
                    and np.all(np.isfinite(est))):
                pairs = zip(est, e["std"], strict=True)
                mag = ", ".join(f"{v:.3g}+-{s:.2g}" for v, s in pairs) + f" {e['unit']}"
            else:
                mag = "-"
            pvs = f"{pv:9.2g}" if math.isfinite(pv) else f"{'-':>9}"
            bw = f"{e['bic_weight']:6.2f}" if math.isfinite(e["bic_weight"]) else f"{'-':>6}"
            ts = e.get("test", "-") if math.isfinite(pv) else "-"
            L.append(f"  {e['effect']:<18} {e['status']:<20} {pvs} {ts:>4} {bw}  {mag}")
        wn = self.raw.get("weight_none", float("nan"))
        L.append(f"  {'none':<18} {'':<20} {'':>9} {'':>4} {wn:6.2f}")
        for a in self.ambiguous:
            L.append(f"Ambiguous: {' / '.join(a['effects'])} (cosine {a['cosine']:.2f}); "
                     f"to separate them: {a['experiment']}")
        for b in self.blind_spots:
            L.append(f"Blind spot: {b['effect']}: {b['reason']}")
        L.append(
            f"How far it shrinks: held-out G {self.held_out_gap:.2f} -> "
            f"{self.held_out_gap_after:.2f} (shrink {self.shrink:.2f}, excess remaining "
            f"{self.excess_remaining:.2f}); held-out RMS {self.rms_before:.3g} -> "
            f"{self.rms_after:.3g} {self.units}"
        )
        for s in self.statements:
            L.append(f"Note: {s}")
        return "\n".join(L)

    def __str__(self) -> str:
        return self.summary()

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (arrays as lists, NaN kept as float NaN)."""

        def conv(v: Any) -> Any:
            if isinstance(v, np.ndarray):
                return v.tolist()
            if isinstance(v, dict):
                return {k: conv(x) for k, x in v.items()}
            if isinstance(v, (list, tuple)):
                return [conv(x) for x in v]
            if isinstance(v, np.generic):
                return v.item()
            return v

        out = {k: conv(getattr(self, k)) for k in self.__dataclass_fields__ if k != "raw"}
        return out

    # -- figures ------------------------------------------------------------------------------
    def plot(self, fig: Any = None) -> Any:
        """Residuals (sigma units) against time, temperature and pose, before and after.

        Needs matplotlib (``pip install accelcal[plot]``). Returns the figure.
        """
        try:
            import matplotlib.pyplot as plt
        except ImportError as exc:  # pragma: no cover - optional dependency
            raise CalibrationError("plot() needs matplotlib: pip install accelcal[plot]") from exc
        d = self.dwells
        if "pose_angle_deg" not in d:  # centrifuge / gradiometer: residuals by row
            if fig is None:
                fig = plt.figure(figsize=(7, 3.4))
            ax = fig.subplots(1, 1)
            x = np.arange(len(d["e"]))
            ax.plot(x, d["e"], "o", ms=4, label="baseline")
            ax.plot(x, d["e_after"], "x", ms=5, label=f"+ {', '.join(self.selected) or 'none'}")
            ax.axhline(0, color="k", lw=0.5)
            ax.set_xlabel("row")
            ax.set_ylabel("residual / sigma")
            ax.legend(fontsize=8)
            fig.suptitle(f"{self.system} gap: chi2/dof {self.chi2_per_dof:.2f}; best = {self.best}")
            fig.tight_layout()
            return fig
        if fig is None:
            fig = plt.figure(figsize=(11, 3.4))
        axs = fig.subplots(1, 3, sharey=True)
        t = d["t"] if d["t"] is not None else np.arange(self.n, dtype=float)
        has_t = d["t"] is not None
        xs: list[tuple[Any, str]] = [(t / 60.0 if has_t else t,
                                      "time, min" if has_t else "dwell")]
        xs.append((d["temperature"], "temperature") if d["temperature"] is not None else (None, ""))
        xs.append((d["pose_angle_deg"], "angle of the z axis from vertical, deg"))
        for axis, (x, lab) in zip(axs, xs, strict=True):
            if x is None:
                axis.text(0.5, 0.5, "no temperature recorded", ha="center",
                          transform=axis.transAxes)
                axis.set_axis_off()
                continue
            axis.plot(x, d["e"], "o", ms=4, label="baseline")
            axis.plot(x, d["e_after"], "x", ms=5, label=f"+ {', '.join(self.selected) or 'none'}")
            axis.axhline(0, color="k", lw=0.5)
            for s in (-2, 2):
                axis.axhline(s, color="grey", lw=0.5, ls=":")
            axis.set_xlabel(lab)
        axs[0].set_ylabel("norm residual / sigma")
        axs[0].legend(fontsize=8)
        fig.suptitle(f"gap: chi2/dof {self.chi2_per_dof:.2f}, held-out G {self.held_out_gap:.2f}"
                     f" -> {self.held_out_gap_after:.2f}; best = {self.best}")
        fig.tight_layout()
        return fig


# ----------------------------------------------------------------------------------------------
# The diagnosis.


def _effect_list(effects: str | Sequence[str]) -> list[str]:
    if isinstance(effects, str):
        if effects == "all":
            return list(EFFECTS)
        effects = [effects]
    out = []
    for e in effects:
        if e not in EFFECTS:
            raise CalibrationError(f"unknown effect {e!r}; known: {', '.join(EFFECTS)}")
        out.append(e)
    return out


def _start_from(fit: Any) -> list[float] | None:
    if fit is None:
        return None
    p = getattr(fit, "params", fit)
    v = np.asarray(p, dtype=np.float64).reshape(-1)
    if v.size != 9 or not np.all(np.isfinite(v)):
        raise CalibrationError("fit must be a StaticFit or [sx,sy,sz,bx,by,bz,m1,m2,m3]")
    return [float(x) for x in v]


def diagnose(
    data: DwellSet | ArrayLike,
    *,
    g: float,
    fit: Any = None,
    effects: str | Sequence[str] = "all",
    alpha: float = 0.05,
    fs: float | None = None,
    noise: ArrayLike | None = None,
    loo: bool = True,
    max_effects: int = 3,
    test: str = "auto",
    gate: str = "auto",
    trust_level: float | None = None,
    correction: str = "minp",
    n_draws: int = 4000,
    gate_margin: float | None = None,
    preset: str = "targeted",
    t: ArrayLike | None = None,
    temperature: ArrayLike | None = None,
) -> GapReport:
    """Diagnose the sim-to-real gap of a static session.

    Parameters
    ----------
    data : DwellSet (dwell means in raw units, with ``var`` and ``count`` for the noise model,
        ``t`` in s and, when recorded, ``temperature``), or a raw (N, 3) sample stream (then
        ``fs`` is required: dwells are detected and the noise of each dwell mean comes from the
        Allan deviation of its samples, see :func:`noise_inflation`).
    g : local gravity, m/s^2.
    fit : optional StaticFit (or its 9 parameters) used as the start instead of the exact
        linear quadric fit.
    effects : "all" or a list of effect names (see :data:`EFFECTS`).
    alpha : family-wise false-alarm level of the attribution over the testable candidates of
        each stepwise stage (see ``correction``).
    fs : sample rate, Hz (raw streams).
    noise : optional std of each dwell mean, (k, 3) or (3,), raw units; overrides var/count.
    loo : compute the leave-one-dwell-out held-out gap (the "how far it shrinks" figures).
    max_effects : at most this many effects are added.
    test : attribution test: "auto" (chi2 score test when the noise model is known and what
        remains after the candidate is consistent with it, upper-tail p > 0.1; the sigma-free F
        test otherwise), "chi2" or "f".
    gate : held-out gate. "strict": an effect selected in-sample is reported as the
        explanation only if it lowers the leave-one-dwell-out gap (selection redone in every
        fold); otherwise it is listed with status "not_confirmed" and the selection stops
        there. "auto" (default): the same, except that an effect after which the remaining
        chi2 is consistent with the known noise model (p >= alpha) is kept (the held-out gap
        is too noisy to confirm weak effects). "off": no held-out check. Needs ``loo=True``.
    trust_level : with ``test="auto"``, the upper-tail p-value of the remaining chi2 above
        which the noise model is trusted (chi2 test) for a candidate.
    correction : family-wise correction over the candidates. "minp" (default): exact min-p
        (Westfall-Young max-statistic) - the adjusted p-value of the best candidate is the
        probability that the smallest p-value over the candidates, computed on the null
        residual ``(I - H) z`` with ``z ~ N(0, I)`` (each candidate keeping the chi2 or F
        test chosen on the data), is at most the observed one; Monte Carlo with fixed-seed
        draws, so results are reproducible, and never above the Bonferroni bound. It gains
        power over "bonferroni" (``p < alpha / M``) because the candidates' projected
        columns are correlated.
    n_draws : at most this many null draws per min-p decision (sequential: fewer when the
        decision is clear; Monte Carlo error of the adjusted p near alpha = 0.05 about 0.0035
        at 4000).
    gate_margin : with ``gate="auto"``, an effect after which the remainder is consistent
        in-sample is also kept when the held-out ``G^2`` grows by at most ``gate_margin *
        sqrt(2/n)`` (a gentler gate: more weak effects confirmed, but more attributions
        under a mis-scaled noise model; see docs/gap-validation.md).
    preset : defaults of ``trust_level`` / ``gate_margin`` when they are not given.
        "targeted" (default; 0.02 / 1.0): the setting validated to meet the issue's targets
        (false alarms <= 5 %, top-1 >= 99 % at lambda >= 30 and >= 80 % at lambda 10-30 with a
        designed schedule); when the reported noise is 1.5x too small it attributes an effect
        in about 21 % of effect-free sessions (the summary then also reports a remaining
        gap). "conservative" (0.1 / 0.0): about 12 % in that case, at the price of about 75 %
        top-1 for weak effects. Use "conservative" when the noise model is in doubt.
    t, temperature : with a raw sample stream, per-sample time (s) and temperature, (N,)
        each, passed to :func:`accelcal.detect_dwells` (dwell mid time and mean temperature;
        the temperature effects are testable on the raw path only with ``temperature``).
        Not allowed with a DwellSet, which carries its own.

    Returns
    -------
    GapReport
    """
    presets = {"targeted": (0.02, 1.0), "conservative": (0.1, 0.0)}
    if preset not in presets:
        raise CalibrationError(f"preset must be one of {sorted(presets)}; got {preset!r}")
    if trust_level is None:
        trust_level = presets[preset][0]
    if gate_margin is None:
        gate_margin = presets[preset][1]
    eff = _effect_list(effects)
    inflation = None
    if isinstance(data, DwellSet):
        if t is not None or temperature is not None:
            raise CalibrationError("t= and temperature= are per-sample arrays for a raw stream; "
                                   "a DwellSet carries its own t and temperature")
        d = data
    else:
        if fs is None:
            raise CalibrationError("raw samples need fs (Hz); or pass a DwellSet")
        samples = np.asarray(data)
        d = detect_dwells(samples, fs, t=t, temperature=temperature)
        if len(d) == 0:
            raise CalibrationError("no static dwells detected in the stream")
        inflation = noise_inflation(samples, d, fs)
    k = len(d)
    order = np.arange(k)
    if d.t is not None and np.any(np.diff(d.t) < 0):
        order = np.argsort(d.t, kind="stable")
    mean = np.ascontiguousarray(d.mean[order], dtype=np.float64)
    t = None if d.t is None else np.ascontiguousarray(d.t[order], dtype=np.float64)
    temp = (None if d.temperature is None
            else np.ascontiguousarray(d.temperature[order], dtype=np.float64))
    statements: list[str] = []
    if noise is not None:
        nz = np.asarray(noise, dtype=np.float64)
        sig = np.broadcast_to(nz.reshape(-1, 3) if nz.size != 3 else nz.reshape(1, 3), (k, 3))
        sig = np.ascontiguousarray(sig[order] if sig.shape[0] == k and nz.size != 3 else sig)
        noise_model = "given std of each dwell mean"
    elif d.var is not None and d.count is not None:
        sig = np.sqrt(d.var[order] / d.count[order, None])
        noise_model = "white noise: sqrt(var / count) of each dwell"
        if inflation is not None:
            sig = sig * inflation[order]
            noise_model = ("Allan deviation of the within-dwell samples at tau = dwell length "
                           f"(inflation over white noise x/y/z "
                           f"{', '.join(f'{v:.2f}' for v in inflation[0])})")
        if np.any(sig <= 0):
            bad = np.where(np.any(sig <= 0, axis=1))[0]
            raise CalibrationError(f"dwell(s) {order[bad].tolist()} have zero variance: the noise "
                                   "model needs var > 0 (quantised constant output?)")
    else:
        sig = None
        noise_model = ("unknown (no var/count): unit weights scaled to the baseline fit; the "
                       "absolute gap is not testable, attribution uses sigma-free F tests")
        statements.append("no per-dwell variance given: chi2 gap not testable (F tests only)")
    if k < 10:
        raise _core.DegenerateDataError(
            f"{k} dwells: the 9-parameter model needs at least 10 dwells for any gap test"
        )
    r = _core.gap_diagnose_raw(
        mean, None if sig is None else np.ascontiguousarray(sig, dtype=np.float64), t, temp,
        float(g), eff, alpha=float(alpha), max_effects=int(max_effects), loo=bool(loo),
        start=_start_from(fit), test=str(test), gate=str(gate),
        trust_level=float(trust_level), correction=str(correction), n_draws=int(n_draws),
        gate_margin=float(gate_margin),
    )
    return _build_report(r, d, order, mean, t, temp, float(g), noise_model, statements, alpha)


def _build_report(
    r: dict[str, Any],
    d: DwellSet,
    order: NDArray[np.int64],
    mean: NDArray[np.float64],
    t: NDArray[np.float64] | None,
    temp: NDArray[np.float64] | None,
    g: float,
    noise_model: str,
    statements: list[str],
    alpha: float,
) -> GapReport:
    n = int(r["n"])
    e = np.asarray(r["e"])
    h = np.clip(np.asarray(r["leverage"]), 0.0, 0.999999)
    t_stud = e / np.sqrt(1.0 - h)
    thr = NormalDist().inv_cdf(1.0 - alpha / (2 * n))
    flag = np.abs(t_stud) > thr
    p = np.asarray(r["base_params"])
    K = np.array([[p[0], 0, 0], [p[6], p[1], 0], [p[7], p[8], p[2]]])
    a = np.linalg.solve(K, (mean - p[3:6]).T).T
    u = a / np.linalg.norm(a, axis=1, keepdims=True)
    loo = r["loo"]
    nan = np.full(n, np.nan)
    dw = {
        "index": order.astype(np.int64),
        "t": t,
        "temperature": temp,
        "resid": np.asarray(r["resid"]),
        "resid_mps2": np.asarray(r["resid"]),
        "e": e,
        "t_stud": t_stud,
        "flag": flag,
        "resid_after": np.asarray(r["resid_after"]),
        "resid_after_mps2": np.asarray(r["resid_after"]),
        "e_after": np.asarray(r["e_after"]),
        "z_loo_before": np.asarray(loo["z_before"]) if loo else nan,
        "z_loo_after": np.asarray(loo["z_after"]) if loo else nan,
        "pose_angle_deg": np.degrees(np.arccos(np.clip(u[:, 2], -1, 1))),
    }
    noise_known = bool(r["noise_known"])
    where: dict[str, Any] = {"threshold": thr, "flagged": order[flag].tolist()}
    dom = np.argmax(np.abs(u), axis=1)
    axes = []
    for i, nm in enumerate("xyz"):
        sel = dom == i
        if sel.any():
            s2 = float(np.sum(e[sel] ** 2))
            axes.append({"axis": nm, "n": int(sel.sum()), "mean_e2": s2 / sel.sum(),
                         "p": _wilson_hilferty_sf(s2, float(sel.sum())) if noise_known
                         else float("nan")})
    where["axes"] = axes
    segs = []
    for j, part in enumerate(np.array_split(np.arange(n), 3)):
        if part.size:
            s2 = float(np.sum(e[part] ** 2))
            segs.append({"segment": ("early", "middle", "late")[j], "n": int(part.size),
                         "mean_e2": s2 / part.size,
                         "p": _wilson_hilferty_sf(s2, float(part.size)) if noise_known
                         else float("nan")})
    where["segments"] = segs
    if n >= 4:
        r1, p1 = _corr_p(e[:-1], e[1:])
        where["serial"] = {"r1": r1, "p": p1,
                           "durbin_watson": float(np.sum(np.diff(e) ** 2)
                                                  / max(np.sum(e**2), 1e-300))}
    if temp is not None and np.ptp(temp) > 0:
        rT, pT = _corr_p(temp, e)
        tt = t if t is not None else np.arange(n, dtype=float)
        dTdt = np.gradient(temp, tt) if np.all(np.diff(tt) > 0) else np.gradient(temp)
        rd, pd = _corr_p(dTdt, e)
        where["temperature"] = {"r_T": rT, "p_T": pT, "r_dTdt": rd, "p_dTdt": pd}

    selected = list(r["selected"])
    effects = []
    blind = [
        {"effect": "wrong_g", "reason": "a wrong gravity reference g(1+delta) is absorbed by the "
         "common scale factor: no static norm session can see it; check g against an absolute "
         "gravity value"},
        {"effect": "upper_coupling", "reason": "coupling beyond the lower-triangular K is a "
         "rotation of the sensor frame, invisible to |a|; it needs an external attitude reference"},
    ]
    for c in r["candidates"]:
        st = c["status"]
        row = {
            "effect": c["effect"], "unit": c["unit"],
            "status": "selected" if c["effect"] in selected else st,
            "p_value": c["p"], "test": "chi2" if c["chi2_used"] else "F", "p_f": c["p_f"],
            "p_chi2": c["p_chi2"] if noise_known else float("nan"),
            "bic_weight": c["weight"], "score": c["score"], "d": c["d"],
            "estimate": np.asarray(c["estimate"]), "std": np.asarray(c["std"]),
            "sines": list(c["sines"]),
        }
        effects.append(row)
        nm = c["effect"]
        if st == "blind":
            blind.append({"effect": nm, "reason": "every direction of it is absorbed by the "
                          "calibration parameters (principal-angle sines "
                          f"{', '.join(f'{s:.3f}' for s in c['sines']) or 'n/a'} < 0.05): not "
                          f"testable with these poses, NOT evidence of absence; to expose it: "
                          f"{_DESIGN_FIX[nm]}"})
        elif st == "no_temperature":
            blind.append({"effect": nm, "reason": "not testable: no temperature was recorded "
                          "(this is not 'no effect'); record the temperature of every dwell"})
        elif st == "constant_temperature":
            rng = float(np.ptp(temp)) if temp is not None else 0.0
            blind.append({"effect": nm, "reason": f"not testable: temperature constant (range "
                          f"{rng:.3g}); heat or cool the sensor between dwells to test it"})
        elif st == "no_time":
            blind.append({"effect": nm, "reason": "not testable: no dwell times were given"})
        elif st == "too_few_dwells":
            blind.append({"effect": nm, "reason": f"not testable: too few dwells ({n}); a "
                          "3-parameter effect needs at least 13 (9 + 3 + 1)"})
    if all(e_["status"] == "too_few_dwells" for e_ in effects if e_["status"] not in
           ("blind", "no_temperature", "constant_temperature", "no_time")) and effects:
        statements.append(f"too few dwells ({n}) for any effect test; add dwells")
    effects.sort(key=lambda x: (0 if x["status"] == "selected" else
                                1 if x["status"] == "testable" else 2,
                                x["p_value"] if math.isfinite(x["p_value"]) else 2.0))
    best = selected[0] if selected else "none"
    nc = r["not_confirmed"]
    if nc is not None:
        nm_, p_, ga_, gb_ = nc
        for e_ in effects:
            if e_["effect"] == nm_:
                e_["status"] = "not_confirmed"
        statements.append(
            f"{nm_} improves the in-sample fit (p = {p_:.2g}) but does not reduce the held-out "
            f"gap (G {ga_:.2f} -> {gb_:.2f}): not an explanation")
        effects.sort(key=lambda x: (0 if x["status"] == "selected" else
                                    1 if x["status"] == "not_confirmed" else
                                    2 if x["status"] == "testable" else 3,
                                    x["p_value"] if math.isfinite(x["p_value"]) else 2.0))
    ambiguous = []
    groups: dict[str, list[tuple[str, float]]] = {}
    for a_, b_, cos in r["ambiguous"]:
        groups.setdefault(a_, []).append((b_, cos))
    for a_, lst in groups.items():
        names = [a_] + [b for b, _ in lst]
        exps = [_SEPARATING.get(frozenset({a_, b}), _GENERIC_SEPARATION) for b, _ in lst]
        ambiguous.append({"effects": names, "cosine": max(c for _, c in lst),
                          "experiment": "; ".join(dict.fromkeys(exps))})
    g_b = loo["g_before"] if loo else float("nan")
    g_a = loo["g_after"] if loo else float("nan")
    shrink = g_a / g_b if loo and g_b > 0 else float("nan")
    excess = (g_a - 1.0) / (g_b - 1.0) if loo and g_b > 1.0 else float("nan")
    if not loo:
        statements.append(f"held-out gap not computed ({n} dwells; leave-one-out needs >= 11)")
    if r["gate_skipped"]:
        statements.append(
            f"leave-one-out with {n} dwells is too small to judge {', '.join(selected)} held "
            "out (a fold keeps fewer than 2 residual degrees of freedom): the held-out gate was "
            "skipped, the in-sample test decides; add dwells to confirm it held out")
    if loo and loo["n_failed"]:
        statements.append(f"{loo['n_failed']} leave-one-out fold(s) could not be fitted")
    chi2, dof = float(r["chi2"]), int(r["dof"])
    p_after = float(r["p_after"])
    if noise_known and math.isfinite(r["p_chi2"]) and r["p_chi2"] < alpha:
        if not selected:
            statements.append(
                "the gap is significant but no dictionary effect explains it: correlated noise "
                "(check the Allan deviation of the within-dwell samples), an effect outside the "
                "dictionary (bias random walk, vibration), or a mis-scaled noise model")
        elif math.isfinite(p_after) and p_after < alpha:
            statements.append(
                f"after {', '.join(selected)} a significant gap remains (chi2/dof "
                f"{r['chi2_after'] / max(r['dof_after'], 1):.2f}): no dictionary effect fully "
                "explains it (fall back to a smooth discrepancy over time/temperature)")
    return GapReport(
        n=n, g=g, chi2=chi2, dof=dof, chi2_per_dof=chi2 / dof if dof else float("nan"),
        p_value=float(r["p_chi2"]), noise_model=noise_model, held_out_gap=g_b, dwells=dw,
        where=where, best=best, selected=selected, effects=effects, ambiguous=ambiguous,
        blind_spots=blind, shrink=shrink, held_out_gap_after=g_a, excess_remaining=excess,
        rms_before=loo["rms_before"] if loo else float("nan"),
        rms_after=loo["rms_after"] if loo else float("nan"),
        remaining={"chi2": float(r["chi2_after"]), "dof": float(r["dof_after"]), "p": p_after},
        statements=statements, params=np.asarray(r["base_params"]),
        params_after=np.asarray(r["params_after"]), std_after=np.asarray(r["std_after"]),
        alpha=float(alpha),
        raw={"weight_none": r["weight_none"], "step_p": r["step_p"], "stop_p": r["stop_p"],
             "step_p_adj": r["step_p_adj"], "step_m": r["step_m"],
             "stop_p_adj": r["stop_p_adj"],
             "fold_counts": loo["fold_counts"] if loo else {},
             "g_steps": list(loo["g_steps"]) if loo else [], "not_confirmed": nc},
    )
