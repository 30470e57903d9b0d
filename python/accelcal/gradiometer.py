"""Gravity gradiometer per-startup bias by platform azimuth rotation (the procedure of the patent
on system-level calibration of the per-startup zero of a rotating-accelerometer gravity
gradiometer, generalised to any azimuth set).

A rotating-accelerometer gravity gradiometer on a stabilised, level platform has two outputs,
inline ``I = (Gxx - Gyy) / 2`` and cross ``C = Gxy`` (Eotvos, 1 E = 1e-9 s^-2), each with a
zero offset that changes at every power-on. Rotating the platform to azimuths ``theta_k``
rotates the navigation-frame gradient seen by the sensor but not the bias::

    y_k = bias + R(2 theta_k) gamma (+ drift (t_k - t_ref)) + e_k,
    R(2t) = [[cos 2t, sin 2t], [-sin 2t, cos 2t]],   gamma = (I, C) in the navigation frame,

so the bias follows by linear least squares (numerics in Rust). Frames: navigation x north,
y east, z down; the platform's x axis at azimuth ``theta`` (clockwise from north seen from
above); the disc phase is measured from the platform x axis towards y.
"""

from __future__ import annotations

import math
import os
import warnings
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._core import CalibrationError, DegenerateDataError
from ._tables import ANGLE_UNITS, GRADIENT_UNITS, TIME_UNITS, Col, read_table
from ._validate import bounds_array, number, positive, real_array

__all__ = [
    "Demodulated",
    "StartupBias",
    "StartupCalibration",
    "StartupMisfitWarning",
    "calibrate_gradiometer_table",
    "demodulate",
    "startup_bias",
]

PARAM_NAMES = ("bias_I", "bias_C", "I", "C", "drift_I", "drift_C")
_F64 = NDArray[np.float64]

#: With ``sigma`` given, residuals whose chi2 has an upper-tail probability below this exceed
#: the noise model (a warning and a note in the summary).
MISFIT_P = 1e-3
#: The azimuths are refused as radians when, read as radians, they leave a (whitened) residual
#: sum of squares this many times smaller than read as degrees.
UNIT_RATIO = 1e3
#: Radians of whole multiples of this many degrees, to within ``_ROUND_TOL_DEG``, look like a
#: design in degrees converted to radians (a session whose data cannot tell the readings apart).
_ROUND_STEP_DEG = 2.5
_ROUND_TOL_DEG = 1e-3
#: Azimuths spanning under ``_NARROW_DEG`` deg as degrees but at least ``_WIDE_DEG`` deg read
#: as radians, all within +-(2 pi + ``_RAD_SLACK``) and not all whole multiples of
#: ``_TYPED_STEP_DEG`` deg, are refused as radians (:func:`_narrow_radians`).
_NARROW_DEG = 10.0
#: Outputs all below this in magnitude (but not all zero), E, look like s^-2 (or m/s^2);
#: any above ``_HUGE_E`` look like raw counts or unconverted units (``check_units``).
_TINY_E = 1e-3
_HUGE_E = 1e7
#: A disc radius above this many metres looks like millimetres given as metres.
_MAX_RADIUS_M = 5.0
_WIDE_DEG = 45.0
_RAD_SLACK = 0.1
_TYPED_STEP_DEG = 0.1
#: Azimuth error stds above this many degrees are refused: far beyond a platform's azimuth
#: repeatability (of order 0.01 to 1 deg), beyond the first-order term, and most likely
#: another unit (arcmin, arcsec, mrad) given as deg.
_MAX_SIGMA_THETA_DEG = 5.0


class StartupMisfitWarning(UserWarning):
    """With ``sigma`` given, the residuals of a start-up fit exceed that noise (chi2 p-value
    below :data:`MISFIT_P`): the std quoted, which come from ``sigma``, are too small."""


# ------------------------------------------------------------------------------------------
# Input coercion
# ------------------------------------------------------------------------------------------
def _azimuths(x: ArrayLike, name: str = "azimuths") -> _F64:
    a = real_array(x, name, "deg").reshape(-1)
    if a.size == 0:
        raise CalibrationError(f"no {name} given")
    if not np.all(np.isfinite(a)):
        raise CalibrationError(
            f"{name} contain NaN or inf at {np.where(~np.isfinite(a))[0].tolist()}"
        )
    far = np.abs(a) > _AZIMUTH_MAX_DEG
    if np.any(far):
        i = int(np.argmax(far))
        raise CalibrationError(
            f"{name}[{i}] = {a[i]:.6g} deg cannot be an azimuth: beyond +-{_AZIMUTH_MAX_DEG:g} "
            "deg a double no longer holds the angle to 1e-6 deg (at 1e17 deg its step is 16 "
            "deg); give the platform angle in degrees, wrapped or unwrapped"
        )
    return a


#: Largest |azimuth| taken, deg: a double's step there is 1.2e-7 deg.
_AZIMUTH_MAX_DEG = 1e9


def _outputs(x: ArrayLike, m: int) -> _F64:
    y = real_array(x, "outputs", "E")
    if y.ndim == 1 and y.size == 2 and m == 1:
        y = y.reshape(1, 2)
    if y.shape != (m, 2):
        raise CalibrationError(
            f"outputs must have shape ({m}, 2) (inline, cross per azimuth, E); got {y.shape}"
        )
    if not np.all(np.isfinite(y)):
        bad = np.where(~np.all(np.isfinite(y), axis=1))[0]
        raise CalibrationError(f"outputs contain NaN or inf at dwell(s) {bad.tolist()}")
    return y


def _times(t: ArrayLike | None, m: int, name: str = "t") -> _F64 | None:
    if t is None:
        return None
    a = real_array(t, name, "s").reshape(-1)
    if a.shape != (m,):
        raise CalibrationError(f"{name} must have shape ({m},) (one time per azimuth, s)")
    if not np.all(np.isfinite(a)):
        raise CalibrationError(f"{name} contains NaN or inf")
    return a


def _dwell_std(sigma: Any, m: int) -> _F64:
    if sigma is None or isinstance(sigma, (str, bytes, bool)):
        raise CalibrationError(
            f"sigma must be a positive number or ({m},) numbers (E, noise std of an average); "
            f"got {sigma!r}"
        )
    s = real_array(sigma, "sigma", "E")
    if s.ndim == 0:
        s = np.full(m, float(s))
    if s.ndim > 1 and s.size == m and max(s.shape) == m:  # a column or a row of m
        s = s.reshape(-1)
    if s.shape != (m,):  # named as given: an (m, 2) array is not m numbers
        raise CalibrationError(
            f"sigma must be a number or have shape ({m},) (one noise std per azimuth, E); "
            f"got shape {s.shape}"
        )
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise CalibrationError(
            f"sigma must be positive and finite (E, noise std of an average); got {sigma!r}"
        )
    return s


def _sigma_theta(x: Any) -> float:
    """The std of independent azimuth errors, deg: finite, >= 0 and at most
    :data:`_MAX_SIGMA_THETA_DEG`; otherwise a CalibrationError that names the unit."""
    st = float(number(x, "sigma_theta", lo=0.0, unit="deg"))
    if st > _MAX_SIGMA_THETA_DEG:
        raise CalibrationError(
            f"sigma_theta is the std of independent azimuth errors in deg; {st:g} deg is not "
            f"a platform's azimuth repeatability (of order 0.01 to 1 deg; above "
            f"{_MAX_SIGMA_THETA_DEG:g} deg refused, where the first-order term no longer "
            f"holds): arcmin, arcsec or mrad given as deg? give it in deg (6 arcmin = 360 "
            f"arcsec = 1.745 mrad = 0.1 deg; np.degrees(x) for x in rad)"
        )
    return st


def _output_units(y: _F64, what: str, fix: str) -> str | None:
    """Why outputs meant in E are plainly in other units, or None: every ``|value|`` below
    :data:`_TINY_E` E (not all zero: s^-2 or m/s^2 given as E), or any above :data:`_HUGE_E`
    E (raw counts, or m/s^2 / s^-2 scaled wrongly). Gravity gradients and gradiometer
    biases are of order 1 to 1e4 E."""
    big = float(np.max(np.abs(y))) if y.size else 0.0
    if 0.0 < big < _TINY_E:
        return (
            f"the {what} look like s^-2 (or m/s^2), not E: every value is below {_TINY_E:g} E "
            f"(largest |value| {big:.3g}, spread {float(np.ptp(y)):.3g}) where gravity "
            f"gradients and biases are of order 1 to 1e4 E (1 E = 1e-9 s^-2); multiply "
            f"s^-2 by 1e9, {fix}"
        )
    if big > _HUGE_E:
        return (
            f"the {what} are far too large for E: largest |value| {big:.3g} E (above "
            f"{_HUGE_E:g} E, where gravity gradients and biases are of order 1 to 1e4 E): "
            f"raw counts, or values not converted to E? convert them, {fix}"
        )
    return None


# ------------------------------------------------------------------------------------------
# Estimator
# ------------------------------------------------------------------------------------------
class StartupBias(_core.StartupBiasCore):
    """Per-startup bias, navigation-frame gradient (and drift) with covariance (the data live
    in the Rust result; arrays are read-only; pickles).

    Attributes
    ----------
    bias : (2,) float
        Per-startup bias of the inline and cross channels, E (at ``t_ref`` with drift).
    gradient : (2,) float
        Navigation-frame gradient ``(I, C)``, E.
    drift : (2,) float or None
        Linear bias drift, E/s (``drift=True`` only).
    covariance : (p, p) float
        Covariance ordered ``[bias_I, bias_C, I, C, (drift_I, drift_C)]``, E^2 (E^2/s, E^2/s^2
        for drift), the azimuth errors' part (``azimuth_covariance``) included. NaN when
        ``sigma`` was not given and the design has no redundancy.
    std : (p,) float
        Square roots of the covariance diagonal.
    sigma_theta : float
        Std of the independent azimuth errors allowed for, deg (0: none).
    azimuth_covariance : (p, p) float
        The part of ``covariance`` from those azimuth errors: first order, evaluated at the
        fitted gradient (zero when ``sigma_theta`` is 0).
    chi2_scale, chi2_dof : float
        With ``sigma`` given, ``chi2`` is tested as ``chi2_scale * chi2(chi2_dof)``, which
        allows for the residuals the azimuth errors leave (Satterthwaite); 1 and ``dof``
        without them.
    residuals : (m, 2) float
        ``y_k - model_k``, E.
    unit_covariance : (p, p) float
        ``(A^T W A)^-1``: the covariance per unit noise variance (absolute when ``sigma`` was
        given per dwell).
    sigma : (m,) float or None
        Noise std of each average used for the covariance, E (given or estimated).
    sigma_estimated : bool
        True when ``sigma`` was estimated from the residuals.
    sigma_source : str
        Where ``sigma`` came from, as the summary says it: ``"given"``, ``"from the streams"``
        (``StartupCalibration(sigma="stream")``: each dwell's own standard error) or
        ``"estimated from residuals"``.
    dof : int
        Redundancy ``2m - p``.
    condition : float
        Condition number of the column-scaled design.
    azimuth_deg, t : (m,) float
        The design (``t`` None without drift); ``t_ref`` the drift reference time, s.
    names : list of str
        Parameter names in covariance order.
    """

    __slots__ = ()
    #: where a non-estimated ``sigma`` came from (see :class:`_StartupBiasFromStreams`)
    _given_sigma: ClassVar[str] = "given"

    def __repr__(self) -> str:
        b, sd = np.asarray(self.bias), np.asarray(self.bias_std)
        return (f"StartupBias(dwells={len(self.azimuth_deg)}, bias_E=[{b[0]:.4g}, {b[1]:.4g}], "
                f"std_E=[{sd[0]:.2g}, {sd[1]:.2g}], dof={self.dof})")

    @property
    def sigma_source(self) -> str:
        """Where ``sigma`` came from: ``"given"``, ``"from the streams"`` or ``"estimated from
        residuals"`` (``""`` without a sigma)."""
        if self.sigma is None:
            return ""
        return "estimated from residuals" if self.sigma_estimated else self._given_sigma

    @property
    def params(self) -> _F64:
        """All parameters in covariance order."""
        parts = [self.bias, self.gradient] + ([self.drift] if self.drift is not None else [])
        return np.concatenate(parts)

    @property
    def bias_std(self) -> _F64:
        """Standard deviations of the bias, E."""
        return self.std[:2]

    @property
    def gradient_std(self) -> _F64:
        """Standard deviations of the gradient, E."""
        return self.std[2:4]

    @property
    def chi2(self) -> float:
        """``sum (residual / sigma)^2`` over both channels with ``sigma`` given; NaN when
        ``sigma`` was estimated or not given."""
        if self.sigma is None or self.sigma_estimated:
            return math.nan
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            return float(np.sum((self.residuals / self.sigma[:, None]) ** 2))

    @property
    def chi2_p(self) -> float:
        """Probability of a chi2 this large or larger under chi2(dof) when ``sigma`` is right
        (NaN without a given ``sigma`` or without residual degrees of freedom)."""
        c = self.chi2
        if self.dof <= 0 or math.isnan(c):
            return math.nan
        if math.isinf(c):
            return 0.0
        if self.sigma_theta > 0:  # residuals of noise and azimuth errors: a scaled chi2
            return float(_core.chi2_sf(c / self.chi2_scale, self.chi2_dof))
        return float(_core.chi2_sf(c, float(self.dof)))

    def misfit_text(self) -> str | None:
        """Why the std quoted are too small, when the residuals exceed the given ``sigma``
        (chi2 p-value below :data:`MISFIT_P`); None otherwise."""
        p = self.chi2_p
        if not p < MISFIT_P:
            return None
        if self.sigma_theta > 0:
            want = self.chi2_scale * self.chi2_dof
            r = self.chi2 / want
            return (
                f"residuals exceed the noise and azimuth-error model (chi2 {self.chi2:.3g} on "
                f"{self.dof} dof where sigma and sigma_theta {self.sigma_theta:g} deg lead to "
                f"expect {want:.3g}, p = {p:.2g}): they are {math.sqrt(r):.3g} times what "
                "that model allows, so the std quoted are too small; suspect wrong azimuths "
                "(units, sign or zero), a wrong sigma or sigma_theta, or a platform error"
            )
        r = self.chi2 / self.dof
        return (
            f"residuals exceed the noise model (chi2/dof {r:.3g} on {self.dof} dof, p = "
            f"{p:.2g}): they are {math.sqrt(r):.3g} times the given noise std, so the std "
            "quoted (from sigma) are too small; suspect wrong azimuths (units, sign or zero), "
            "a wrong sigma, or a platform error"
        )

    def summary(self) -> str:
        """A readable block: estimates with standard deviations."""
        units = {"bias": "E", "I": "E", "C": "E", "drift": "E/s"}
        lines = [
            f"start-up bias from {len(self.azimuth_deg)} azimuths "
            f"({', '.join(f'{a:g}' for a in self.azimuth_deg)} deg), dof {self.dof}, "
            f"condition {self.condition:.3g}"
        ]
        for n, v, s in zip(self.names, self.params, self.std, strict=True):
            u = units[n.split("_")[0]]
            lines.append(f"  {n:<8} {v:>14.6g} +- {s:<10.3g} {u}")
        if self.dof <= 0 and not np.all(np.isfinite(self.std)):
            lines.append(
                f"  std n/a: {len(self.azimuth_deg)} azimuths leave no residual degree of "
                "freedom to estimate the noise from (the solution fits them exactly); give "
                "sigma= (the noise std of an average, E) or add azimuths")
        if self.sigma is not None:
            lines.append(f"  noise std of an average: {np.mean(self.sigma):.3g} E "
                         f"({self.sigma_source})")
            if self.sigma_estimated and 0 < self.dof < 10:
                rel = 1.0 / np.sqrt(2.0 * self.dof)
                lines.append(
                    f"  caution: sigma comes from only {self.dof} residual degree(s) of freedom, "
                    f"so it and every std above are uncertain by about +-{100 * rel:.0f} % "
                    "(give sigma= from the dwell noise, or add azimuths)"
                )
        if self.sigma_theta > 0:
            az_sd = np.sqrt(np.diag(self.azimuth_covariance)[:2])
            lines.append(
                f"  azimuth errors: {self.sigma_theta:g} deg (independent), at the fitted "
                f"gradient {az_sd[0]:.3g}, {az_sd[1]:.3g} E of the bias std (in quadrature, "
                "included above)"
            )
        misfit = self.misfit_text()
        if misfit is not None:
            lines.append(f"  note: {misfit}")
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.summary()

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return {
            "names": list(self.names),
            "bias_E": self.bias.tolist(),
            "gradient_E": self.gradient.tolist(),
            "drift_E_per_s": None if self.drift is None else self.drift.tolist(),
            "covariance": self.covariance.tolist(),
            "std": self.std.tolist(),
            "residuals_E": self.residuals.tolist(),
            "sigma_E": None if self.sigma is None else self.sigma.tolist(),
            "sigma_estimated": self.sigma_estimated,
            "chi2": self.chi2 if math.isfinite(self.chi2) else None,
            "chi2_p": self.chi2_p if math.isfinite(self.chi2_p) else None,
            "dof": self.dof,
            "condition": self.condition,
            "azimuth_deg": self.azimuth_deg.tolist(),
            "t_s": None if self.t is None else self.t.tolist(),
            "t_ref_s": self.t_ref,
            "sigma_theta_deg": self.sigma_theta,
            "azimuth_covariance": self.azimuth_covariance.tolist(),
        }


class _StartupBiasFromStreams(StartupBias):
    """A :class:`StartupBias` whose ``sigma`` is each dwell's standard error from the
    demodulated streams (``StartupCalibration(sigma="stream")``); it pickles as such."""

    __slots__ = ()
    _given_sigma: ClassVar[str] = "from the streams"


def startup_bias(
    azimuth_deg: ArrayLike,
    outputs: ArrayLike,
    *,
    t: ArrayLike | None = None,
    drift: bool = False,
    sigma: float | ArrayLike | None = None,
    t_ref: float | None = None,
    check_units: bool = True,
    sigma_theta: float = 0.0,
) -> StartupBias:
    """Per-startup bias of the inline and cross channels by least squares.

    Parameters
    ----------
    azimuth_deg : (m,) float
        Platform azimuth of each dwell, deg.
    outputs : (m, 2) float
        Average inline and cross output at each azimuth, E.
    t : (m,) float, optional
        Dwell mid times, s (needed with ``drift=True``).
    drift : bool
        Also fit a linear bias drift ``bias(t) = bias + drift (t - t_ref)``.
    sigma : float or (m,) float, optional
        Known noise std of an average (per dwell when an array), E. When None it is estimated
        from the residuals (needs redundancy, ``2m > p``); otherwise the covariance is NaN.
    t_ref : float, optional
        Reference time of the bias with drift, s; default the mean of ``t`` (the centre of
        the sequence, where a time-symmetric sequence decorrelates drift from bias).
    check_units : bool
        Refuse azimuths that look like radians and outputs that plainly are not in E (see
        Raises); False fits them as given whatever they look like.
    sigma_theta : float
        Std of independent azimuth errors of the platform (its azimuth repeatability), deg;
        0 (the default) leaves them out. Their first-order effect, evaluated at the gradient
        fitted to these data (an error ``dtheta_k`` moves the outputs by ``2 dtheta_k
        R'(2 theta_k) gamma``), is added to the covariance; it is the
        ``azimuth_covariance`` of :func:`predict_startup_accuracy` with ``gradient`` the
        fitted one, about ``sqrt(2) sigma_theta |gamma| / sqrt(m)`` on the bias std for a
        balanced set. A common offset of all azimuths does not affect the bias and does not
        belong here. With ``sigma`` estimated, the share of the residuals the azimuth errors
        are expected to leave is taken out of the noise estimate first (so it is not counted
        twice); with ``sigma`` given, ``chi2_p`` allows for it. Refused above 5 deg.

    Returns
    -------
    StartupBias
        With ``sigma`` given, ``chi2`` / ``chi2_p`` test the residuals against it (and
        ``sigma_theta``).

    Raises
    ------
    DegenerateDataError
        When the azimuth set cannot separate bias and gradient (e.g. 0/180 deg), with why.
    CalibrationError
        When every azimuth lies within +-2 pi and either (a) read as radians they fit the
        data far better than read as degrees (whitened residual sum of squares
        :data:`UNIT_RATIO` times smaller, and with ``sigma`` given the radians reading
        within the noise, chi2 p >= :data:`MISFIT_P`, and the degrees reading not), or (b)
        they are radians of whole multiples of 2.5 deg (to 1e-3 deg: ``np.radians(45)``)
        and the data do not favour the degrees reading that much, or (c) read as degrees they
        span under 10 deg while read as radians they span 45 deg or more (all within
        +-(2 pi + 0.1)), unless every azimuth is a whole multiple of 0.1 deg (a tiny design
        typed in degrees, such as 0, 1, 2, 3, is not refused; measured or converted radians
        such as 0.0122, 1.5865 are). Also, with ``check_units``, outputs whose every
        ``|value|`` is below 1e-3 E (not all zero: s^-2 or m/s^2 given as E) or any above
        1e7 E (raw counts, unconverted units). Always: ``sigma_theta`` negative, not finite,
        not a number, or above 5 deg (arcmin, arcsec or mrad given as deg?).

    Warns
    -----
    StartupMisfitWarning
        With ``sigma`` given and residual degrees of freedom, when the residuals exceed it
        (chi2 p-value below :data:`MISFIT_P`); the summary says so too.
    """
    az = _azimuths(azimuth_deg, "azimuth_deg")
    m = az.size
    y = _outputs(outputs, m)
    tt = _times(t, m)
    if drift and tt is None:
        raise CalibrationError("drift=True needs the dwell times t (s)")
    tref = None
    if drift and t_ref is not None:
        tref = number(t_ref, "t_ref", unit="s")
    if check_units:
        why = _output_units(y, "outputs", "or check_units=False if they are E")
        if why is not None:
            raise CalibrationError(why)
    sd = None if sigma is None else _dwell_std(sigma, m)
    st = _sigma_theta(sigma_theta)
    td = tt if drift else None
    raw = _core.startup_bias_raw(az, y, sd, td, tref, st)
    fit = StartupBias(*raw.__reduce__()[1])
    hint = None
    if check_units:
        refuse, hint = _radians_check(az, y, sd, td, tref, fit)
        if refuse is not None:
            raise CalibrationError(refuse)
    misfit = fit.misfit_text()
    if misfit is not None:
        warnings.warn(misfit + ("" if hint is None else f"; {hint}"), StartupMisfitWarning,
                      stacklevel=2)
    return fit


def _list(v: _F64, n: int = 8) -> str:
    """At most ``n`` numbers, comma separated."""
    words = [f"{x:g}" for x in v[:n]]
    return ", ".join(words + (["..."] if v.size > n else []))


def _narrow_radians(az: _F64) -> str | None:
    """Why azimuths given as degrees are plainly radians by their spread alone, or None: all
    within +-(2 pi + :data:`_RAD_SLACK`), spanning under :data:`_NARROW_DEG` deg read as
    degrees but at least :data:`_WIDE_DEG` deg read as radians, and not all whole multiples
    of :data:`_TYPED_STEP_DEG` deg (a tiny design typed in degrees, such as 0, 1, 2, 3 or
    0.3, 1.2, 2.7, is round; radians from a measured or converted design are not)."""
    if az.size < 2 or not np.all(np.abs(az) <= 2.0 * np.pi + _RAD_SLACK):
        return None
    span = float(np.ptp(az))
    span_rad = math.degrees(span)
    if not (0.0 < span < _NARROW_DEG and span_rad >= _WIDE_DEG):
        return None
    step = az / _TYPED_STEP_DEG
    if np.all(np.abs(step - np.round(step)) <= 1e-9 * np.maximum(1.0, np.abs(step))):
        return None
    return (
        f"the azimuths look like radians, not degrees: they ({_list(az)}) span only "
        f"{span:.3g} deg, but read as radians ({_list(np.degrees(az))} deg) {span_rad:.3g} "
        f"deg (a start-up design spans tens of degrees; one under {_NARROW_DEG:g} deg barely "
        "separates bias from gradient)"
    )


def _radians_check(
    az: _F64, y: _F64, sd: _F64 | None, t: _F64 | None, t_ref: float | None, fit: StartupBias
) -> tuple[str | None, str | None]:
    """Whether azimuths given as degrees look like radians: ``(why to refuse, hint)``.

    Only azimuths that all lie within +-2 pi (and are not all 0) are candidates. The same
    data are fitted with the azimuths read as radians and the two (whitened) residual sums of
    squares compared: see :func:`startup_bias` (Raises) for the rule. The hint (for the misfit
    warning) is set when, with ``sigma`` given, the radians reading fits markedly (10x)
    better without meeting the rule.
    """
    fix = ("pass np.degrees(azimuth) as azimuth_deg, or check_units=False if they are "
           "degrees")
    refuse, hint = _radians_by_fit(az, y, sd, t, t_ref, fit, fix)
    if refuse is None:
        narrow = _narrow_radians(az)
        if narrow is not None:
            return f"{narrow}; {fix}", None
    return refuse, hint


def _radians_by_fit(
    az: _F64, y: _F64, sd: _F64 | None, t: _F64 | None, t_ref: float | None, fit: StartupBias,
    fix: str,
) -> tuple[str | None, str | None]:
    """Rules (a) and (b) of :func:`startup_bias` (Raises): the two readings' fits compared,
    and radians of round degrees."""
    if not (np.any(az != 0.0) and np.all(np.abs(az) <= 2.0 * np.pi * (1.0 + 1e-12))):
        return None, None
    deg = np.degrees(az)
    try:
        alt = _core.startup_bias_raw(deg, y, sd, t, t_ref)
    except CalibrationError:  # degenerate as radians (e.g. 0 and pi): not that reading
        return None, None
    w = (np.ones(az.size) if sd is None else 1.0 / sd)[:, None]
    with np.errstate(over="ignore", invalid="ignore"):
        rss_d = float(np.sum((fit.residuals * w) ** 2))
        rss_r = float(np.sum((alt.residuals * w) ** 2))
        floor = 1e-18 * float(np.sum((y * w) ** 2))  # a residual at rounding level
    if not (math.isfinite(rss_d) and math.isfinite(rss_r) and math.isfinite(floor)):
        return None, None
    dof = fit.dof
    head = (f"the azimuths look like radians, not degrees: all lie within +-2 pi "
            f"({_list(az)})")
    if dof > 0 and rss_d > UNIT_RATIO * max(rss_r, floor):
        if sd is None:
            ratio = math.sqrt(rss_d / max(rss_r, floor))
            return (
                f"{head}, and read as radians ({_list(deg)} deg) they fit the data with "
                f"residuals {ratio:.3g} times smaller (rms {math.sqrt(rss_r / dof):.3g} E "
                f"against {math.sqrt(rss_d / dof):.3g} E read as degrees); {fix}"
            ), None
        p_d = float(_core.chi2_sf(rss_d, float(dof)))
        p_r = float(_core.chi2_sf(rss_r, float(dof)))
        if p_r >= MISFIT_P > p_d:
            return (
                f"{head}, and read as radians ({_list(deg)} deg) they fit the data within the "
                f"given noise (chi2 {rss_r:.3g} on {dof} dof, p = {p_r:.2g}) where read as "
                f"degrees they do not (chi2 {rss_d:.3g}, p = {p_d:.2g}); {fix}"
            ), None
    off = np.abs(deg - np.round(deg / _ROUND_STEP_DEG) * _ROUND_STEP_DEG)
    if np.all(off <= _ROUND_TOL_DEG) and not rss_r > UNIT_RATIO * max(rss_d, floor):
        why = ("leave no residual to tell the two readings apart" if dof <= 0
               else "do not tell the two readings apart")
        return (
            f"{head}, which are {_list(deg)} deg in radians, and the data {why}; {fix}"
        ), None
    if sd is not None and dof > 0 and rss_d > 10.0 * max(rss_r, floor):
        return None, (
            f"read as radians ({_list(deg)} deg) the azimuths leave chi2/dof "
            f"{rss_r / dof:.3g} instead of {rss_d / dof:.3g}: if they are radians, pass "
            "np.degrees(azimuth) as azimuth_deg"
        )
    return None, None


# ------------------------------------------------------------------------------------------
# Sequence design
# ------------------------------------------------------------------------------------------
# ------------------------------------------------------------------------------------------
# 2-omega demodulation
# ------------------------------------------------------------------------------------------
class Demodulated(_core.DemodulatedCore):
    """Per-dwell inline and cross channels from raw rotating-accelerometer streams (the data
    live in the Rust result; arrays are read-only; pickles).

    Attributes
    ----------
    inline_E, cross_E : (k,) float
        Demodulated channels, E (samples in m/s^2).
    std_inline_E, std_cross_E : (k,) float
        White-noise standard errors from the fit residuals, E.
    outputs : (k, 2) float
        ``inline_E`` and ``cross_E`` as columns, E: the per-dwell outputs that
        ``startup_bias`` and ``diagnose_gradiometer`` take.
    std : (k, 2) float
        ``std_inline_E`` and ``std_cross_E`` as columns, E (``std.mean()`` is a ``sigma=`` for
        them).
    start, stop : (k,) int
        Samples used: ``[start, stop)`` covers whole revolutions from the dwell start.
    revolutions : (k,) int
        Whole revolutions used.
    resid_rms : (k,) float
        RMS residual of ``(a1 + a3) - (a2 + a4)`` after the fit, input units.
    nuisance : (k, 3) float
        Constant, cos and sin 1-omega terms of the combination, input units.
    t : (k,) float or None
        Mid time of the samples used, s.
    """

    __slots__ = ()

    @property
    def outputs(self) -> _F64:
        """``(k, 2)`` inline and cross, E."""
        return np.column_stack([self.inline_E, self.cross_E])

    @property
    def std(self) -> _F64:
        """``(k, 2)`` standard errors, E."""
        return np.column_stack([self.std_inline_E, self.std_cross_E])


def _accel(x: ArrayLike) -> NDArray[Any]:
    a = np.asarray(x)
    if a.dtype.kind not in "fiu":
        raise CalibrationError(
            f"accel must be real numbers (m/s^2); got dtype {a.dtype}"
        )
    if a.ndim != 2 or a.shape[1] != 4:
        raise CalibrationError(f"accel must have shape (N, 4) (a1..a4 per row); got {a.shape}")
    if a.shape[0] == 0:
        raise CalibrationError("accel is empty (0 rows)")
    if a.dtype not in (np.float64, np.float32, np.int16, np.int32) or not a.dtype.isnative:
        a = a.astype(np.float64)
    return a


#: A dwell of at least this many samples is checked for dead, stuck and clipped channels.
_CHANNEL_MIN_SAMPLES = 30
#: A channel with more than this fraction of a dwell's samples on its largest (or smallest)
#: value, and more than ``_RAIL_PILEUP`` times as many as on its next value, is on a rail.
_RAIL_FRACTION = 0.02
_RAIL_PILEUP = 4.0


def _channel_faults(a: NDArray[Any], b: NDArray[Any]) -> str | None:
    """Why an accelerometer channel of a dwell did not follow the sensor, or None: see
    :func:`demodulate` (Raises). Per dwell, vectorised over the four channels. As for
    :meth:`accelcal.DwellSet.faults`, constancy is a fault only where the noise is otherwise
    resolvable: when no channel of any dwell varies, the data are below the resolution."""
    spans = [(k, s0, s1) for k, (s0, s1) in enumerate(np.asarray(b).tolist())
             if s1 - s0 >= _CHANNEL_MIN_SAMPLES]
    stats = []  # per dwell: largest, smallest and how many samples on each, per channel
    for _, s0, s1 in spans:
        xt = np.ascontiguousarray(a[s0:s1].T)  # a channel per row: reductions several x faster
        hi, lo = xt.max(axis=1), xt.min(axis=1)
        stats.append((hi, lo, np.count_nonzero(xt == hi[:, None], axis=1),
                      np.count_nonzero(xt == lo[:, None], axis=1)))
    resolvable = any(bool(np.any(hi != lo)) for hi, lo, _, _ in stats)
    for (k, s0, s1), (hi, lo, on_hi, on_lo) in zip(spans, stats, strict=True):
        n = s1 - s0
        where = f"dwell {k} (samples {s0}..{s1})"
        const = np.flatnonzero(hi == lo).tolist()
        if const and resolvable:
            c = const[0]
            v = float(hi[c])
            what = ("all zero: a dead channel" if v == 0.0
                    else f"constant at {v:.10g}: a stuck channel")
            if len(const) == 4:
                what += " (all four channels constant: a frozen output)"
            return (
                f"accelerometer a{c + 1} of {where} is {what} (all {n} samples the same), so "
                "the demodulated inline and cross channels are wrong by the gradient signal "
                "it should have carried; check that accelerometer and its logging, or "
                "check_channels=False to demodulate as given"
            )
        for side, val, on in (("largest", hi, on_hi), ("smallest", lo, on_lo)):
            for c in np.flatnonzero((on > _RAIL_FRACTION * n) & (hi != lo)).tolist():
                col = a[s0:s1, c]
                rest = col[col != val[c]]
                nxt = rest.max() if side == "largest" else rest.min()
                if on[c] <= _RAIL_PILEUP * np.count_nonzero(rest == nxt):
                    continue  # a coarsely quantised peak, not a pile-up on a rail
                return (
                    f"accelerometer a{c + 1} of {where}: {int(on[c])} of {n} samples "
                    f"({100.0 * on[c] / n:.2g} %) at {float(val[c]):.10g}, its {side} value, "
                    f"with the rest {'below' if side == 'largest' else 'above'}: clipped at "
                    "the sensor's range (a rail), so the demodulated inline and cross "
                    "channels are biased; reduce the gain or range, or check_channels=False "
                    "to demodulate as given"
                )
    return None


#: A wrap period within this fraction of 360 (the wrap jumps plus one step) is degrees.
_PHASE_PERIOD_TOL = 0.05


def _phase_in_degrees(ph: _F64) -> str | None:
    """Why the spin phase ``ph`` (meant in radians) plainly is in degrees, or None: see
    :func:`demodulate` (Raises) for the rule. Non-finite values are left to the core."""
    v = ph[np.isfinite(ph)]
    if v.size < 3:
        return None
    d = np.diff(v)
    step = float(np.median(d))
    if step == 0.0 or not math.isfinite(step):
        return None
    fix = ("pass np.radians(phase) (or np.deg2rad), or check_units=False if it is in "
           "radians")
    span = float(np.ptp(v))
    back = d[d * step < 0.0]  # steps against the spin: wraps (or glitches)
    wraps = np.abs(back[np.abs(back) > np.pi])
    if wraps.size:
        period = float(np.median(wraps)) + abs(step)
        if (abs(period - 360.0) <= _PHASE_PERIOD_TOL * 360.0
                and 2.0 * np.pi * (1.0 + _PHASE_PERIOD_TOL) < span
                <= 360.0 * (1.0 + _PHASE_PERIOD_TOL)):
            return (
                f"the phase looks like degrees, not radians: it wraps around {wraps.size} "
                f"time(s) by about {float(np.median(wraps)):.4g} (a period of about "
                f"{period:.4g}, where radians wrap by 2 pi = 6.283) and its values span "
                f"{span:.4g} (from {float(v.min()):.4g} to {float(v.max()):.4g}; a phase "
                f"wrapped in radians spans at most 2 pi); {fix}"
            )
        return None
    if np.pi < abs(step) <= 90.0:
        return (
            f"the phase looks like degrees, not radians: it advances {abs(step):.4g} per "
            f"sample (median), which read as radians is more than half a turn per sample "
            f"(the spin and its 2-omega signal cannot be sampled so) and read as degrees "
            f"{360.0 / abs(step):.3g} samples per turn; {fix}"
        )
    return None


def demodulate(
    accel: ArrayLike,
    phase: ArrayLike,
    bounds: ArrayLike | None = None,
    *,
    radius_m: float,
    t: ArrayLike | None = None,
    check_units: bool = True,
    check_channels: bool = True,
) -> Demodulated:
    """Inline and cross channels per dwell by 2-omega demodulation (numerics in Rust).

    Forms ``d = (a1 + a3) - (a2 + a4) = 4R [I sin 2phi - C cos 2phi] + ...`` and, over whole
    revolutions from each dwell start, fits ``d = c0 + c1 cos phi + s1 sin phi + c2 cos 2phi +
    s2 sin 2phi`` by least squares: ``I = s2 / 4R``, ``C = -c2 / 4R``. Linear and angular
    acceleration cancel in ``d``; the 1-omega terms absorb what scale mismatch lets through
    of a tilt.

    Parameters
    ----------
    accel : (N, 4) float64/float32 (or int16/int32)
        Tangential accelerometer outputs a1..a4, m/s^2 (a1 at phase ``phi``, a_i at
        ``phi + (i - 1) pi / 2``).
    phase : (N,) float
        Spin phase of accelerometer 1, rad, from the platform x axis; wrapped or continuous.
    bounds : (k, 2) int, optional
        ``[start, stop)`` dwells (default: the whole stream as one dwell).
    radius_m : float
        Disc radius R, m.
    t : (N,) float, optional
        Sample times, s (gives each dwell's mid time).
    check_units : bool
        Refuse a phase that plainly is in degrees, a radius that looks like millimetres and
        channels far too large for E (see Raises); False demodulates as given.
    check_channels : bool
        Refuse a dwell with a dead, stuck or clipped accelerometer channel (see Raises);
        False demodulates it as given.

    Raises
    ------
    CalibrationError
        Bad shapes; with ``check_channels`` a dwell of at least 30 samples in which an
        accelerometer channel is constant (all zero: dead; else stuck) or clipped: more than
        2 % of its samples on its largest (or smallest) value with the rest below (above),
        and more than 4 times as many as on its next value (so that a coarsely quantised
        peak is not taken for a rail); the message names the channel, the dwell and what
        was seen. With ``check_units``: ``radius_m`` above 5 m (millimetres given as
        metres); demodulated channels above 1e7 E (raw counts, or accelerations not in
        m/s^2); and a phase in degrees: (a) a wrapped phase whose
        wrap-around jumps plus one step make about 360 (within 5 %) and whose values span
        more than 2 pi (a phase wrapped in radians spans at most 2 pi), or (b) a phase without
        wraps that advances more than pi per sample (half a turn or more per sample read as
        radians; at most 90, 4 samples a turn or more, read as degrees). A continuous phase
        in degrees sampled finely (under pi per sample) cannot be told from radians by its
        values and is not refused: pass ``np.radians(phase)``.
    """
    a = _accel(accel)
    n = a.shape[0]
    ph = real_array(phase, "phase", "rad").reshape(-1) if np.ndim(phase) == 1 else None
    if ph is None or ph.shape != (n,):
        raise CalibrationError(
            f"phase must have shape ({n},) to match accel (rad); got {np.shape(phase)}"
        )
    if check_units:
        why = _phase_in_degrees(ph)
        if why is not None:
            raise CalibrationError(why)
    b = bounds_array([[0, n]] if bounds is None else bounds)
    r = positive(radius_m, "radius_m", " (m)")
    if check_units and r > _MAX_RADIUS_M:
        raise CalibrationError(
            f"radius_m {r:g} m is not a gradiometer disc radius (of order 0.1 m; above "
            f"{_MAX_RADIUS_M:g} m refused): millimetres given as metres? pass radius_m="
            f"{r / 1000.0:g} if it is {r:g} mm, or check_units=False if it is metres"
        )
    tv = None
    if t is not None:
        tv = real_array(t, "t", "s").reshape(-1)
        if tv.shape != (n,):
            raise CalibrationError(f"t must have shape ({n},) to match accel")
    if check_channels and np.all((b[:, 0] >= 0) & (b[:, 0] < b[:, 1]) & (b[:, 1] <= n)):
        why = _channel_faults(a, b)
        if why is not None:
            raise CalibrationError(why)
    raw = _core.demodulate_raw(a, ph, b, r, tv)
    dm = Demodulated(*raw.__reduce__()[1])
    if check_units:
        chans = dm.outputs
        fin = np.abs(chans[np.isfinite(chans)])
        if fin.size and float(fin.max()) > _HUGE_E:
            raise CalibrationError(
                f"the demodulated channels are far too large for E: largest |value| "
                f"{float(fin.max()):.3g} E (above {_HUGE_E:g} E, where gravity gradients and "
                f"biases are of order 1 to 1e4 E; accel up to {float(np.max(np.abs(a))):.3g}, "
                f"radius_m {r:g} m): raw counts, or accelerations not in m/s^2? convert accel "
                "to m/s^2 (counts times the scale factor), or check_units=False to demodulate "
                "as given"
            )
    return dm


# ------------------------------------------------------------------------------------------
# The patent's procedure as a workflow
# ------------------------------------------------------------------------------------------
#: Streams shorter than this get no correlation correction in ``StartupCalibration.record``.
_AR1_MIN_SAMPLES = 20


def _ar1_inflation(c: _F64) -> _F64:
    """Per column of ``c`` (N, j), ``sqrt((1 + rho) / (1 - rho))``: the factor by which the
    standard error of the mean of first-order autocorrelated noise exceeds the white-noise
    one, ``rho`` the lag-1 autocorrelation of the linearly detrended column, clipped to
    [0, 0.99] (1 under :data:`_AR1_MIN_SAMPLES` samples or without variation)."""
    n = c.shape[0]
    if n < _AR1_MIN_SAMPLES:
        return np.ones(c.shape[1])
    i = np.arange(n, dtype=np.float64) - 0.5 * (n - 1)
    x = c - c.mean(axis=0)
    x = x - np.outer(i, (i @ x) / (i @ i))
    ss = np.sum(x * x, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = np.sum(x[1:] * x[:-1], axis=0) / ss
    rho = np.where(np.isfinite(rho) & (ss > 0), rho, 0.0)
    rho = np.clip(rho + (1.0 + 3.0 * rho) / n, 0.0, 0.99)  # Kendall's small-sample bias
    return np.asarray(np.sqrt((1.0 + rho) / (1.0 - rho)), dtype=np.float64)


def frame_rotation(azimuth_deg: float) -> _F64:
    """``C_b^r = Rz(theta)`` (3, 3): rotate the IMU's body-frame rates and accelerations by this
    before initial alignment, and the north-pointing control law holds the platform at
    ``theta`` (patent step 2). z down, ``theta`` clockwise from north seen from above."""
    th = np.radians(float(azimuth_deg))
    c, s = np.cos(th), np.sin(th)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class StartupCalibration:
    """Patent steps 1-4 for an acquisition script.

    Example::

        cal = StartupCalibration(drift=True)
        for az in plan_azimuths(4, drift=True):          # 0, 90, 90, 0
            platform.set_virtual_frame(StartupCalibration.frame_rotation(az))
            stream, t = acquire(...)                     # (N, 2) inline/cross in E
            cal.record(az, stream, t=t)                  # averaged by the dwell engine
        result = cal.solve()

    ``record_raw`` takes the raw a1..a4 streams and the spin phase instead (demodulated in
    Rust); ``record_mean`` takes averages computed elsewhere. ``check_units=False`` lets
    :meth:`solve` fit azimuths that look like radians (see :func:`startup_bias`).
    ``sigma_theta`` (deg) is the platform's azimuth repeatability, added to the covariance as
    in :func:`startup_bias`.
    """

    frame_rotation = staticmethod(frame_rotation)

    def __init__(
        self,
        *,
        drift: bool = False,
        sigma: float | ArrayLike | str | None = None,
        radius_m: float | None = None,
        check_units: bool = True,
        sigma_theta: float = 0.0,
    ) -> None:
        self.drift = bool(drift)
        self.check_units = bool(check_units)
        self.sigma_theta = _sigma_theta(sigma_theta)
        if isinstance(sigma, str) and sigma != "stream":
            raise CalibrationError(
                f"sigma must be a number, an array, 'stream' or None; got {sigma!r}"
            )
        self.sigma = sigma
        self.radius_m = None if radius_m is None else positive(radius_m, "radius_m", " (m)")
        self._az: list[float] = []
        self._y: list[tuple[float, float]] = []
        self._t: list[float | None] = []
        self._sem: list[float | None] = []
        self._n: list[int] = []

    def __len__(self) -> int:
        return len(self._az)

    def __repr__(self) -> str:
        return f"StartupCalibration({len(self)} azimuths recorded, drift={self.drift})"

    def _add(self, az: float, y: tuple[float, float], t: float | None, sem: float | None,
             n: int) -> None:
        a = number(az, "azimuth_deg", unit="deg")
        if not (np.isfinite(y[0]) and np.isfinite(y[1])):
            raise CalibrationError(f"azimuth {a:g} deg: channel average is NaN or inf")
        self._az.append(a)
        self._y.append((float(y[0]), float(y[1])))
        self._t.append(None if t is None else number(t, "t", unit="s"))
        self._sem.append(sem)
        self._n.append(n)

    def record(self, azimuth_deg: float, channels: ArrayLike, *, t: ArrayLike | None = None
               ) -> None:
        """Average one azimuth's ``(N, 2)`` inline/cross stream (E) with the dwell engine.

        ``t`` (N,) sample times in s give the dwell's mid time (needed for drift). The
        standard error kept for ``sigma="stream"`` is the white-noise one times
        ``sqrt((1 + rho) / (1 - rho))`` per channel, ``rho`` the lag-1 autocorrelation of the
        linearly detrended stream (plus Kendall's small-sample bias ``(1 + 3 rho) / N``,
        clipped to [0, 0.99]; 0 under 20 samples), and the sample variance divided by
        ``1 - (1 + rho) / ((1 - rho) N)`` (by which it falls short on such noise): right for
        first-order (AR(1), e.g. a one-pole low-pass) noise, about 1 for white noise; noise
        correlated over longer than one dwell (flicker, random walk) is still understated.
        """
        from .dwell import dwell_stats

        c = np.asarray(channels, dtype=np.float64)
        if c.ndim != 2 or c.shape[1] != 2 or c.shape[0] == 0:
            raise CalibrationError(
                f"channels must have shape (N, 2) (inline, cross in E); got {c.shape}"
            )
        n = c.shape[0]
        pad = np.zeros((n, 3))
        pad[:, :2] = c
        ds = dwell_stats(pad, [[0, n]], t=t)
        sem = None
        if n > 1 and ds.var is not None:
            # the sample variance of correlated noise falls short by about f2 / n of it
            f2 = np.minimum(_ar1_inflation(c) ** 2, 0.5 * n)
            sem = float(np.sqrt(np.mean(ds.var[0, :2] * f2 / (1.0 - f2 / n)) / n))
        tm = None if ds.t is None else float(ds.t[0])
        self._add(azimuth_deg, (ds.mean[0, 0], ds.mean[0, 1]), tm, sem, n)

    def record_raw(
        self,
        azimuth_deg: float,
        accel: ArrayLike,
        phase: ArrayLike,
        *,
        t: ArrayLike | None = None,
        radius_m: float | None = None,
        check_units: bool = True,
        check_channels: bool = True,
    ) -> Demodulated:
        """Demodulate one azimuth's raw ``(N, 4)`` streams (m/s^2; ``phase`` in rad) and
        record the channels. ``check_units`` and ``check_channels`` as for
        :func:`demodulate` (a phase in degrees, and a dead, stuck or clipped channel, are
        refused)."""
        r = radius_m if radius_m is not None else self.radius_m
        if r is None:
            raise CalibrationError("record_raw needs the disc radius (radius_m, m)")
        dm = demodulate(accel, phase, radius_m=r, t=t, check_units=check_units,
                        check_channels=check_channels)
        tm = None if dm.t is None else float(dm.t[0])
        sem = float(np.sqrt(0.5 * (dm.std_inline_E[0] ** 2 + dm.std_cross_E[0] ** 2)))
        self._add(azimuth_deg, (dm.inline_E[0], dm.cross_E[0]), tm, sem,
                  int(dm.stop[0] - dm.start[0]))
        return dm

    def record_mean(
        self,
        azimuth_deg: float,
        inline_E: float,
        cross_E: float,
        *,
        t: float | None = None,
        std: float | None = None,
    ) -> None:
        """Record averages computed elsewhere (E; ``t`` the dwell mid time in s)."""
        sd = None if std is None else number(std, "std", lo=0.0, lo_open=True, unit="E")
        self._add(azimuth_deg, (number(inline_E, "inline_E", unit="E"),
                                number(cross_E, "cross_E", unit="E")), t, sd, 0)

    @property
    def azimuth_deg(self) -> _F64:
        """Azimuths recorded so far, deg."""
        return np.array(self._az)

    @property
    def outputs(self) -> _F64:
        """``(m, 2)`` averages recorded so far, E."""
        return np.array(self._y, dtype=np.float64).reshape(-1, 2)

    def solve(self) -> StartupBias:
        """Step 4: the per-startup bias from everything recorded.

        ``sigma="stream"`` (constructor) uses each dwell's own white-noise standard error;
        a number or array is a known noise std; None estimates it from the residuals.
        """
        m = len(self)
        if m == 0:
            raise DegenerateDataError("no azimuth recorded yet")
        t = None
        if self.drift:
            if any(v is None for v in self._t):
                missing = [i for i, v in enumerate(self._t) if v is None]
                raise CalibrationError(f"drift needs a time for every dwell; missing: {missing}")
            t = np.array(self._t, dtype=np.float64)
        sig: Any = self.sigma
        if isinstance(sig, str):
            if sig != "stream":
                raise CalibrationError("sigma must be a number, an array, 'stream' or None")
            if any(v is None or not v > 0 for v in self._sem):
                raise CalibrationError("sigma='stream' needs the noise of every recorded dwell")
            sig = np.array(self._sem, dtype=np.float64)
        fit = startup_bias(self.azimuth_deg, self.outputs, t=t, drift=self.drift, sigma=sig,
                           check_units=self.check_units, sigma_theta=self.sigma_theta)
        if isinstance(self.sigma, str):  # "stream": say where sigma came from
            fit = _StartupBiasFromStreams(*fit.__reduce__()[1])
        return fit


# ------------------------------------------------------------------------------------------
# Table input (the CLI)
# ------------------------------------------------------------------------------------------
def calibrate_gradiometer_table(
    path: str | os.PathLike[str],
    *,
    drift: bool | None = None,
    sigma: float | None = None,
    check_units: bool = True,
    sigma_theta: float = 0.0,
) -> StartupBias:
    """Start-up bias from a table of per-azimuth averages (delimited text, ``#`` comments).

    Columns are found by name, in any order, with the unit in brackets or implied by the name:
    the azimuth (``azimuth_deg``, ``azimuth``, ``az``, ``heading``; degrees unless
    ``[rad]``), the inline and cross channels (``inline_E``, ``inline``, ``cross_E``,
    ``cross``; E unless ``[mE]`` or ``[1/s^2]``) and optionally the time (``t_s``, ``t``,
    ``time``; s unless ``[min]`` or ``[h]``). ``drift=None`` fits a drift when there is a time
    column and at least 3 rows. ``check_units`` as for :func:`startup_bias` (an azimuth
    column in radians whose header does not say so is refused); ``sigma_theta`` (deg) the
    std of independent azimuth errors, as there.
    """
    d = read_table(path, [
        Col("azimuth_deg", "the azimuth (azimuth_deg, azimuth, az, heading)", {
            "azimuthdeg": "deg", "azimuth": "", "az": "", "heading": "", "headingdeg": "deg",
            "azimuthrad": "rad", "angle": ""}, ANGLE_UNITS, "deg"),
        Col("inline_E", "the inline channel (inline_E, inline)", {
            "inlinee": "e", "inline": "", "inlineme": "me"}, GRADIENT_UNITS, "e"),
        Col("cross_E", "the cross channel (cross_E, cross)", {
            "crosse": "e", "cross": "", "crossme": "me"}, GRADIENT_UNITS, "e"),
        Col("t_s", "the time (t_s, t, time)", {
            "ts": "s", "t": "", "time": "", "tmin": "min", "timemin": "min", "th": "h"},
            TIME_UNITS, "s", required=False),
    ], "gradiometer table")
    t = d.get("t_s")
    az = d["azimuth_deg"]
    use_drift = (t is not None and az.shape[0] >= 3) if drift is None else bool(drift)
    return startup_bias(
        az,
        np.column_stack([d["inline_E"], d["cross_E"]]),
        t=t,
        drift=use_drift,
        sigma=sigma,
        check_units=check_units,
        sigma_theta=sigma_theta,
    )
