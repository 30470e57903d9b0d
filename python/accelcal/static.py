"""Static field calibration by norm observation (numerics in Rust).

Sensor model: raw output ``am = K a + b``; calibrated specific force ``a = K^-1 (am - b)``.
At rest ``|a| = g`` whatever the attitude, so dwell means at several attitudes plus a
reference ``g`` determine ``K`` and ``b``.

Parameter vector, always in this order ``[sx, sy, sz, bx, by, bz, m1, m2, m3]``:

- ``model="lower"`` (the norm-observation paper's): ``K = [[sx, 0, 0], [m1, sy, 0],
  [m2, m3, sz]]``; ``m1`` is the x-input seen by the y output, ``m2`` x seen by z, ``m3`` y
  seen by z.
- ``model="upper"`` (imu_tk's triangle): ``K = [[sx, m1, m2], [0, sy, m3], [0, 0, sz]]``;
  ``m1`` is the y-input seen by the x output, ``m2`` z seen by x, ``m3`` z seen by y.
- ``model="diag"``: ``K = diag(sx, sy, sz)``, first 6 values only.

``am`` is in the sensor's raw (input) units (counts, mg, g or m/s^2, as recorded): ``K`` is in
raw (input) units per unit of ``g`` (counts per m/s^2 for raw counts; it maps calibrated to raw),
``b`` in raw (input) units; residuals and calibrated values are in the units of ``g`` (m/s^2).

The fit is maximum likelihood: the whitened residual of dwell ``k`` is
``(|K^-1 (am_k - b)| - g) / sigma_k`` with ``sigma_k^2 = w_k^T Sigma_k w_k``,
``w_k = K^-T a_k / |a_k|``, and ``sigma_k`` is re-evaluated with the parameters.
"""

from __future__ import annotations

import copyreg
import math
import warnings
from contextvars import ContextVar
from dataclasses import dataclass
from functools import cached_property
from typing import Any, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core, _quiet
from ._core import CalibrationError
from ._triad import PARAM_NAMES, k_matrix
from ._triad import fibonacci_sphere as _fibonacci
from ._triad_model import TriadModel, dwell_fingerprints, units_of_g
from ._triad_model import accelcal_version as _accelcal_version
from ._validate import number, real_array
from .dwell import DwellSet, check_faults

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

#: Result of :func:`fit_static_batch` (one row per session; see its fields).
BatchFit = _core.BatchFit

_OBSERVABILITY = ("raise", "warn", "ignore")
#: Weakest predicted std (relative) above which a returned fit's warning says its poses cannot
#: be told from a singular design: the two-plane field procedure (exactly singular) fitted to
#: noisy means gives 0.4 to several hundred along its null combination, whatever the noise.
_SINGULAR_LIKE_STD = 0.3
_F64 = np.dtype(np.float64)


class WeakDesignWarning(UserWarning):
    """The dwells determine the parameters only weakly (large predicted std)."""


class OffNormWarning(UserWarning):
    """Dwells whose means cannot be at rest (:func:`off_norm_dwells`) are in the fit."""


def _ignored(category: type[Warning]) -> bool:
    """The active warning filters ignore ``category`` whatever its text and origin (then the
    text need not be built). Any filter that looks at the text, module or line: False."""
    for action, msg, cat, mod, lineno in warnings.filters:
        if msg is not None or mod is not None or lineno:
            return False
        if issubclass(category, cat):
            return bool(action == "ignore")
    return bool(getattr(warnings, "defaultaction", "default") == "ignore")


def unit_label(g: float) -> str:
    """:func:`units_of_g` for text: ``"units of g"`` when ``g`` is in none of the three."""
    return units_of_g(g) or "units of g"


# ------------------------------------------------------------------------------------------
def _t95(dof: int) -> float:
    """The two-sided 95 % Student t quantile for ``dof`` degrees of freedom (``t^2`` is
    F(1, dof): the F tail of the core, bisected)."""
    lo, hi = 1.959, 1e3
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if _core.f_sf(mid * mid, 1.0, float(dof)) > 0.05:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def _frozen(a: Any) -> NDArray[np.float64]:
    """``a`` made read-only: a cached result array handed out on every access, which an edit
    in place (``fit.K /= 9.80665``) would change for the fit, its summary and its file."""
    a = np.asarray(a, dtype=np.float64)
    a.setflags(write=False)
    return a


def _as_means(x: Any, name: str) -> NDArray[np.float64]:
    """(k, 3) float64 (any layout; boolean, complex, text and object refused)."""
    a = real_array(x, name, "output units")
    if a.ndim != 2 or a.shape[1] != 3:
        raise CalibrationError(f"{name} must have shape (k, 3); got {a.shape}")
    return a


def _variance_message(bad: float) -> str:
    return (
        f"sigma = {bad!r} is out of range: its square (the variance of a dwell mean) is not "
        "a finite positive number; give the std of each dwell mean in output units "
        "(1e-150 .. 1e150)"
    )


def _variance(s: Any) -> Any:
    """sigma^2, refusing a sigma whose square over- or underflows (no finite variance)."""
    with np.errstate(over="ignore", under="ignore"):
        v = np.square(s)
    if not (np.all(np.isfinite(v)) and np.all(v > 0)):
        bad = float(np.asarray(s).reshape(-1)[np.argmax(~(np.isfinite(v) & (v > 0)).reshape(-1))])
        raise CalibrationError(_variance_message(bad))
    return v


def _resolvable(var: Any, means: NDArray[np.float64]) -> Any:
    """Refuse a dwell-mean noise below what double precision resolves in the means (the
    whitened problem would overflow)."""
    mag = float(np.max(np.abs(means))) if means.size else 0.0
    floor = (1e-12 * mag) ** 2
    if mag > 0 and np.any(np.asarray(var) < floor):
        low = float(np.sqrt(np.min(var)))
        raise CalibrationError(
            f"sigma = {low:.3g} is below the double-precision resolution of dwell means of "
            f"size {mag:.3g} (sigma must be >= {1e-12 * mag:.3g}, 1e-12 of the largest mean): "
            "give the std of each dwell mean in the means' units"
        )
    return var


def _inputs(
    data: Any, sigma: Any
) -> tuple[NDArray[np.float64], NDArray[np.float64] | float | None, str, str]:
    """Dwell means, the per-axis variance of each mean (one number for all, (k, 3), or None:
    estimated), how the noise model was obtained, and the input units."""
    if type(data) is np.ndarray and data.dtype is _F64 and data.flags.aligned:
        # The common case, without the general coercion: float64 as given (any strides).
        means, units = data, ""
        sh = data.shape
        if len(sh) != 2 or sh[1] != 3:
            raise CalibrationError(f"dwell means must have shape (k, 3); got {sh}")
    elif isinstance(data, DwellSet):
        check_faults(data, "fit_static")
        means, units = data.mean, data.units
    else:
        means, units = _as_means(data, "dwell means"), ""
    if sigma is None:
        if not isinstance(data, DwellSet):
            return means, None, _ESTIMATED_ISOTROPIC, units
    elif type(sigma) is float or (
        isinstance(sigma, (int, np.floating, np.integer)) and not isinstance(sigma, bool)
    ):
        sv = sigma if type(sigma) is float and 0.0 < sigma < math.inf else number(
            sigma, "sigma", lo=0.0, lo_open=True, unit="(std of each dwell mean, output units)")
        # One variance for every dwell and axis, checked without NumPy (its error state and
        # reductions cost more than the fit); the resolution against the means' size is
        # checked in Rust.
        v = sv * sv
        if not (math.isfinite(v) and v > 0.0):
            raise CalibrationError(_variance_message(sv))
        return means, v, _GIVEN_SIGMA, units
    if sigma is not None:
        k = means.shape[0]
        s = np.asarray(sigma)
        if s.dtype.kind not in "fiu":
            raise CalibrationError(f"sigma must be a real number or array; got {sigma!r}")
        s = s.astype(np.float64)
        if s.ndim == 0:
            s = np.full((k, 3), float(s))
        elif s.shape == (k,):
            s = np.repeat(s[:, None], 3, axis=1)
        elif s.shape != (k, 3):
            raise CalibrationError(
                f"sigma must be a scalar, ({k},) or ({k}, 3) (std of each dwell mean, output "
                f"units); got shape {s.shape}"
            )
        if not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise CalibrationError(
                "sigma must be positive and finite (std of each dwell mean, output units)"
            )
        return means, _resolvable(_variance(s), means), "given sigma (std of each dwell mean)", \
            units
    if isinstance(data, DwellSet) and data.var is not None and data.count is not None:
        v = data.var / data.count[:, None]
        if np.all(np.isfinite(v)) and np.all(v.sum(axis=1) > 0):
            return means, v, "dwell variance / count (white noise)", units
        return means, None, "estimated from the residuals (dwell variances unusable)", units
    return means, None, _ESTIMATED_ISOTROPIC, units


_ESTIMATED_ISOTROPIC = "estimated from the residuals (isotropic output noise)"
_GIVEN_SIGMA = "given sigma (std of each dwell mean)"


# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class NormStats:
    """Norm statistics as the norm-observation paper reports them.

    mean_norm_g : mean |a| / g;  residual_std_g : std(|a| - g) / g;  rms_g : RMS(|a| - g) / g
    (all in units of g); rms : RMS(|a| - g) in the units of the reference ``g`` (``units``).
    """

    mean_norm_g: float
    residual_std_g: float
    rms_g: float
    rms: float
    units: str = ""

    def line(self) -> str:
        u = self.units or "units of the reference g"
        rms = f"{self.rms_g:.3e} g" + ("" if u == "g" else f" = {self.rms:.3e} {u}")
        return (
            f"mean |a| = {self.mean_norm_g:.6f} g, std(|a| - g) = {self.residual_std_g:.3e} g, "
            f"RMS(|a| - g) = {rms}"
        )


def _norm_stats(norms: NDArray[np.float64], g: float) -> NormStats:
    r = norms - g
    rms = float(np.sqrt(np.mean(r * r)))
    return NormStats(
        float(np.mean(norms) / g), float(np.std(r) / g), rms / g, rms, units_of_g(g)
    )


class StaticFit(_core.StaticFit):
    """Result of :func:`fit_static` (everything in the caller's units; residuals in g's).

    Fields computed in Rust (see ``accelcal._core.StaticFit``): ``vector`` (p,)
    ``[sx, sy, sz, bx, by, bz, m1, m2, m3]`` (p = 6 for ``model="diag"``), ``start``,
    ``covariance_unscaled`` ``(J^T W J)^-1``, ``residuals`` ``|a_k| - g`` per dwell,
    ``sigma_residual`` (predicted std of each residual), ``chi2_dof``, ``chi2_p`` (its
    upper-tail probability under the noise model), ``dof``, ``cost``,
    ``iterations``, ``converged``, ``noise_known``, ``weak``, ``degenerate``,
    ``predicted_std_relative``, ``means``, ``var``, ``g``, ``model``, ``method``,
    ``noise_model``, ``input_units``, ``nominal``.

    Uncertainty (the rule of the field guide):

    - ``covariance`` / ``std``: from the noise model when it is known; with the noise
      estimated, from the noise level the residuals show (``covariance_scaled``).
    - ``covariance_scaled``: ``covariance_unscaled * chi2_dof``.
    - ``sigma_g`` (the std of the reference gravity, when given): its covariance
      ``covariance_gravity`` (``sigma_g^2 j j^T``, ``j = dp/dg``: ``-p / g`` for the entries
      of K, 0 for the biases) is added to every covariance above but
      ``covariance_unscaled``, so ``covariance``, ``std``, ``covariance_realistic``,
      ``std_realistic`` and the exports include it. The weak/degenerate checks
      (``predicted_std_relative``) leave it out: the poses cannot determine g.
    - ``realistic`` names the one to quote: ``"scaled"`` when the noise is estimated or when
      the residuals exceed the noise model (``chi2_dof > 1``: the Birge-ratio inflation), else
      ``"noise_model"``; ``covariance_realistic`` / ``std_realistic`` are that one. The
      summary prints it and :meth:`to_model` stores it (with both labelled).
    """

    # -- pickling and copying -----------------------------------------------------------
    def __getstate__(self) -> dict[str, Any]:
        """The instance dict without the cached values: a copy or an unpickled fit computes
        them again, read-only as here (pickle and deepcopy would hand the cached arrays back
        writable, and an edit in place would then contradict the fit)."""
        cls = type(self)
        return {k: v for k, v in self.__dict__.items()
                if not isinstance(getattr(cls, k, None), cached_property)}

    def __reduce__(self) -> tuple[Any, ...]:
        # The core's arguments by name, for every protocol (0 and 1 cannot call
        # __getnewargs_ex__ themselves).
        return (copyreg.__newobj_ex__, (type(self), *self.__getnewargs_ex__()),  # type: ignore[attr-defined]
                self.__getstate__())

    # -- parameters ---------------------------------------------------------------------
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

    @cached_property
    def K(self) -> NDArray[np.float64]:
        """(3, 3) raw (input) units per unit of g (per m/s^2): calibrated to raw."""
        return _frozen(k_matrix(self.vector, self.model))

    # -- uncertainty --------------------------------------------------------------------
    @cached_property
    def covariance_scaled(self) -> NDArray[np.float64]:
        """``covariance_unscaled * chi2_dof``: the noise level that the residuals show (plus
        ``covariance_gravity`` with ``sigma_g`` given)."""
        c = self.covariance_unscaled * self.chi2_dof
        return _frozen(c + self.covariance_gravity if self.sigma_g else c)

    @property
    def covariance_noise_model(self) -> NDArray[np.float64]:
        """From the noise model: unscaled when it is known, scaled when it was estimated
        (plus ``covariance_gravity`` with ``sigma_g`` given)."""
        if not self.noise_known:
            return self.covariance_scaled
        c = self.covariance_unscaled
        return c + self.covariance_gravity if self.sigma_g else c  # type: ignore[no-any-return]

    @property
    def covariance(self) -> NDArray[np.float64]:
        """Same as :attr:`covariance_noise_model`."""
        return self.covariance_noise_model

    @cached_property
    def std(self) -> NDArray[np.float64]:
        return _frozen(np.sqrt(np.diag(self.covariance)))

    @property
    def realistic(self) -> str:
        """``"scaled"`` or ``"noise_model"``: the covariance to quote (see the class doc)."""
        if not self.noise_known or (math.isfinite(self.chi2_dof) and self.chi2_dof > 1.0):
            return "scaled"
        return "noise_model"

    @property
    def covariance_realistic(self) -> NDArray[np.float64]:
        if self.realistic == "scaled" and math.isfinite(self.chi2_dof):
            return self.covariance_scaled
        return self.covariance_noise_model

    @cached_property
    def std_realistic(self) -> NDArray[np.float64]:
        return _frozen(np.sqrt(np.diag(self.covariance_realistic)))

    @property
    def correlation(self) -> NDArray[np.float64]:
        s = self.std
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.covariance / np.outer(s, s)  # type: ignore[no-any-return]

    # -- residuals ----------------------------------------------------------------------
    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residuals**2)))

    # -- norm statistics ----------------------------------------------------------------
    def calibrated_means(self) -> NDArray[np.float64]:
        """Calibrated dwell means (k, 3), units of g."""
        return np.asarray(np.linalg.solve(self.K, (self.means - self.bias).T).T, dtype=np.float64)

    def norms_before(self) -> tuple[NDArray[np.float64], str] | None:
        """Norm of every dwell mean before calibration, in the units of ``g``, and how it was
        obtained: through ``nominal`` when given; the raw norm when the data already look
        like units of g; else (raw counts) the fitted bias removed and one common scale (the
        fit's mean scale factor) applied, so that only the per-axis scale and the
        misalignment are left uncorrected."""
        if self.nominal is not None:
            cal = self.nominal.apply(self.means, check_units=False)
            return np.linalg.norm(cal, axis=1), "nominal model"
        nrm = np.linalg.norm(self.means, axis=1)
        if 0.5 < np.median(nrm) / self.g < 2.0:
            return nrm, "raw output"
        s = abs(float(np.linalg.det(self.K))) ** (1.0 / 3.0)
        if not (s > 0 and math.isfinite(s)):
            return None
        return (
            np.linalg.norm(self.means - self.bias, axis=1) / s,
            "fitted bias removed, one common scale",
        )

    @cached_property
    def norm_stats(self) -> dict[str, Any]:
        """Norm statistics before/after as the paper reports them (``before`` None when no
        sensible "before" exists); ``before_source`` says how "before" was computed."""
        after = _norm_stats(self.g + self.residuals, self.g)
        nb = self.norms_before()
        before = None if nb is None else _norm_stats(nb[0], self.g)
        red = None
        if before is not None and before.residual_std_g > 0:
            red = 100.0 * (1.0 - after.residual_std_g / before.residual_std_g)
        return {
            "before": before,
            "before_source": None if nb is None else nb[1],
            "after": after,
            "std_reduction_percent": red,
        }

    # -- warnings text ------------------------------------------------------------------
    def weak_text(self) -> str:
        """The weakly determined parameters: predicted std (the parameters' units) and
        relative std of every parameter whose relative std exceeds ``weak_std``."""
        std = self.std.tolist()
        if not all(map(math.isfinite, std)):
            return (
                "no redundancy (as many dwells as parameters): the noise and the uncertainty "
                "cannot be estimated"
            )
        rel = self.predicted_std_relative.tolist()
        lim = self.weak_std
        parts = [
            f"{nm} +-{std[i]:.3g} ({100 * rel[i]:.2g} % {'g' if 3 <= i < 6 else 'of scale'})"
            for i, nm in enumerate(self.names)
            if not rel[i] <= lim
        ]
        txt = f"predicted std {', '.join(parts)} (1 sigma)"
        one_sided = self._one_sided_axes()
        noise = self._noise_limited([i for i in range(len(rel)) if not rel[i] <= lim])
        if one_sided:
            txt += (f"; {'; '.join(one_sided)}: an axis seen on one side only barely separates "
                    "its scale from its bias, whatever the model: add poses with it turned the "
                    "other way")
        elif noise:
            txt += noise
        elif len(rel) == 9 and not all(r <= lim for r in rel[6:]):
            txt += '; model "diag" (bias + scale) needs fewer attitudes'
        return txt

    def _noise_limited(self, weak: list[int]) -> str:
        """When the same number of poses spread evenly over the sphere would determine the
        weak parameters ``weak`` no better (within 1.5x, the Cramer-Rao bound at the same
        noise), the noise limits them, not the poses: the text that says so; ``""``
        otherwise."""
        from .design import predict_accuracy

        n, rel = len(self.residuals), self.predicted_std_relative
        sig = float(np.median(self.sigma_residual))
        if self.noise_known and self.realistic == "scaled" and self.chi2_dof > 1.0:
            sig *= math.sqrt(self.chi2_dof)  # the std quoted is scaled so
        if not weak or n < 2 * rel.size or not (math.isfinite(sig) and sig > 0):
            return ""
        try:
            ideal = predict_accuracy(_fibonacci(n), sig, self.model, g=self.g)
        except CalibrationError:
            return ""
        unit = np.array([self.g if 3 <= i < 6 else 1.0 for i in range(rel.size)])
        best = np.asarray(ideal.std, dtype=np.float64) / unit
        if not all(rel[i] <= 1.5 * best[i] for i in weak):
            return ""
        u = unit_label(self.g)
        return (f"; the poses are not what limits them: {n} poses spread evenly over the "
                f"sphere would give about the same at this noise ({sig:.2g} {u} per axis of a "
                "dwell mean): average more samples per pose (the std falls as one over the "
                "square root of the samples) or record more poses")

    @cached_property
    def _directions(self) -> NDArray[np.float64] | None:
        """The calibrated gravity direction of every dwell (k, 3), or None when some dwell
        has none (a non-finite or zero calibrated mean); computed once for the summary's
        one-sided axes, distinct poses and pose spacing."""
        a = self.calibrated_means()
        if a.ndim != 2 or a.shape[0] == 0 or not np.all(np.isfinite(a)):
            return None
        n = np.linalg.norm(a, axis=1)
        return np.ascontiguousarray(a / n[:, None]) if np.all(n > 0) else None

    def _one_sided_axes(self) -> list[str]:
        """The axes no pose turned towards gravity (or away from it): their calibrated
        component stays above -0.5 g (or below +0.5 g) in every dwell."""
        u = self._directions
        if u is None:
            return []
        out = []
        for k, name in enumerate("xyz"):
            lo, hi = float(u[:, k].min()), float(u[:, k].max())
            side = "down" if lo > -0.5 else "up" if hi < 0.5 else ""
            if side:
                out.append(f"no pose turned {name} {side} ({name} from {lo:+.2f} to {hi:+.2f} g)")
        return out

    def warning_text(self) -> str | None:
        """The weak-design warning of this fit (None when the design is determined). When
        some combination is barely determined (predicted std above 10 % relative) the warning
        names it: along it the numbers are set by the noise, not by the poses."""
        if self.degenerate:
            o = self.observability()
            return (
                f"the dwells cannot determine {o.combination} (predicted std "
                f"{o.weakest_std:.3g} relative); results are not meaningful"
            )
        if not self.weak:
            return None
        txt = f"weakly determined calibration ({len(self.residuals)} dwells): "
        if self.weakest_std > 0.1:
            o = self.observability()
            txt += (
                f"the dwells barely determine {o.combination} (predicted std "
                f"{o.weakest_std:.2g} relative: along it the result is set by the noise"
            )
            if self.weakest_std > _SINGULAR_LIKE_STD:
                txt += (
                    "; as large as poses that cannot see this combination at all give with "
                    "noise (the two-plane field procedure: 0.4 or more whatever the noise), "
                    "so these poses cannot be told from such a design: treat it as "
                    "undetermined, or refuse such fits with degenerate_std="
                    f"{_SINGULAR_LIKE_STD:g}"
                )
            txt += "); "
        return txt + self.weak_text()

    # -- export -------------------------------------------------------------------------
    def to_model(self, **meta: Any) -> TriadModel:
        """The fitted :class:`TriadModel` (``meta``: sensor_id, date, temperature, ...).

        It stores both covariances, labelled, and which one is realistic (the one
        :meth:`summary` prints; ``TriadModel.covariance``); the metadata records chi2/dof,
        the degrees of freedom, the noise model, the residual RMS, the dwell count, a short
        hash of each dwell mean (``fit_dwells``: :meth:`TriadModel.own_dwells` tells a check
        against the same dwells) and the session itself (``fit_session``: the dwell means and
        their variances, from which a check of the calibration draws its uncertainty), and
        ``sigma_g`` (0 when none), ``g_source`` ("given" unless the metadata says otherwise),
        ``accelcal_version`` and ``method``.
        """
        md = dict(meta.pop("metadata", None) or {})
        md.update(
            chi2_dof=None if not math.isfinite(self.chi2_dof) else float(self.chi2_dof),
            dof=int(self.dof),
            noise_model=self.noise_model,
            residual_rms=float(self.rms),
            n_dwells=int(len(self.residuals)),
            fit_dwells=dwell_fingerprints(self.means),
            fit_session=self._session(),
        )
        # The covariances include sigma_g's term (see covariance_gravity); 0 is recorded too,
        # so a file always says how its g was counted. g_source: "given" unless the caller
        # says where g came from (the command line's --lat: "latitude formula ...").
        md["sigma_g"] = float(self.sigma_g or 0.0)
        md.setdefault("g_source", "given")
        md.setdefault("accelcal_version", _accelcal_version())
        md.setdefault("method", self.method)
        if not self.check_g:  # a g outside local gravity was meant: load says nothing of it
            md["check_g"] = False
        if self.input_units and "input_units" not in meta:
            meta["input_units"] = self.input_units
        # The calibrated output is in the units of g (a fit to g = 1 calibrates to g).
        meta.setdefault("units", unit_label(self.g))
        # A fit without redundancy and with the noise estimated (9 dwells for 9 parameters)
        # has no finite covariance: the model then carries none (it failed to be made).
        noise: Any = self.covariance_noise_model
        noise = noise if np.all(np.isfinite(noise)) else None
        scaled: Any = self.covariance_scaled
        scaled = scaled if np.all(np.isfinite(scaled)) else None
        realistic: str | None = self.realistic
        if realistic == "scaled" and scaled is None:
            realistic = "noise_model" if noise is not None else None
        if realistic == "noise_model" and noise is None:
            realistic = None
        return TriadModel(
            self.K,
            self.bias,
            model=self.model,
            covariance_noise_model=noise,
            covariance_scaled=scaled,
            realistic=realistic,
            g=self.g,
            metadata=md,
            **meta,
        )

    def _session(self) -> dict[str, Any] | None:
        """The dwell means this fit was made from and the variance of each (per axis, input
        units squared; the estimated isotropic variance when the noise was estimated), so a
        check of the calibration can refit its session with fresh noise (a parametric
        bootstrap of its uncertainty). None when the variances are not known finite."""
        m = np.asarray(self.means, dtype=np.float64)
        var = self.chi2_dof if self.var is None else self.var
        v = np.broadcast_to(np.asarray(var, dtype=np.float64), m.shape)
        if not (np.all(np.isfinite(m)) and np.all(np.isfinite(v)) and np.all(v > 0)):
            return None
        return {"means": m.tolist(), "var": np.array(v).tolist(),
                "noise_known": bool(self.noise_known)}

    def to_dict(self) -> dict[str, Any]:
        """The fit as plain data (the command line's ``--json``). With the noise estimated
        (``noise_known`` false) there is no noise model to test: ``chi2_dof`` is then the
        estimated variance of a dwell mean per axis (input units squared, as
        :attr:`chi2_dof`), ``chi2_p`` is NaN (null in JSON), and ``noise_std_estimated`` is
        its root."""
        ns = self.norm_stats
        est = (math.sqrt(self.chi2_dof) if not self.noise_known
               and math.isfinite(self.chi2_dof) else None)
        return {
            "model": self.model,
            "method": self.method,
            "names": list(self.names),
            "vector": self.vector.tolist(),
            "std": self.std_realistic.tolist(),
            "std_source": self.realistic,
            "std_noise_model": self.std.tolist(),
            "covariance": self.covariance_realistic.tolist(),
            "residuals": self.residuals.tolist(),
            "rms": self.rms,
            "units": units_of_g(self.g),
            "chi2_dof": self.chi2_dof,
            "chi2_p": self.chi2_p,
            "dof": self.dof,
            "noise_model": self.noise_model,
            "noise_known": bool(self.noise_known),
            "noise_std_estimated": est,
            "iterations": self.iterations,
            "converged": self.converged,
            "g": self.g,
            "sigma_g": self.sigma_g,
            "weak": self.weak,
            "predicted_std_relative": self.predicted_std_relative.tolist(),
            "norm_before": None if ns["before"] is None else ns["before"].__dict__,
            "norm_before_source": ns["before_source"],
            "norm_after": ns["after"].__dict__,
            "std_reduction_percent": ns["std_reduction_percent"],
        }

    def summary(self, truth: ArrayLike | None = None) -> str:
        """Readable table of parameters with their realistic std (and truth), plus norm
        statistics with units."""
        tv = None if truth is None else np.asarray(truth, dtype=np.float64).reshape(-1)
        u = unit_label(self.g)
        chi = (
            "chi2/dof n/a (no redundancy)" if self.dof <= 0
            else f"chi2/dof = {self.chi2_dof:.3g}"
            if self.noise_known
            else f"estimated noise of a dwell mean {math.sqrt(self.chi2_dof):.3g} "
            f"{self.input_units or 'raw (input) units'} per axis"
            if math.isfinite(self.chi2_dof)
            else "no redundancy"
        )
        lines = [
            f"static fit: model {self.model!r}, method {self.method!r}, {len(self.residuals)} "
            f"dwells, g = {self.g} {u}",
            f"  noise model: {self.noise_model}; {chi}; iterations {self.iterations}"
            f"{'' if self.converged else ' (NOT converged)'}",
        ]
        if self.realistic == "scaled" and self.noise_known:
            p = self.chi2_p
            if p < 0.05:
                lines.append(
                    f"  note: residuals exceed the noise model (chi2/dof {self.chi2_dof:.3g}, "
                    f"p = {p:.2g}); std below is scaled by chi2/dof (covariance_scaled, the "
                    "realistic one)")
            else:
                lines.append(
                    f"  note: chi2/dof {self.chi2_dof:.3g} is above 1 but within what the noise "
                    f"model allows (p = {p:.2g}); std below is scaled by it all the same "
                    "(covariance_scaled: the Birge-ratio convention)")
        src = "scaled by chi2/dof" if self.realistic == "scaled" else "from the noise model"
        if self.sigma_g:
            src += f", including reference-gravity uncertainty sigma_g = {self.sigma_g:.3g} {u}"
        lines.append(f"  std: {src}; K in {self.input_units or 'raw (input) units'} per {u}")
        if self.realistic == "scaled" and 0 < self.dof < 30 and math.isfinite(self.chi2_dof):
            # The scale is estimated from the residuals: intervals are Student t (at 3 dof
            # +-2 std covered 84 %).
            lines.append(
                f"  the noise level behind the std is estimated from {self.dof} degree"
                f"{'' if self.dof == 1 else 's'} of freedom: a 95 % interval is "
                f"+-{_t95(self.dof):.3g} std (Student t), not +-1.96")
        hdr = f"  {'param':<6} {'value':>14} {'std':>11}"
        if tv is not None:
            hdr += f" {'truth':>14} {'error/std':>10}"
        lines.append(hdr)
        std = self.std_realistic
        for i, nm in enumerate(self.names):
            ln = f"  {nm:<6} {self.vector[i]:>14.7g} {std[i]:>11.3g}"
            if tv is not None and i < tv.size:
                e = (self.vector[i] - tv[i]) / std[i] if std[i] > 0 else np.nan
                ln += f" {tv[i]:>14.7g} {e:>10.2f}"
            lines.append(ln)
        ns = self.norm_stats
        if ns["before"] is not None:
            lines.append(f"  norm before ({ns['before_source']}): " + ns["before"].line())
        lines.append("  norm after:  " + ns["after"].line())
        if self.dof <= 0:
            lines.append("  std(|a| - g) reduction: n/a (no redundancy: the fit passes through "
                         "every dwell)")
        elif ns["std_reduction_percent"] is not None:
            red = float(ns["std_reduction_percent"])
            lines.append(f"  std(|a| - g) reduced by {red:.1f} %" if red >= 0.05 else
                         f"  std(|a| - g) increased by {-red:.1f} %" if red <= -0.05 else
                         "  std(|a| - g) unchanged (within 0.05 %)")
        if self.dof <= 0:
            src = ("the std above comes from the noise model alone"
                   if np.all(np.isfinite(std)) else
                   "and without a known noise model (sigma, or dwell variances) there is no "
                   "std either (nan above)")
            lines.append(
                "  no redundancy (as many dwells as parameters): the residuals cannot test the "
                f"model; {src}"
            )
        repeats = self._repeats_text()
        if repeats:
            lines.append(f"  {repeats}")
        if self.weak:
            lines.append("  WEAKLY determined: " + self.weak_text())
        return "\n".join(lines)

    @cached_property
    def distinct_poses(self) -> int:
        """Number of distinct poses among the dwells: calibrated gravity directions within
        ``SAME_POSE`` (0.05, about 3 deg) of each other are one pose."""
        u = self._directions
        if u is None:
            return len(self.residuals)
        return int(_core.gap_distinct_poses(u, _core.SAME_POSE))

    def _repeats_text(self) -> str:
        """When dwells repeat poses so that fewer of the residuals' degrees of freedom test
        the model than the dof says: how many do; ``""`` otherwise."""
        n, p, k = len(self.residuals), len(self.names), self.distinct_poses
        if self.dof <= 0 or k >= n or k - p >= self.dof or self._dense_poses():
            return ""
        test = max(k - p, 0)
        dof = f"{self.dof} degree{'' if self.dof == 1 else 's'} of freedom"
        if test == 0:
            return (f"the {n} dwells are at {k} distinct poses: none of the residuals' {dof} "
                    "tests the model, they show only how well a pose repeats (new poses test "
                    "the model)")
        return (f"the {n} dwells are at {k} distinct poses: {test} of the residuals' {dof} "
                f"test{'s' if test == 1 else ''} the model, the rest show only how well a "
                "pose repeats")

    def _dense_poses(self) -> bool:
        """Whether the poses sample the sphere too densely for repeats to mean anything: the
        distinct poses' typical spacing (median nearest neighbour beyond ``SAME_POSE``) is
        under 4 times ``SAME_POSE`` (a bench stepping 3 deg: neighbours within the tolerance
        are different poses, not a pose placed twice). Not judged beyond 2000 dwells (the
        pairwise distances take 32 MB there)."""
        u = self._directions
        if u is None or len(u) < 3 or len(u) > 2000:
            return False
        d = np.sqrt(np.maximum(2.0 - 2.0 * (u @ u.T), 0.0))  # chords
        np.fill_diagonal(d, np.inf)
        d[d <= _core.SAME_POSE] = np.inf  # repeats of a pose: not the spacing
        nn = d.min(axis=1)
        nn = nn[np.isfinite(nn)]
        return bool(nn.size and float(np.median(nn)) < 4.0 * _core.SAME_POSE)

    def __repr__(self) -> str:
        # With the noise estimated (unit weights) chi2/dof is the residual variance, not a
        # test: its value would read as a gross overfit.
        tail = (f"chi2_dof={self.chi2_dof:.3g}" if self.noise_known else
                f"noise estimated {float(np.sqrt(self.chi2_dof)):.3g} per axis")
        return (f"StaticFit(model={self.model!r}, method={self.method!r}, "
                f"rms={self.rms:.3g}, {tail})")


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
    degenerate_std: float = 3.0,
    max_iter: int = 200,
    check_g: bool = True,
    sigma_g: float | None = None,
    input_units: str | None = None,
) -> StaticFit:
    """Calibrate a triaxial accelerometer from static dwell means and a reference gravity.

    Parameters
    ----------
    data : DwellSet or (k, 3) array
        Dwell means in the sensor's raw (input) units (counts, mg, m/s^2 ...). A DwellSet's
        ``var``/``count`` give each dwell's noise (white-noise standard error).
    g : float
        Reference gravity (e.g. from an atomic gravimeter, or :func:`local_gravity`), in the
        units the calibrated output should have (m/s^2).
    model : "lower" (the paper's, 9), "diag" (bias + scale, 6) or "upper" (imu_tk, 9)
    method : "lm" (default: exact quadric start, then Levenberg-Marquardt on the maximum-
        likelihood cost), "gauss-newton", "quadric" (exact linear solution of the quadric
        regression) or "linear-paper" (the paper's small-M back-substitution, for
        reproduction).
    sigma : scalar, (k,) or (k, 3), optional
        Std of each dwell mean per axis, in the units of the means (raw (input) units;
        overrides the DwellSet's variances).
        Without it and without variances the output noise is taken as isotropic and its level
        estimated from the residuals (``noise_model`` says which).
    start : (p,), optional
        Start of GN/LM (default the quadric solution), e.g. the paper's e0. Its scale
        factors ``sx, sy, sz`` must be positive: the norm cannot tell an axis's sign, so a
        negative one would converge to a mirrored calibration (det K < 0).
    nominal : TriadModel, optional
        Nominal model for the "before" norm statistics.
    observability : "raise" (default), "warn" or "ignore"
        What to do when the dwells cannot determine the parameters (DegenerateDataError
        naming the undetermined combination). Weakly determined parameters (predicted std
        above ``weak_std`` relative / g) always give a :class:`WeakDesignWarning` unless
        ``observability="ignore"``. Fewer dwells than parameters, or a design so degenerate
        that the exact linear solution fails too (no start to iterate from), raise whatever
        this says: there is no fit to return.
    weak_std, degenerate_std : float
        Thresholds of the predicted std in relative units (scale relative, biases in g).
        Above ``degenerate_std`` (3: 300 % of the scale, or 3 g) a combination counts as
        undetermined. A fit returned with a weakest predicted std above 0.3 is warned about
        as indistinguishable from a singular design: an exactly singular pose set fitted to
        noisy means gets 0.4 or more along its null combination whatever the noise.
    max_iter : int
        Iteration limit of GN/LM, in [1, 100000].
    check_g : bool
        Refuse a ``g`` that is not a plausible local gravity in m/s^2, g or cm/s^2.
    sigma_g : float, optional
        Std of the reference gravity ``g``, in the units of ``g`` (e.g. 1e-5 m/s^2 from an
        absolute gravimeter, about 1e-3 m/s^2 from a latitude formula such as
        :func:`local_gravity`). Every reported covariance and std (``covariance``, ``std``,
        ``*_realistic``, :meth:`~StaticFit.summary`, :meth:`~StaticFit.to_dict`,
        :meth:`~StaticFit.to_model`) then includes it: a g off by ``e`` relative scales K by
        ``1 / (1 + e)`` and leaves the bias, so it adds ``sigma_g^2 j j^T`` with ``j = -p / g``
        for the entries of K. None or 0 (default) leaves g exact. Must be non-negative,
        finite and at most 1 % of ``g`` (a larger one is most likely in other units).
    input_units : str, optional
        The raw (input) units of the dwell means ("counts", "mg" ...): recorded by the fit
        (``StaticFit.input_units``, the summary's "K in ... per m/s^2") and by
        :meth:`~StaticFit.to_model` in the calibration file's ``units.input``. Default: a
        DwellSet's ``units`` (a DwellSet whose units disagree is refused), else none.

    Raises
    ------
    DegenerateDataError
        Too few dwells, singular or numerically singular pose set, not an ellipsoid.
    CalibrationError
        NaN, bad shapes or options (the message names the argument, value and valid range),
        implausible g, a start with a scale factor not positive, non-convergence.
    """
    if observability not in _OBSERVABILITY:
        raise CalibrationError(
            f"observability must be 'raise', 'warn' or 'ignore'; got {observability!r}"
        )
    st: list[float] | None = None
    var: Any
    if (
        type(data) is np.ndarray and data.dtype is _F64 and start is None
        and (sigma is None or (type(sigma) is float and 1e-150 < sigma < 1e150))
    ):
        # The common call (float64 means, no start, sigma absent or a float whose square is a
        # normal number) without the general coercion: the constructor checks the shape and
        # values and reads any strides and alignment.
        means, units = data, ""
        var, noise_model = (None, _ESTIMATED_ISOTROPIC) if sigma is None else (
            sigma * sigma, _GIVEN_SIGMA)
    else:
        means, var, noise_model, units = _inputs(data, sigma)
        if start is not None:
            st = _start(start)
    if input_units is not None:
        units = _given_units(input_units, units)
    try:
        fit = StaticFit(  # positional: the fastest call into the constructor
            means, g, model, method, var, st, max_iter,  # type: ignore[arg-type]
            observability == "raise", degenerate_std, weak_std, check_g, noise_model, units,
            nominal, sigma_g,
        )
    except CalibrationError as e:  # dwells that cannot determine a calibration: why?
        why = _explained(e, means, g)
        if why is None:
            raise
        raise why from None
    if nominal is not None:
        _mirrored_axes(nominal)
    attention = fit._attention  # one read: bit 0 not converged, bit 1 weak or degenerate,
    if attention & 1:  # bit 2 a norm residual beyond 5 % of g
        raise _not_converged(fit, method, means, g)
    if attention & 4:
        _warn_off_norm(means, g)
    if attention & 2 and observability != "ignore":
        if _quiet.recorded(WeakDesignWarning) or not (
                _ignored(WeakDesignWarning) or _quiet.silenced(WeakDesignWarning)):
            # (the text costs more than the fit: not built for a warning that is dropped)
            _quiet.warn(str(fit.warning_text()), WeakDesignWarning, stacklevel=2)
    return fit


def _warn_off_norm(means: Any, g: float) -> None:
    """An OffNormWarning naming the dwells that cannot be at rest, when the screen finds
    any among a fit's dwells (one zeroed dwell mean among 20 gave chi2/dof 4e6 and sy 3000
    std off, with no word from the API; the command line leaves such dwells out)."""
    off = off_norm_dwells(means, g)
    if off is not None:
        _quiet.warn(f"{off.text(g)}; they are in this fit: leave them out (d[mask], or the "
                    "rows of the array) and fit the others", OffNormWarning, stacklevel=3)


def _given_units(given: Any, found: str) -> str:
    """fit_static's ``input_units`` against the units the data carry (a DwellSet's)."""
    if not isinstance(given, str):
        raise CalibrationError(f"input_units must be a string (the raw units of the dwell "
                               f"means, e.g. 'counts' or 'mg'); got {type(given).__name__}")
    want = given.strip()
    if want and found and want != found.strip():
        raise CalibrationError(f"input_units={given!r} disagrees with the units of the dwell "
                               f"means ({found!r}, the DwellSet's): give the one they are in")
    return want or found


def _mirrored_axes(nominal: Any) -> None:
    """Warn when the nominal model has an axis wired backwards (a negative scale): the norm
    cannot see an axis's sign, so the fit has that scale positive and its calibrated output of
    that axis the opposite sign of the nominal's (a y axis wired backwards came back +0.99999
    for -1, with no word)."""
    neg = [n for n, v in zip("xyz", np.diag(np.asarray(nominal.K)), strict=True) if v < 0]
    if neg:
        axes = ", ".join(neg)
        _quiet.warn(
            f"the nominal model has a negative scale on {axes} (wired backwards): the norm "
            f"cannot see an axis's sign, so this fit has it positive and calibrates {axes} "
            "with the opposite sign of the nominal's (a mirrored triad); negate that column "
            "of the data before fitting and applying to keep the nominal's convention",
            UserWarning, stacklevel=3)


def _start(start: ArrayLike) -> list[float]:
    """A GN/LM start as a list, refused when a scale factor (its first three entries) is not
    positive: ``|K^-1 (a - b)|`` is the same with an axis mirrored, so such a start converges
    to a mirrored calibration (det K < 0) that fits the norms as well. The length and the
    other values are the core's to check."""
    v = real_array(start, "start").reshape(-1)
    sc = v[:3]
    bad = [f"{n} = {x:g}" for n, x in zip(PARAM_NAMES, sc, strict=False) if not x > 0]
    if bad:
        raise CalibrationError(
            f"start: the scale factors (sx, sy, sz, its first three entries) must be positive; "
            f"got {', '.join(bad)}. The norm |a| cannot tell an axis's sign, so this start "
            "would converge to a mirrored calibration (det K < 0) that fits as well: give "
            "positive scale factors, or no start (the exact quadric solution)"
        )
    return v.tolist()  # type: ignore[no-any-return]


def fit_quietly(data: DwellSet | ArrayLike, g: float, **kw: Any) -> StaticFit:
    """:func:`fit_static` for a check inside another step: no gravity check, and no warning (a
    weak design among them: the caller words what it found); refusals raise as ever."""
    with _quiet.quiet(), np.errstate(all="ignore"):
        return fit_static(data, g, check_g=False, **kw)


def _explained(e: CalibrationError, means: Any, g: float) -> CalibrationError | None:
    """The fit's refusal ``e`` with its likely cause first (dwells that cannot be at rest,
    or outputs that do not see gravity), or None to raise it as it is. Kept out of
    :func:`fit_static`, whose common call is timed in microseconds."""
    if not (isinstance(e, _core.DegenerateDataError) or "ran away" in str(e)):
        return None
    off = off_norm_dwells(means, g)
    if off is not None:  # the cause, before what the fit said with them in
        return type(e)(f"{off.text(g)}; leave them out (d[mask], or the rows of the array) "
                       f"and fit the others. With them in, the fit says: {e}")
    hint = _gravity_free_hint(means)
    return type(e)(f"{e}. {hint}") if hint else None


def _not_converged(fit: StaticFit, method: str, means: Any, g: float) -> CalibrationError:
    """The error of a fit that did not reach the minimum, with advice."""
    src = fit.start_source
    advice = ("use the default start (the exact quadric solution) or more iterations"
              if src == "user" else
              "the dwells may barely determine the model: check their attitudes (fit "
              "observability()), or give more iterations (max_iter=)")
    off = off_norm_dwells(means, g)
    if off is not None:  # the likely cause
        advice = f"{off.text(g)}; leave them out and fit the others"
    return CalibrationError(f"{method} did not reach the minimum in {fit.max_iter} iterations "
                            f"(start {fit.start.tolist()}, {src}); {advice}")


#: Set while :func:`off_norm_dwells` fits the other dwells (its failures get no hint).
_SCREENING: ContextVar[bool] = ContextVar("accelcal_off_norm_screening", default=False)


@dataclass(frozen=True)
class OffNorm:
    """Dwells that cannot be at rest (:func:`off_norm_dwells`): their indices, the norm of
    each mean (input units), the median norm of all dwells, each one's norm residual (units
    of g) under the bias + scale calibration of the other dwells, whose own residual RMS is
    ``rms``, the number of dwells screened, and whether their raw norms stood out (else only
    their calibrated norms did: the sensor's own scale errors spread the raw ones)."""

    index: tuple[int, ...]
    norm: tuple[float, ...]
    median_norm: float
    residual: tuple[float, ...]
    rms: float
    n_dwells: int
    raw_far: bool = True

    def text(self, g: float) -> str:
        """In words, for reference gravity ``g``."""
        n = self.n_dwells
        u = unit_label(g)
        rows = ", ".join(str(i) for i in self.index)
        lo, hi = min(self.norm), max(self.norm)
        r = [abs(x) for x in self.residual]
        if len(self.index) == 1:
            whose, norms, lie, them = "its mean's norm", f"{lo:.4g}", "lies", "it"
            off = f"{r[0]:.3g}"
        else:
            whose, norms, lie, them = ("their means' norms", f"{lo:.4g} to {hi:.4g}", "lie",
                                       "them")
            off = f"{min(r):.3g} to {max(r):.3g}"
        far = (f"{whose} ({norms}) {lie} far from every other dwell's (median "
               f"{self.median_norm:.4g}), and " if self.raw_far else "")
        return (f"{len(self.index)} of {n} dwells (#{rows}, counted from 0) cannot be at rest: "
                f"{far}the "
                f"bias + scale calibration of the others leaves {them} {off} {u} off g, "
                f"against {self.rms:.2g} {u} RMS for the others: recorded while moving, or a "
                "mistyped row")


def off_norm_dwells(data: DwellSet | ArrayLike, g: float) -> OffNorm | None:
    """Dwells whose means cannot be at rest (a row of a table of pose means recorded while
    the sensor moved, say): None when there are none.

    A dwell is a candidate when the norm of its mean lies further from the median norm than
    8 robust standard deviations (1.4826 MAD) of the dwells' norms and 5 % of the median or,
    when no norm does (an uncalibrated sensor whose norms spread widely from pose to pose),
    when the bias + scale calibration of all the dwells leaves it further from the median
    residual than 8 robust standard deviations of the residuals and 2 % of ``g``. A candidate
    is named when the bias + scale calibration of the other dwells leaves it more than 6 times
    their residual RMS and 2 % of ``g`` off ``g``. A sensor whose outputs carry large offsets
    has a calibration that fits every pose: none is found there. At most a quarter of the
    dwells are named; more than that is no longer a few bad rows. ``g`` is the reference
    gravity of the fit. None too while it screens (its own fits asking it again).
    """
    if _SCREENING.get():
        return None
    try:
        m = np.asarray(data.mean if isinstance(data, DwellSet) else data, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    if m.ndim != 2 or m.shape[1] != 3 or len(m) < 8 or not np.all(np.isfinite(m)):
        return None
    r = np.linalg.norm(m, axis=1)
    med = float(np.median(r))
    cand = _far_out(r, 0.05 * med)
    raw_far = cand.size > 0
    token = _SCREENING.set(True)
    try:
        if not raw_far:  # the raw norms spread too widely to tell: calibrated norms
            diag = fit_quietly(m, g, model="diag").to_model()
            res_all = np.linalg.norm(diag.apply(m, check_units=False), axis=1)
            cand = _far_out(res_all, 0.02 * g)
        if cand.size == 0 or cand.size > len(m) // 4:
            return None
        keep = np.setdiff1d(np.arange(len(m)), cand)
        fit = fit_quietly(m[keep], g, model="diag")
    except CalibrationError:
        return None
    finally:
        _SCREENING.reset(token)
    a = fit.to_model().apply(m, check_units=False)
    res = np.linalg.norm(a, axis=1) - g
    rms = float(np.sqrt(np.mean(res[keep] ** 2)))
    bad = [int(k) for k in cand if abs(res[k]) > max(6.0 * rms, 0.02 * g)]
    if not bad:
        return None
    return OffNorm(index=tuple(bad), norm=tuple(float(r[k]) for k in bad), median_norm=med,
                   residual=tuple(float(res[k]) for k in bad), rms=rms, n_dwells=len(m),
                   raw_far=raw_far)


def median_and_spread(x: NDArray[np.float64]) -> tuple[float, float]:
    """The median of ``x`` and its robust standard deviation about it: 1.4826 x the median
    absolute deviation (the std of normal data)."""
    med = float(np.median(x))
    return med, 1.4826 * float(np.median(np.abs(x - med)))


def _far_out(x: NDArray[np.float64], floor: float) -> NDArray[np.intp]:
    """Indices of ``x`` further from its median than 8 robust standard deviations (1.4826
    MAD) and ``floor``."""
    med, mad = median_and_spread(x)
    return np.flatnonzero(np.abs(x - med) > max(8.0 * mad, floor))


def without_off_norm(d: DwellSet, g: float) -> tuple[DwellSet, OffNorm | None]:
    """The dwells of ``d`` without those :func:`off_norm_dwells` names, and what it found."""
    off = off_norm_dwells(d, g)
    if off is None:
        return d, None
    keep = np.ones(len(d), dtype=bool)
    keep[list(off.index)] = False
    return d[keep], off


def distinct_poses(mean: ArrayLike) -> int:
    """Distinct poses among raw dwell means (k, 3): means closer than 5 % of their median
    norm (about 3 deg) are one pose. Outputs with offsets comparable to g merge poses here:
    a fit's :attr:`StaticFit.distinct_poses` counts on the calibrated directions."""
    m = np.ascontiguousarray(mean, dtype=np.float64).reshape(-1, 3)
    tol = _core.SAME_POSE * float(np.median(np.linalg.norm(m, axis=1)))
    return int(_core.gap_distinct_poses(m, tol))


def _gravity_free_hint(means: Any) -> str:
    """For dwells that cannot determine a calibration: when their norms differ by a quarter
    of their mean or more, the outputs may not see gravity at all (a sensor at rest reads
    about the same |g| in every pose); ``""`` otherwise."""
    try:
        m = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    except (TypeError, ValueError):
        return ""
    r = np.linalg.norm(m, axis=1)
    mu = float(np.mean(r)) if r.size else 0.0
    if not (math.isfinite(mu) and mu > 0) or float(np.std(r)) < 0.25 * mu:
        return ""
    return (f"The dwell means' norms differ by {float(np.std(r)) / mu:.0%} of their mean "
            "from dwell to dwell, while a sensor at rest reads about the same |g| in every "
            "pose: these outputs may not see gravity (a 'linear' or 'user' acceleration, from "
            "which a phone's or an AHRS's sensor fusion removed gravity, or not an "
            "accelerometer); calibrate the raw accelerometer output")


# ------------------------------------------------------------------------------------------
def fit_static_batch(
    means: ArrayLike | list[ArrayLike],
    g: float | ArrayLike,
    *,
    model: str = "lower",
    method: str = "lm",
    sigma: float | None = None,
    start: ArrayLike | None = None,
    max_iter: int = 200,
    degenerate_std: float = 3.0,
    weak_std: float = 1e-3,
    mask: ArrayLike | None = None,
    check_g: bool = True,
    sigma_g: float | None = None,
) -> BatchFit:
    """Fit B independent sessions of dwell means on all cores.

    ``means`` is a (B, n, 3) array, with an optional (B, n) boolean ``mask`` of the dwells to
    use (padding), or a list of (n_i, 3) arrays (sessions of different dwell counts). ``g`` is
    a scalar or (B,); ``sigma`` (scalar std of each dwell mean per axis, raw units) gives
    the noise, None estimates it per session. Never raises per session: each row has a
    ``status`` (0 ok, 1 degenerate, 2 not converged, 3 invalid input), ``state`` ("ok",
    "weak", "degenerate", "error") and ``messages`` ("session 17: dwell 3 has a NaN mean"; for a
    fitted session, the dwell whose norm residual exceeds 5 % of g: it may not be at rest).
    The interpreter is released during the work; results do not depend on the thread count.

    ``check_g`` (as for :func:`fit_static`) refuses, for the whole batch, a ``g`` that is not
    a plausible local gravity in m/s^2, g or cm/s^2 (the CalibrationError names the session
    of a (B,) ``g``); ``start`` is checked as there (positive scale factors). ``sigma_g``
    (std of the reference gravity, units of g, shared by all sessions) adds its term to every
    ``std`` as in :func:`fit_static`.
    """
    if isinstance(means, (list, tuple)):
        m: Any = [_as_means(x, f"session {i}") for i, x in enumerate(means)]
    else:
        m = real_array(means, "means", "output units")
        if m.ndim != 3 or m.shape[2] != 3:
            raise CalibrationError(f"means must have shape (B, n, 3); got {m.shape}")
    mk = None
    if mask is not None:
        mk = np.asarray(mask)
        if mk.dtype != np.bool_:
            raise CalibrationError(
                f"mask must be boolean (True for the dwells to use); got {mk.dtype}"
            )
    gv: Any = g if np.ndim(g) == 0 else np.asarray(g, dtype=np.float64).reshape(-1).tolist()
    if check_g:
        _check_batch_g(gv)
    st = None if start is None else _start(start)
    return _core.static_fit_batch(
        m,
        gv,
        model=cast(Any, model),
        method=cast(Any, method),
        sigma=sigma,
        start=st,
        max_iter=max_iter,
        degenerate_std=degenerate_std,
        weak_std=weak_std,
        mask=mk,
        sigma_g=sigma_g,
    )


def _check_batch_g(gv: Any) -> None:
    """:func:`fit_static`'s gravity check on a batch's scalar or per-session ``g``; values
    that are not positive finite numbers are left to the core, which names them."""
    try:
        vals = np.asarray(gv if isinstance(gv, list) else [gv], dtype=np.float64)
    except (TypeError, ValueError):
        return  # not numbers: the core says so
    # Each distinct value once (a fleet's sessions share a few g), at its first session.
    uniq, first = np.unique(vals, return_index=True)
    for x, i in sorted(zip(uniq.tolist(), first.tolist(), strict=True), key=lambda p: p[1]):
        if not (math.isfinite(x) and x > 0):
            continue
        why = _core.gravity_problem(x)
        if why is not None:
            where = f"g[{i}] (session {i}): " if isinstance(gv, list) else ""
            raise CalibrationError(f"{where}{why}")


# ------------------------------------------------------------------------------------------
#: The std of :func:`local_gravity` against a gravimeter, m/s^2 (local anomalies): the
#: ``sigma_g`` the command line and the fleet use with a g from a latitude.
LAT_FORMULA_SIGMA_G = 1e-3


def local_gravity(lat_deg: float, height_m: float = 0.0) -> float:
    """WGS84 normal gravity (Somigliana) at geodetic latitude ``lat_deg`` and ellipsoidal
    height ``height_m``, with the second-order free-air correction (about -3.086e-6 m/s^2 per
    m). Accuracy against a gravimeter: typically 1e-3 m/s^2 (local anomalies). Returns m/s^2.
    """
    try:
        lat = float(lat_deg)
        h = float(height_m)
    except (TypeError, ValueError):
        raise CalibrationError(
            f"latitude and height must be numbers; got {lat_deg!r}, {height_m!r}"
        ) from None
    if not (math.isfinite(lat) and -90.0 <= lat <= 90.0):
        raise CalibrationError(f"latitude must be in [-90, 90] degrees; got {lat_deg!r}")
    if not (math.isfinite(h) and -11000.0 <= h <= 50000.0):
        raise CalibrationError(f"height must be within -11 km .. 50 km (metres); got {height_m!r}")
    ge, k, e2 = 9.7803253359, 0.00193185265241, 0.00669437999013
    a, f, m = 6378137.0, 1.0 / 298.257223563, 0.00344978650684
    s2 = math.sin(math.radians(lat)) ** 2
    g0 = ge * (1.0 + k * s2) / math.sqrt(1.0 - e2 * s2)
    return g0 * (1.0 - 2.0 / a * (1.0 + f + m - 2.0 * f * s2) * h + 3.0 * h * h / (a * a))
