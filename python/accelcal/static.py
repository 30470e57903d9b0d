"""Static field calibration by norm observation (seed 000; numerics in Rust).

Sensor model: raw output ``am = K a + b``; calibrated specific force ``a = K^-1 (am - b)``.
At rest ``|a| = g`` whatever the attitude, so dwell means at several attitudes plus a
reference ``g`` determine ``K`` and ``b``.

Parameter vector, always in the seed's order ``[sx, sy, sz, bx, by, bz, m1, m2, m3]``:

- ``model="lower"`` (seed 000): ``K = [[sx, 0, 0], [m1, sy, 0], [m2, m3, sz]]``; ``m1`` is the
  x-input seen by the y output, ``m2`` x seen by z, ``m3`` y seen by z.
- ``model="upper"`` (imu_tk's triangle): ``K = [[sx, m1, m2], [0, sy, m3], [0, 0, sz]]``; ``m1``
  is the y-input seen by the x output, ``m2`` z seen by x, ``m3`` z seen by y.
- ``model="diag"``: ``K = diag(sx, sy, sz)``, first 6 values only.

``K`` is in output units per (m/s^2) (counts per m/s^2 for raw counts), ``b`` in output units;
residuals and calibrated values are in the units of ``g`` (m/s^2).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import warnings
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._core import CalibrationError
from ._files import atomic_write
from ._triad import PARAM_NAMES
from ._triad import k_matrix as _k_matrix
from ._triad import n_params as _n_params
from ._validate import samples_array
from .dwell import DwellSet

__all__ = [
    "PARAM_NAMES",
    "BatchFit",
    "StaticFit",
    "TriadModel",
    "WeakDesignWarning",
    "fit_static",
    "fit_static_batch",
    "local_gravity",
]

_METHODS = ("lm", "gauss-newton", "quadric", "linear-paper")


class WeakDesignWarning(UserWarning):
    """The dwells determine the parameters only weakly (large predicted std)."""




def _check_g(g: Any, check: bool) -> float:
    try:
        gv = float(g)
    except (TypeError, ValueError):
        raise CalibrationError(f"g must be a number (reference gravity); got {g!r}") from None
    if not math.isfinite(gv) or gv <= 0:
        raise CalibrationError(
            f"g must be a positive, finite reference gravity (e.g. 9.81 m/s^2); got {g!r}"
        )
    if check and not (9.7 <= gv <= 9.9 or 0.99 <= gv <= 1.01 or 970.0 <= gv <= 990.0):
        raise CalibrationError(
            f"g = {gv} is not a plausible local gravity: Earth's is 9.78-9.84 m/s^2 "
            "(0.997-1.003 in units of g, 978-983 cm/s^2). Give g in the units the calibrated "
            "output should have, or pass check_g=False for a deliberate other value."
        )
    return gv


def _means_of(data: Any) -> tuple[NDArray[np.float64], DwellSet | None]:
    if isinstance(data, DwellSet):
        return data.mean, data
    m = np.asarray(data, dtype=np.float64)
    if m.ndim != 2 or m.shape[1] != 3:
        raise CalibrationError(f"dwell means must have shape (k, 3); got {np.shape(data)}")
    return m, None


def _noise_var(
    k: int, ds: DwellSet | None, sigma: Any
) -> tuple[NDArray[np.float64] | None, str]:
    if sigma is not None:
        s = np.asarray(sigma, dtype=np.float64)
        if s.ndim == 0:
            s = np.full((k, 3), float(s))
        elif s.shape == (k,):
            s = np.repeat(s[:, None], 3, axis=1)
        elif s.shape != (k, 3):
            raise CalibrationError(
                f"sigma must be a scalar, ({k},) or ({k}, 3) (std of each dwell mean); "
                f"got {s.shape}"
            )
        if not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise CalibrationError("sigma must be positive and finite")
        return np.ascontiguousarray(s * s), "given sigma (std of each dwell mean)"
    if ds is not None and ds.var is not None and ds.count is not None:
        v = ds.var / ds.count[:, None]
        if np.all(np.isfinite(v)) and np.all(v.sum(axis=1) > 0):
            return np.ascontiguousarray(v), "dwell variance / count (white noise)"
        return None, "estimated from the residuals (dwell variances unusable)"
    return None, "estimated from the residuals (unit weights)"


# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class NormStats:
    """Norm statistics as the seed paper reports them (units of g)."""

    mean_norm_g: float
    residual_std_g: float
    rms: float

    def line(self) -> str:
        return (
            f"mean |a|/g = {self.mean_norm_g:.6f}, std(|a| - g) = {self.residual_std_g:.3e} g, "
            f"RMS = {self.rms:.3e}"
        )


def _norm_stats(norms: NDArray[np.float64], g: float) -> NormStats:
    r = norms - g
    return NormStats(
        float(np.mean(norms) / g), float(np.std(r) / g), float(np.sqrt(np.mean(r * r)))
    )


class StaticFit:
    """Result of :func:`fit_static` (everything in the caller's units; residuals in g's).

    Attributes
    ----------
    vector : (p,) [sx, sy, sz, bx, by, bz, m1, m2, m3] (p = 6 for ``model="diag"``)
    scale, bias, nonorth : (3,) parts of ``vector`` (nonorth = (m1, m2, m3), zeros for diag)
    K : (3, 3) output units per (m/s^2) (per unit of g's units);
    covariance, std, correlation of ``vector``
    residuals : (k,) ``|a_k| - g`` per dwell;  rms, chi2_dof, dof
    noise_model : how the dwell weights were obtained
    iterations, converged : of GN/LM (0 / True for the linear methods)
    """

    def __init__(
        self,
        raw: Any,
        *,
        means: NDArray[np.float64],
        g: float,
        method: str,
        noise_model: str,
        nominal: Any = None,
    ) -> None:
        self._raw = raw
        self._means = means
        self.g = g
        self.model: str = raw.model
        self.method = method
        self.noise_model = noise_model
        self.noise_known: bool = raw.noise_known
        self._nominal = nominal
        self._weak_std = 1e-3
        self.input_units: str = ""

    # -- parameters ---------------------------------------------------------------------
    @cached_property
    def vector(self) -> NDArray[np.float64]:
        return self._raw.params  # type: ignore[no-any-return]

    @property
    def names(self) -> tuple[str, ...]:
        return PARAM_NAMES[: self.vector.size]

    @property
    def scale(self) -> NDArray[np.float64]:
        return self.vector[0:3].copy()

    @property
    def bias(self) -> NDArray[np.float64]:
        return self.vector[3:6].copy()

    @property
    def nonorth(self) -> NDArray[np.float64]:
        return self.vector[6:9].copy() if self.vector.size == 9 else np.zeros(3)

    @property
    def K(self) -> NDArray[np.float64]:
        return _k_matrix(self.vector, self.model)

    @property
    def start(self) -> NDArray[np.float64]:
        """Start of GN/LM (the quadric solution unless ``start=`` was given)."""
        return self._raw.start  # type: ignore[no-any-return]

    # -- uncertainty --------------------------------------------------------------------
    @cached_property
    def covariance_unscaled(self) -> NDArray[np.float64]:
        """``(J^T W J)^-1`` with the noise model's weights (unit weights when estimated)."""
        return self._raw.covariance  # type: ignore[no-any-return]

    @property
    def covariance_scaled(self) -> NDArray[np.float64]:
        """``covariance_unscaled * chi2_dof``: uses the noise level the residuals show."""
        return self.covariance_unscaled * self.chi2_dof

    @property
    def covariance(self) -> NDArray[np.float64]:
        """Parameter covariance: unscaled for a known noise model, scaled when estimated."""
        return self.covariance_unscaled if self.noise_known else self.covariance_scaled

    @property
    def std(self) -> NDArray[np.float64]:
        return np.sqrt(np.diag(self.covariance))

    @property
    def correlation(self) -> NDArray[np.float64]:
        s = self.std
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.covariance / np.outer(s, s)

    # -- residuals ----------------------------------------------------------------------
    @cached_property
    def residuals(self) -> NDArray[np.float64]:
        return self._raw.residuals  # type: ignore[no-any-return]

    @property
    def sigma_residual(self) -> NDArray[np.float64]:
        """Predicted std of each residual from the noise model (NaN when estimated)."""
        s = self._raw.sigma_r
        return s if self.noise_known else np.full_like(s, np.nan)

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residuals**2)))

    @property
    def chi2_dof(self) -> float:
        """Whitened cost per degree of freedom (sigma^2 estimate when the noise is estimated)."""
        return float(self._raw.chi2_dof)

    @property
    def dof(self) -> int:
        return int(self._raw.dof)

    @property
    def iterations(self) -> int:
        return int(self._raw.iterations)

    @property
    def converged(self) -> bool:
        return bool(self._raw.converged)

    # -- observability ------------------------------------------------------------------
    @property
    def predicted_std_relative(self) -> NDArray[np.float64]:
        """Predicted std in comparable units (scale/misalignment relative, biases in g)."""
        return self._raw.std_comparable  # type: ignore[no-any-return]

    @property
    def weak(self) -> bool:
        return bool(self._raw.weak)

    @property
    def degenerate(self) -> bool:
        return bool(self._raw.degenerate)

    def observability(self) -> dict[str, Any]:
        """SVD of the whitened Jacobian in comparable units: singular values, condition,
        predicted std of each parameter and of the least determined combination (named)."""
        return dict(self._raw.observability())

    # -- norm statistics ----------------------------------------------------------------
    def calibrated_means(self) -> NDArray[np.float64]:
        """Calibrated dwell means (k, 3), units of g."""
        return np.asarray(np.linalg.solve(self.K, (self._means - self.bias).T).T, dtype=np.float64)

    @cached_property
    def norm_stats(self) -> dict[str, Any]:
        """Norm statistics before/after as the paper reports them.

        ``before`` uses the nominal model (``nominal=`` of :func:`fit_static`; identity when
        the data already look like units of g), ``None`` when there is no sensible nominal.
        """
        after = _norm_stats(self.g + self.residuals, self.g)
        before: NormStats | None = None
        nom = self._nominal
        if nom is None:
            nrm = np.linalg.norm(self._means, axis=1)
            if 0.5 < np.median(nrm) / self.g < 2.0:
                before = _norm_stats(nrm, self.g)
        else:
            before = _norm_stats(np.linalg.norm(nom.apply(self._means), axis=1), self.g)
        red = None
        if before is not None and before.residual_std_g > 0:
            red = 100.0 * (1.0 - after.residual_std_g / before.residual_std_g)
        return {"before": before, "after": after, "std_reduction_percent": red}

    # -- export -------------------------------------------------------------------------
    def to_model(self, **meta: Any) -> TriadModel:
        """The fitted :class:`TriadModel` (``meta``: sensor_id, date, temperature, ...).

        The stored ``covariance`` is the more realistic of the two: scaled by chi2/dof when
        the residuals exceed the noise model (chi2/dof > 1), else the noise-model one. The
        metadata records chi2/dof, the noise model and both covariances' choice.
        """
        md = dict(meta.pop("metadata", None) or {})
        scaled = bool(self.dof > 0 and np.isfinite(self.chi2_dof) and self.chi2_dof > 1.0)
        cov = self.covariance_scaled if scaled else self.covariance
        md.update(
            chi2_dof=None if not np.isfinite(self.chi2_dof) else float(self.chi2_dof),
            dof=int(self.dof),
            noise_model=self.noise_model,
            covariance="scaled by chi2/dof" if scaled else "from the noise model",
            residual_rms=float(self.rms),
            n_dwells=int(len(self.residuals)),
        )
        if self.input_units and "input_units" not in meta:
            meta["input_units"] = self.input_units
        return TriadModel(
            self.K,
            self.bias,
            model=self.model,
            covariance=cov,
            g=self.g,
            metadata=md,
            **meta,
        )

    def to_dict(self) -> dict[str, Any]:
        ns = self.norm_stats
        return {
            "model": self.model,
            "method": self.method,
            "names": list(self.names),
            "vector": self.vector.tolist(),
            "std": self.std.tolist(),
            "covariance": self.covariance.tolist(),
            "residuals": self.residuals.tolist(),
            "rms": self.rms,
            "chi2_dof": self.chi2_dof,
            "dof": self.dof,
            "noise_model": self.noise_model,
            "iterations": self.iterations,
            "converged": self.converged,
            "g": self.g,
            "weak": self.weak,
            "predicted_std_relative": self.predicted_std_relative.tolist(),
            "norm_before": None if ns["before"] is None else ns["before"].__dict__,
            "norm_after": ns["after"].__dict__,
            "std_reduction_percent": ns["std_reduction_percent"],
        }

    def summary(self, truth: ArrayLike | None = None) -> str:
        """Readable table of parameters with std (and truth), plus norm statistics."""
        tv = None if truth is None else np.asarray(truth, dtype=np.float64).reshape(-1)
        lines = [
            f"static fit: model {self.model!r}, method {self.method!r}, {len(self.residuals)} "
            f"dwells, g = {self.g}",
            f"  noise model: {self.noise_model}; chi2/dof = {self.chi2_dof:.3g}; "
            f"iterations {self.iterations}{'' if self.converged else ' (NOT converged)'}",
        ]
        if self.noise_known and self.chi2_dof > 3:
            lines.append(
                f"  note: residuals exceed the noise model (chi2/dof {self.chi2_dof:.3g}); "
                "covariance_scaled is the more realistic uncertainty"
            )
        hdr = f"  {'param':<6} {'value':>14} {'std':>11}"
        if tv is not None:
            hdr += f" {'truth':>14} {'error/std':>10}"
        lines.append(hdr)
        for i, nm in enumerate(self.names):
            ln = f"  {nm:<6} {self.vector[i]:>14.7g} {self.std[i]:>11.3g}"
            if tv is not None and i < tv.size:
                e = (self.vector[i] - tv[i]) / self.std[i] if self.std[i] > 0 else np.nan
                ln += f" {tv[i]:>14.7g} {e:>10.2f}"
            lines.append(ln)
        ns = self.norm_stats
        if ns["before"] is not None:
            lines.append("  norm before: " + ns["before"].line())
        lines.append("  norm after:  " + ns["after"].line())
        if ns["std_reduction_percent"] is not None:
            lines.append(f"  residual std reduced by {ns['std_reduction_percent']:.1f} %")
        if self.dof <= 0:
            lines.append(
                "  no redundancy (as many dwells as parameters): the residuals cannot test the "
                "model; the std above comes from the noise model alone"
            )
        if self.weak:
            lines.append("  WEAK design: " + _weak_text(self))
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (
            f"StaticFit(model={self.model!r}, method={self.method!r}, "
            f"rms={self.rms:.3g}, chi2_dof={self.chi2_dof:.3g})"
        )


def _weak_text(fit: StaticFit) -> str:
    # Formatted in Rust (Python's .3g/.2g): formatting a dozen floats here cost more than the fit.
    return fit._raw.weak_text(fit._weak_std)  # type: ignore[no-any-return]


def fit_static(
    data: DwellSet | ArrayLike,
    g: float,
    *,
    model: str = "lower",
    method: str = "lm",
    sigma: ArrayLike | None = None,
    start: ArrayLike | None = None,
    nominal: TriadModel | None = None,
    observability: str = "raise",
    weak_std: float = 1e-3,
    degenerate_std: float = 0.1,
    max_iter: int = 200,
    check_g: bool = True,
) -> StaticFit:
    """Calibrate a triaxial accelerometer from static dwell means and a reference gravity.

    Parameters
    ----------
    data : DwellSet or (k, 3) array
        Dwell means in output units (raw counts or m/s^2). A DwellSet's ``var``/``count``
        give each dwell's weight (white-noise standard error).
    g : float
        Reference gravity (e.g. from an atomic gravimeter, or :func:`local_gravity`), in the
        units the calibrated output should have (m/s^2).
    model : "lower" (seed 000, 9), "diag" (bias + scale, 6) or "upper" (imu_tk, 9)
    method : "lm" (default: exact quadric start, then Levenberg-Marquardt on the whitened
        ``|a_k| - g``, maximum likelihood), "gauss-newton", "quadric" (exact linear solution,
        SPEC 1) or "linear-paper" (the paper's small-M back-substitution, for reproduction).
    sigma : scalar, (k,) or (k, 3), optional
        Std of each dwell mean per axis, output units (overrides the DwellSet's variances).
        Without it and without variances, unit weights and the noise is estimated from the
        residuals (``noise_model`` says which).
    start : (p,), optional
        Start of GN/LM (default the quadric solution), e.g. the paper's e0.
    nominal : TriadModel, optional
        Nominal model for the "before" norm statistics.
    observability : "raise" (default), "warn" or "ignore"
        What to do when the dwells cannot determine the parameters (DegenerateDataError
        naming the undetermined combination). Weakly determined parameters (predicted std
        above ``weak_std`` relative / g) always give a :class:`WeakDesignWarning` unless
        ``observability="ignore"``.

    Raises
    ------
    DegenerateDataError
        Too few dwells, singular or numerically singular pose set, not an ellipsoid.
    CalibrationError
        NaN, bad shapes, implausible g, non-convergence.
    """
    means, ds = _means_of(data)
    gv = _check_g(g, check_g)
    if method not in _METHODS:
        raise CalibrationError(
            f"unknown method {method!r}; use 'lm', 'gauss-newton', 'quadric' or 'linear-paper'"
        )
    if observability not in ("raise", "warn", "ignore"):
        raise CalibrationError("observability must be 'raise', 'warn' or 'ignore'")
    var, noise_model = _noise_var(means.shape[0], ds, sigma)
    st = None
    if start is not None:
        st = [float(v) for v in np.asarray(start, dtype=np.float64).reshape(-1)]
    raw = _core.static_fit_raw(
        means,
        gv,
        model,
        method,
        var,
        st,
        int(max_iter),
        observability == "raise",
        float(degenerate_std),
        float(weak_std),
    )
    if not raw.converged and not raw.degenerate:
        raise CalibrationError(
            f"{method} did not converge in {max_iter} iterations (start {raw.start.tolist()}); "
            "use the default start (the exact quadric solution) or more iterations"
        )
    fit = StaticFit(
        raw, means=means, g=gv, method=method, noise_model=noise_model, nominal=nominal
    )
    fit._weak_std = float(weak_std)
    if isinstance(data, DwellSet):
        fit.input_units = data.units
    if observability != "ignore" and (raw.weak or raw.degenerate):
        if raw.degenerate:
            o = fit.observability()
            msg = (
                f"the dwells cannot determine {o['combination']} (predicted std "
                f"{o['weakest_std']:.3g} relative); results are not meaningful"
            )
        else:
            msg = f"weakly determined calibration ({len(means)} dwells): " + _weak_text(fit)
        warnings.warn(msg, WeakDesignWarning, stacklevel=2)
    return fit


# ------------------------------------------------------------------------------------------
@dataclass
class BatchFit:
    """Result of :func:`fit_static_batch` (B sessions).

    params, std : (B, p); rms : (B,); iterations : (B,);
    status : (B,) 0 ok, 1 degenerate data, 2 not converged / diverged, 3 invalid input.
    """

    params: NDArray[np.float64]
    std: NDArray[np.float64]
    rms: NDArray[np.float64]
    iterations: NDArray[np.int64]
    status: NDArray[np.uint8]

    @property
    def ok(self) -> NDArray[np.bool_]:
        return self.status == 0  # type: ignore[no-any-return]


def fit_static_batch(
    means: ArrayLike,
    g: float | ArrayLike,
    *,
    model: str = "lower",
    method: str = "lm",
    sigma: float | None = None,
    start: ArrayLike | None = None,
    max_iter: int = 200,
    degenerate_std: float = 0.1,
) -> BatchFit:
    """Fit B independent sessions of n dwell means each, ``means`` (B, n, 3), on all cores.

    ``g`` is a scalar or (B,); ``sigma`` (scalar std of each dwell mean per axis) gives known
    weights, None estimates the noise per session. No exceptions per session: see ``status``.
    The interpreter is released during the work.
    """
    m = np.ascontiguousarray(np.asarray(means, dtype=np.float64))
    if m.ndim != 3 or m.shape[2] != 3:
        raise CalibrationError(f"means must have shape (B, n, 3); got {m.shape}")
    gv = np.ascontiguousarray(np.atleast_1d(np.asarray(g, dtype=np.float64)))
    if gv.ndim != 1 or gv.size not in (1, m.shape[0]):
        raise CalibrationError(f"g must be a scalar or have shape ({m.shape[0]},)")
    st = None if start is None else [float(v) for v in np.asarray(start, float).reshape(-1)]
    d = _core.static_fit_batch_raw(
        m,
        gv,
        model,
        method,
        None if sigma is None else float(sigma),
        st,
        int(max_iter),
        float(degenerate_std),
    )
    return BatchFit(d["params"], d["std"], d["rms"], d["iterations"], d["status"])


# ------------------------------------------------------------------------------------------
class TriadModel:
    """A calibrated accelerometer triad: ``a = K^-1 (am - b)``.

    K : (3, 3) output units per (m/s^2);  bias : (3,) output units.
    Saved as versioned JSON (format ``accelcal.TriadModel``, version 1) with units,
    covariance of the parameter vector and metadata (sensor id, date, g, temperature).
    """

    FORMAT = "accelcal.TriadModel"
    VERSION = 1

    def __init__(
        self,
        K: ArrayLike,
        bias: ArrayLike,
        *,
        model: str = "lower",
        covariance: ArrayLike | None = None,
        g: float | None = None,
        units: str = "m/s^2",
        input_units: str = "",
        sensor_id: str = "",
        date: str | None = None,
        temperature: float | None = None,
        metadata: dict[str, Any] | None = None,
    ) -> None:
        k = np.array(K, dtype=np.float64)
        b = np.array(bias, dtype=np.float64).reshape(-1)
        if k.shape != (3, 3) or b.shape != (3,):
            raise CalibrationError("K must be (3, 3) and bias (3,)")
        if not (np.all(np.isfinite(k)) and np.all(np.isfinite(b))):
            raise CalibrationError("K and bias must be finite")
        if abs(np.linalg.det(k)) == 0.0:
            raise CalibrationError("K is singular")
        _n_params(model)
        self.K = k
        self.bias = b
        self.model = model
        self.covariance = None if covariance is None else np.array(covariance, dtype=np.float64)
        self.g = None if g is None else float(g)
        self.units = units
        self.input_units = input_units
        self.sensor_id = sensor_id
        self.date = date or _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        self.temperature = None if temperature is None else float(temperature)
        self.metadata = dict(metadata or {})

    @property
    def vector(self) -> NDArray[np.float64]:
        k = self.K
        v = [k[0, 0], k[1, 1], k[2, 2], *self.bias]
        if self.model == "lower":
            v += [k[1, 0], k[2, 0], k[2, 1]]
        elif self.model == "upper":
            v += [k[0, 1], k[0, 2], k[1, 2]]
        return np.array(v)

    @classmethod
    def from_vector(cls, vector: ArrayLike, model: str = "lower", **kw: Any) -> TriadModel:
        v = np.asarray(vector, dtype=np.float64).reshape(-1)
        if v.size != _n_params(model):
            raise CalibrationError(f"model {model!r} needs {_n_params(model)} values")
        return cls(_k_matrix(v, model), v[3:6], model=model, **kw)

    def apply(self, raw: ArrayLike) -> NDArray[np.float64]:
        """Calibrated specific force (N, 3) float64 of raw output (N, 3) (float64, float32,
        int16, int32 read in place; other integer types widened). Stateless per sample, so
        chunks of a stream can be applied one at a time."""
        a = np.asarray(raw)
        if a.ndim == 1 and a.size == 3:
            return self.apply(a.reshape(1, 3))[0]  # type: ignore[no-any-return]
        s = samples_array(a, "raw")
        return _core.apply_triad_raw(  # type: ignore[no-any-return]
            s, self.K.tolist(), self.bias.tolist()
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": self.FORMAT,
            "version": self.VERSION,
            "model": self.model,
            "parameter_names": list(PARAM_NAMES[: 6 if self.model == "diag" else 9]),
            "vector": self.vector.tolist(),
            "K": self.K.tolist(),
            "bias": self.bias.tolist(),
            "units": {
                "output": self.units,
                "input": self.input_units,
                "K": f"input units per {self.units}",
                "bias": "input units",
            },
            "covariance": None if self.covariance is None else self.covariance.tolist(),
            "g": self.g,
            "sensor_id": self.sensor_id,
            "date": self.date,
            "temperature": self.temperature,
            "metadata": self.metadata,
        }

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the model as JSON, atomically."""
        atomic_write(path, json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> TriadModel:
        """Read a model written by :meth:`save`."""
        try:
            with open(path, encoding="utf-8") as fh:
                d = json.load(fh)
        except OSError as e:
            raise CalibrationError(f"cannot read model {str(path)!r}: {e.strerror}") from None
        except json.JSONDecodeError as e:
            raise CalibrationError(f"{str(path)!r} is not JSON: {e}") from None
        if not isinstance(d, dict) or d.get("format") != cls.FORMAT:
            raise CalibrationError(f"{str(path)!r} is not an accelcal TriadModel file")
        ver = d.get("version")
        if not isinstance(ver, int) or ver > cls.VERSION:
            raise CalibrationError(
                f"TriadModel file version {ver!r} is newer than this accelcal supports "
                f"({cls.VERSION})"
            )
        units = d.get("units") or {}
        return cls(
            d["K"],
            d["bias"],
            model=d.get("model", "lower"),
            covariance=d.get("covariance"),
            g=d.get("g"),
            units=units.get("output", "m/s^2"),
            input_units=units.get("input", ""),
            sensor_id=d.get("sensor_id", ""),
            date=d.get("date"),
            temperature=d.get("temperature"),
            metadata=d.get("metadata"),
        )

    def __repr__(self) -> str:
        v = np.array2string(self.vector, precision=6)
        return f"TriadModel(model={self.model!r}, vector={v})"


# ------------------------------------------------------------------------------------------
def local_gravity(lat_deg: float, height_m: float = 0.0) -> float:
    """WGS84 normal gravity (Somigliana) at geodetic latitude ``lat_deg`` and ellipsoidal
    height ``height_m``, with the second-order free-air correction (about -3.086e-6 m/s^2 per
    m). Accuracy against a gravimeter: typically 1e-3 m/s^2 (local anomalies). Returns m/s^2.
    """
    lat = float(lat_deg)
    h = float(height_m)
    if not (math.isfinite(lat) and -90.0 <= lat <= 90.0):
        raise CalibrationError(f"latitude must be in [-90, 90] degrees; got {lat_deg!r}")
    if not (math.isfinite(h) and -11000.0 <= h <= 50000.0):
        raise CalibrationError(f"height must be within -11 km .. 50 km (metres); got {height_m!r}")
    ge, k, e2 = 9.7803253359, 0.00193185265241, 0.00669437999013
    a, f, m = 6378137.0, 1.0 / 298.257223563, 0.00344978650684
    s2 = math.sin(math.radians(lat)) ** 2
    g0 = ge * (1.0 + k * s2) / math.sqrt(1.0 - e2 * s2)
    return g0 * (1.0 - 2.0 / a * (1.0 + f + m - 2.0 * f * s2) * h + 3.0 * h * h / (a * a))


# ------------------------------------------------------------------------------------------
