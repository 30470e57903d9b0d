"""Centrifuge calibration with quadratic (K2) coefficients by norm observation.

Model (g units): ``N = S Phi (f + K2 f^2 [+ K3 f^3]) + b``, constraint ``|f|^2 = A^2 + 1`` with
``A = omega^2 R / g``: the method of Wang and Li (2021), doi:10.19306/j.cnki.2095-8110.2021.06.019,
with its printed equations corrected (``docs/centrifuge-reproduction.md``).

Sign convention: the norm cannot tell ``S_i`` from ``-S_i`` (exactly so when K2 = 0); results
always have ``S_i > 0`` (with K2, misalignment and lever arm signs folded accordingly).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from typing import Any, Literal, cast

import numpy as np
from numpy.typing import NDArray

from . import _core, _quiet
from ._core import CalibrationError
from ._plain import plain
from ._tables import RATE_UNITS, Col, read_table
from ._validate import number, real_array
from .static import WeakDesignWarning

__all__ = [
    "EARTH_RATE",
    "CENTRIFUGE_TRUTH",
    "SEED004_TRUTH",
    "CentrifugeDesign",
    "centrifuge_outputs",
    "paper_design",
    "paper_positions",
    "CentrifugeFit",
    "CentrifugeModelWarning",
    "CentrifugeOutlierWarning",
    "CentrifugeTable",
    "calibrate_centrifuge_table",
    "fit_centrifuge",
    "read_centrifuge_table",
]

# ------------------------------------------------------------------------------------------
# Forward model of a centrifuge test (deterministic physics; the simulator adds noise)
# ------------------------------------------------------------------------------------------
#: Earth rotation rate (rad/s).
EARTH_RATE = 7.2921150e-5

#: Truth of the simulation in Wang and Li (2021), doi:10.19306/j.cnki.2095-8110.2021.06.019
#: (its Table 1 reproduces from it): scale, bias (g) and K2 (1/g).
CENTRIFUGE_TRUTH: dict[str, NDArray[np.float64]] = {
    "scale": np.array([1.29, 1.21, 1.26]),
    "bias": np.array([0.213, 0.256, 0.516]),
    "k2": np.array([0.57e-4, 0.31e-4, 0.45e-4]),
}
#: Former name of :data:`CENTRIFUGE_TRUTH` (kept for existing scripts).
SEED004_TRUTH = CENTRIFUGE_TRUTH


@dataclass(frozen=True)
class CentrifugeDesign:
    """Positions x speeds of a centrifuge test.

    Attributes
    ----------
    omega : ndarray (k,)
        Spin rate per row (rad/s).
    radial : ndarray (k, 3)
        Inward radial unit vector in the body frame per row.
    spin_axis : ndarray (k, 3)
        Spin-axis (up) unit vector in the body frame per row.
    position : ndarray (k,) int
        Position number (1-based).
    speed_index : ndarray (k,) int
        Speed number (1-based).
    radius : float
        Nominal radius (m).
    """

    omega: NDArray[np.float64]
    radial: NDArray[np.float64]
    spin_axis: NDArray[np.float64]
    position: NDArray[np.int64]
    speed_index: NDArray[np.int64]
    radius: float = 1.0

    def __len__(self) -> int:
        return int(self.omega.shape[0])


def paper_positions() -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The paper's 20 positions: (radial (20, 3), spin_axis (20, 3)) body-frame unit vectors."""
    rad = np.empty((20, 3))
    up = np.empty((20, 3))
    k = 0
    for a_deg in (0.0, 45.0, 90.0, 135.0, 180.0):
        a = np.radians(a_deg)
        for t_deg in (180.0, 120.0, 60.0, 0.0):
            t = np.radians(t_deg)
            rad[k] = (np.cos(a) * np.cos(t), -np.sin(a), -np.cos(a) * np.sin(t))
            up[k] = (np.sin(t), 0.0, np.cos(t))
            k += 1
    rad[np.abs(rad) < 1e-15] = 0.0
    up[np.abs(up) < 1e-15] = 0.0
    return rad, up


def paper_design(
    omegas: Any = (2 * np.pi, 4 * np.pi, 6 * np.pi), radius: float = 1.0
) -> CentrifugeDesign:
    """The 20-position x 3-speed design of Wang and Li (2021,
    doi:10.19306/j.cnki.2095-8110.2021.06.019), rows ordered speed-major like its Table 1."""
    om = np.asarray(omegas, dtype=np.float64).ravel()
    rad, up = paper_positions()
    n = len(om)
    return CentrifugeDesign(
        omega=np.repeat(om, 20),
        radial=np.tile(rad, (n, 1)),
        spin_axis=np.tile(up, (n, 1)),
        position=np.tile(np.arange(1, 21), n),
        speed_index=np.repeat(np.arange(1, n + 1), 20),
        radius=float(radius),
    )


def _vec3(x: Any, name: str, default: Any) -> NDArray[np.float64]:
    a = np.asarray(default if x is None else x, dtype=np.float64)
    if a.shape != (3,):
        raise CalibrationError(f"{name} must have 3 values (x, y, z); got shape {a.shape}")
    return a


def centrifuge_outputs(
    design: CentrifugeDesign,
    *,
    scale: Any = None,
    bias: Any = None,
    k2: Any = None,
    k3: Any = None,
    misalignment: Any = None,
    lever_arm: Any = None,
    radius_error: float = 0.0,
    rate_error: float = 0.0,
    latitude_deg: float | None = None,
    g: float = 9.8,
) -> NDArray[np.float64]:
    """Noise-free outputs (k, 3) in g of a triad on ``design`` (see :func:`centrifuge_session`)."""
    s = _vec3(scale, "scale", SEED004_TRUTH["scale"])
    b = _vec3(bias, "bias", SEED004_TRUTH["bias"])
    d = _vec3(k2, "k2", SEED004_TRUTH["k2"])
    e = _vec3(k3, "k3", np.zeros(3))
    m = np.zeros((3, 3)) if misalignment is None else np.asarray(misalignment, dtype=np.float64)
    if m.shape != (3, 3):
        raise CalibrationError(f"misalignment must be a (3, 3) small-angle matrix; got {m.shape}")
    phi = np.eye(3) + m - np.diag(np.diag(m))
    lev = np.zeros((3, 3)) if lever_arm is None else np.asarray(lever_arm, dtype=np.float64)
    if lev.shape != (3, 3):
        raise CalibrationError(
            "lever_arm must be (3, 3): row i = body-frame offset (m) of accelerometer i; "
            f"got {lev.shape}"
        )
    w = design.omega * (1.0 + rate_error)
    if latitude_deg is not None:
        # The platform's inertial rate about the local vertical is the commanded (signed) rate
        # plus the Earth rate's vertical part, whichever way the arm turns: a forward run
        # (w > 0, counter-clockwise seen from above) sees w + Omega sin(lat), a reverse run
        # -(|w| - Omega sin(lat)), so a forward/reverse pair cancels it to first order.
        w = w + EARTH_RATE * np.sin(np.radians(latitude_deg))
    r_true = design.radius + radius_error
    a = w**2 * r_true / g
    c1, c3 = design.radial, design.spin_axis
    f0 = a[:, None] * c1 + c3
    # Accelerometer i at offset r_i sees -(w^2/g) (I - c3 c3^T) r_i more specific force.
    f = np.empty_like(f0)
    for i in range(3):
        r = lev[i]
        proj = r[i] - c3[:, i] * (c3 @ r)
        f[:, i] = f0[:, i] - (w**2 / g) * proj
    h = f + d * f**2 + e * f**3
    return np.asarray((h @ phi.T) * s + b, dtype=np.float64)



#: Estimation methods of :func:`fit_centrifuge`.
CentrifugeMethod = Literal["nls", "taylor-paper"]
#: Lever-arm models of :func:`fit_centrifuge`.
LeverModel = Literal["along", "full"]

_PAPER_TABLE2 = {
    "k2": np.array([5.700684e-5, 3.100221e-5, 4.500459e-5]),
    "scale": np.array([1.28999, 1.21001, 1.25996]),
    "bias": np.array([0.212999, 0.256004, 0.515972]),
}


class CentrifugeOutlierWarning(UserWarning):
    """Rows inconsistent with the centrifuge model were excluded from the fit."""


class CentrifugeModelWarning(UserWarning):
    """The residuals exceed the noise model across the rows (a model error, not outliers): the
    robust screen kept every row (:attr:`CentrifugeFit.screen_kept_all`)."""


class CentrifugeFit(_core.CentrifugeFitCore):
    """Result of :func:`fit_centrifuge` (the data live in the Rust result; arrays are read-only).

    Attributes
    ----------
    scale : ndarray (3,)
        Scale factors S (output g per input g), positive by convention.
    bias : ndarray (3,)
        Biases b (g).
    k2 : ndarray (3,)
        Quadratic coefficients K2 = D (g/g^2).
    k3 : ndarray (3,) or None
        Cubic coefficients (g/g^3) when fitted.
    misalignment : ndarray (3,) or None
        Small angles (m_yx, m_zx, m_zy) in rad of ``Phi = I + M`` (lower triangular).
    lever_arm : ndarray (3,) or (3, 3) or None
        Offsets (m): along each accelerometer's own axis, or a body-frame vector per row.
    params, names : ndarray (p,), list of str
        All parameters in order.
    covariance : ndarray (p, p)
        Parameter covariance: absolute when the output noise ``sigma`` was given
        (``noise_known``), else scaled by the residual variance.
    std : ndarray (p,)
        Standard deviations, ``sqrt(diag(covariance))``.
    residuals : ndarray (k,)
        Norm residual per row, ``(|f|^2 - A^2 - 1) / (2 sqrt(A^2 + 1))`` ~ ``|f| - |f_true|``
        in g, outliers included (inf where a row cannot be inverted).
    residual_std : ndarray (k,)
        Standard deviation of each row's norm residual, g: propagated from ``sigma`` when
        given, else the residual scale of the rows used.
    studentized : ndarray (k,)
        The screening statistic of each row: its residual in standard deviations of what a
        good row's residual would be (externally studentised for the rows used, a prediction
        residual for the excluded ones).
    threshold : float
        Rows with ``|studentized| > threshold`` are excluded (the Student-t equivalent of
        ``outlier_k`` normal standard deviations).
    outliers : ndarray int
        Rows excluded by the robust screen (0-based; :meth:`row_name` names them).
    screen_kept_all : bool
        The screen ran but kept every row: what it would exclude is a misfit spread over the
        rows (a model error), not sparse outliers; the fit is the plain one, whose rows beyond
        ``threshold`` remain (:meth:`model_error_text` says so).
    residual_rms : float
        RMS of the weighted residuals of the rows used (g; whitened, ~1, when ``sigma`` was
        given).
    observability : dict
        ``singular_values`` (column-normalised Jacobian), ``condition_number``, and
        ``unobservable`` (always empty: a singular design raises DegenerateDataError naming it).
    method : str
    taylor_coefficients : ndarray (13,) or None
        The regression coefficients ``[C0, C11..C13, C21..C23, C31..C33, C41..C43]``
        (taylor-paper only).
    labels : list of str
        Name of each row (e.g. ``"speed 1, position 5"``), empty when none was given.
    extra : dict
        ``screen_sigma``: residual scale of the rows used (g; 1 when ``sigma`` was given).
    """

    __slots__ = ()

    def __repr__(self) -> str:
        return (f"CentrifugeFit(method={self.method!r}, rows={len(self.residuals)}, "
                f"excluded={len(self.outliers)}, residual_rms={self.residual_rms:.3g} g)")

    @property
    def scale(self) -> NDArray[np.float64]:
        """Scale factors S (3,), output g per input g."""
        return self.params[0:3]

    @property
    def bias(self) -> NDArray[np.float64]:
        """Biases b (3,), g."""
        return self.params[3:6]

    @property
    def k2(self) -> NDArray[np.float64]:
        """Quadratic coefficients K2 (3,), g/g^2."""
        return self.params[6:9]

    @property
    def k3(self) -> NDArray[np.float64] | None:
        """Cubic coefficients (3,), g/g^3, when fitted."""
        return self.params[9:12] if self.fit_k3 else None

    @property
    def misalignment(self) -> NDArray[np.float64] | None:
        """Small angles (m_yx, m_zx, m_zy), rad, when fitted."""
        if not self.fit_misalignment:
            return None
        at = 12 if self.fit_k3 else 9
        return self.params[at : at + 3]

    @property
    def lever_arm(self) -> NDArray[np.float64] | None:
        """Lever arms, m: (3,) along each axis, or (3, 3) (row = accelerometer)."""
        if self.lever_model is None:
            return None
        at = 9 + 3 * self.fit_k3 + 3 * self.fit_misalignment
        if self.lever_model == "along":
            return self.params[at : at + 3]
        return self.params[at : at + 9].reshape(3, 3)

    @property
    def observability(self) -> dict[str, Any]:
        """Singular values and condition number of the column-normalised Jacobian."""
        return {
            "singular_values": self.singular_values,
            "condition_number": self.condition_number,
            "unobservable": [],
        }

    @property
    def extra(self) -> dict[str, Any]:
        """``screen_sigma`` (g): the residual scale of the rows used."""
        return {"screen_sigma": self.screen_sigma}

    @property
    def screen_kept_all(self) -> bool:
        """The robust screen ran (``draws > 0``) yet kept every row although rows exceed the
        threshold: it judged the misfit a model error spread over the rows, not outliers (the
        core's rule: more than half of the rows excluded; the excluded rows' residuals made by
        the exclusion, over 30 times their plain-fit residuals; with ``sigma`` given, more
        than a quarter excluded while the rows kept still reject the noise model; more than a
        quarter excluded that are not lost minus signs; 4 or more such rows with residuals
        agreeing in sign and within a factor 2; or 6 or more such rows at one speed)."""
        return bool(self.draws > 0 and not len(self.outliers)
                    and np.any(np.abs(self.studentized) > self.threshold))

    def model_error_text(self) -> str:
        """What :attr:`screen_kept_all` means, one line (empty when the screen did not keep
        every row that way)."""
        if not self.screen_kept_all:
            return ""
        k = len(self.residuals)
        over = int(np.sum(np.abs(self.studentized) > self.threshold))
        unit = "(whitened)" if self.noise_known else "g"
        std = ("their std, from the given noise, understates the error"
               if self.noise_known else "their std holds only if the misfit is noise-like")
        return (
            f"kept all {k} rows: the residuals exceed the noise model across many rows "
            f"({over} of {k} beyond the {self.threshold:.3g}-sigma threshold, residual rms "
            f"{self.residual_rms:.3g} {unit}), a misfit spread over the rows, not a few "
            "outliers: a model error (the radius or rate, a lever arm, misalignment, K3), "
            "which excluding rows would only hide. The parameters carry that error and "
            f"{std}; accelcal.diagnose_centrifuge names the effect (then fit it: lever_arm=, "
            "misalignment=, k3=, or correct the radius or rate)"
        )

    @property
    def outlier_residuals(self) -> NDArray[np.float64]:
        """Residuals (g) of the excluded rows, in the order of :attr:`outliers`."""
        return np.asarray(self.residuals[self.outliers], dtype=np.float64)

    def row_name(self, k: int) -> str:
        """``"row k"`` with its label (e.g. ``"row 4 (speed 1, position 5)"``)."""
        k = int(k)
        return f"row {k} ({self.labels[k]})" if self.labels else f"row {k}"

    def excluded_text(self) -> str:
        """The excluded rows with their residuals, one line (empty when none)."""
        if not len(self.outliers):
            return ""
        return (
            f"excluded {len(self.outliers)} of {len(self.residuals)} rows inconsistent with "
            "|f|^2 = A^2 + 1: "
            + "; ".join(
                f"{self.row_name(k)} {r:+.3g} g"
                for k, r in zip(self.outliers, self.outlier_residuals, strict=True)
            )
        )

    def correct(self, outputs: Any) -> NDArray[np.float64]:
        """Specific force (k, 3) in g from outputs (k, 3) in g by exact inversion of the model
        (at the accelerometers: lever arms are not applied)."""
        n = np.atleast_2d(real_array(outputs, "outputs", "g"))
        if n.ndim != 2 or n.shape[1] != 3:
            raise CalibrationError(f"outputs must have shape (k, 3) in g; got {n.shape}")
        return np.asarray(_core.centrifuge_correct_raw(
            self.params, n, self.fit_k3, self.fit_misalignment,
            cast("LeverModel | None", self.lever_model)))

    def summary(self) -> str:
        """Human-readable table of parameters with standard deviations; the excluded rows are
        named once, by index and label."""
        noise = "the given noise" if self.noise_known else "the residual scatter"
        unit = "(whitened)" if self.noise_known else "g"
        lines = [
            f"centrifuge fit ({self.method}): {len(self.residuals)} rows, "
            f"{len(self.outliers)} excluded, residual rms {self.residual_rms:.3g} {unit}, "
            f"condition {self.condition_number:.3g}, std from {noise}"
        ]
        units = {"s": "g/g", "b": "g", "k2": "g/g^2", "k3": "g/g^3", "m": "rad", "lever": "m"}
        for n, v, s in zip(self.names, self.params, self.std, strict=True):
            u = units.get(n.split("_")[0].rstrip("xyz") or n[0], "")
            lines.append(f"  {n:<10} {v: .9g}  +- {s:.2g} {u}")
        if self.screen_kept_all:
            lines.append(f"  model error, not outliers: {self.model_error_text()}")
        if len(self.outliers):
            lines.append(f"  excluded {len(self.outliers)} of {len(self.residuals)} rows "
                         "inconsistent with |f|^2 = A^2 + 1 (residual, studentised):")
            for k, r in zip(self.outliers, self.outlier_residuals, strict=True):
                t = self.studentized[k]
                lines.append(f"    {self.row_name(k):<32} {r:+11.4g} g  {t:+9.3g}")
        return "\n".join(lines)

    def _rms_g(self) -> float:
        """RMS of the norm residuals of the rows used, in g (``residual_rms`` is whitened when
        the noise was given)."""
        if not self.noise_known:
            return float(self.residual_rms)
        r = np.asarray(self.residuals, dtype=np.float64)
        used = np.ones(r.size, dtype=bool)
        used[np.asarray(self.outliers, dtype=np.intp)] = False
        used &= np.isfinite(r)
        return float(np.sqrt(np.mean(np.square(r[used])))) if used.any() else float("nan")

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly dictionary (lists and floats)."""
        return {
            "method": self.method,
            "scale": plain(self.scale),
            "bias_g": plain(self.bias),
            "k2_g_per_g2": plain(self.k2),
            "k3_g_per_g3": plain(self.k3),
            "misalignment_rad": plain(self.misalignment),
            "lever_arm_m": plain(self.lever_arm),
            "names": list(self.names),
            "params": plain(self.params),
            "std": plain(self.std),
            "covariance": plain(self.covariance),
            "noise_known": self.noise_known,
            "residuals_g": plain(self.residuals, strict=True),
            "studentized": plain(self.studentized, strict=True),
            "threshold": self.threshold,
            "outliers": plain(self.outliers),
            "row_labels": list(self.labels),
            # In g whatever the noise: with sigma given, residual_rms is whitened (its own key).
            "residual_rms_g": self._rms_g(),
            "residual_rms_whitened": self.residual_rms if self.noise_known else None,
            "observability": plain(self.observability),
            "iterations": self.iterations,
            "converged": self.converged,
            "taylor_coefficients": plain(self.taylor_coefficients),
            "radius_m": self.radius,
            "g_mps2": self.g,
        }


def _unit_message(found: tuple[float, list[Any]], off: str) -> str:
    """Words for the unit check's finding (``off`` says how to turn the check off)."""
    scale, findings = found
    need = (
        f"as given, the outputs would need scale factors of about {scale:.3g} (output g per "
        "input g) to meet |f|^2 = A^2 + 1 (A = omega^2 R / g), where a triad reporting in g has "
        "0.2..5"
    )
    if not findings:
        return (f"implausible units: {need}. Give the outputs in g, omega in rad/s and the "
                f"radius in m, or {off} if this scale factor is right")
    what, unit, want, fix, s, rms = findings[0]
    verb = "look" if what == "outputs" else "looks"
    msg = (f"{what} {verb} like {unit}, not {want}: {need}; with {what} converted ({fix}) they "
           f"need {s:.3g}")
    if np.isfinite(rms):
        msg += f" and the fit leaves {rms:.2g} g rms"
    for w2, u2, _, _, s2, r2 in findings[1:]:
        msg += f" (less likely: {w2} in {u2}, scale {s2:.3g}, {r2:.2g} g rms)"
    return msg + f". Give {what} in {want}, or {off} if the units are right"


def fit_centrifuge(
    outputs: Any,
    omega: Any,
    radius: float,
    *,
    g: float = 9.80665,
    method: CentrifugeMethod = "nls",
    k3: bool = False,
    misalignment: bool = False,
    lever_arm: LeverModel | None = None,
    spin_axis: Any = None,
    sigma: Any = None,
    robust: bool = True,
    outlier_k: float = 5.0,
    max_draws: int = 20000,
    seed: int = 0,
    check_units: bool = True,
    labels: Any = None,
) -> CentrifugeFit:
    """Calibrate an accelerometer triad from centrifuge per-position mean outputs.

    Parameters
    ----------
    outputs : array_like (k, 3)
        Mean outputs per position and speed (g). Any layout (C or Fortran order, strided,
        a DataFrame), float or integer dtype, either byte order. The ``outputs`` of a table
        read in m/s^2 (:func:`read_centrifuge_table`) are converted again with this ``g``
        when the reader was not given one; a different ``g`` given to the reader is refused.
    omega : array_like (k,)
        Signed spin rate of each row (rad/s); at least two distinct speeds (rows at rest,
        0, count as one).
    radius : float
        Nominal radius (m).
    g : float
        Local gravity (m/s^2) used to express ``A = omega^2 R / g`` in g. With ``check_units``
        a value outside 9.76..9.84 is refused (CalibrationError naming the unit it looks like:
        32.17 ft/s^2, 980.7 cm/s^2, 1 g).
    method : {"nls", "taylor-paper"}
        ``"nls"``: exact per-axis inversion and least squares on the norm (default).
        ``"taylor-paper"``: the paper's 13-coefficient regression with its closed form, as
        corrected in ``docs/centrifuge-reproduction.md`` and made consistent with its series
        (scale + bias + K2 only; D is biased by the truncated series). Its std are those of the
        exact norm least squares at its parameters: they include neither the truncation error
        nor the extra scatter of the unweighted regression, and understate its errors (with
        ``sigma`` given, by factors of 10 to 50, and a :class:`CentrifugeModelWarning` says
        so). ``"nls"`` is the default for that reason.
    k3, misalignment : bool
        Add the cubic coefficient / the three observable small misalignment angles (nls only).
    lever_arm : {None, "along", "full"}
        Per-accelerometer offset along its own axis (3 params) or full vector (9 params),
        in m; needs ``spin_axis``. A design that cannot see a component raises
        DegenerateDataError naming it.
    spin_axis : array_like (k, 3), optional
        Spin-axis (up) unit vector in the body frame per row (lever-arm models).
    sigma : float, array_like (k,) or (k, 3), optional
        Noise standard deviation of each **output** per axis (g), the same on every row and
        axis (scalar), per row, or per row and axis: for mean outputs, the per-sample noise
        over sqrt(samples averaged). It is propagated to each row's norm residual at the
        fitted parameters (``residual_std``), which weights the rows; the covariance is then
        absolute and ``residual_rms`` is whitened (about 1 when the noise is right). Without
        it the rows weigh equally and the covariance is scaled by the residual variance.
    robust : bool
        Screen rows inconsistent with the model; excluded rows raise a
        :class:`CentrifugeOutlierWarning` naming them. See ``outlier_k``. The screen is for
        sparse gross errors (a lost sign, a wrong row): when what it would exclude is a misfit
        spread over the rows instead (more than half of them; residuals the exclusion itself
        makes, over 30 times the rows' plain-fit residuals; with ``sigma`` given, more than
        a quarter of the rows while those kept still reject the noise model; more than a
        quarter of the rows not explained as lost minus signs; 4 or more such rows whose
        residuals agree in sign and within a factor 2; or 6 or more such rows at one speed),
        every row is kept, :attr:`CentrifugeFit.screen_kept_all` is set and a
        :class:`CentrifugeModelWarning` says the residuals point to a model error. When fewer
        rows than the parameters need agree with any fit, DegenerateDataError says so. A fit
        returned with residuals far above its noise (whitened rms above 3 with ``sigma``, or
        above 1e-3 of the norm without) warns with :class:`CentrifugeModelWarning`; a weak
        design (condition number above 1e4, or an input-referred bias std above 5e-3 g) with
        :class:`accelcal.WeakDesignWarning`; a fit that does not converge raises
        CalibrationError. The plain fit restarts from the screen's least-median start when the
        linear start leaves it unconverged or above 1e-4 of the norm.
    outlier_k : float
        Screening threshold as a normal tail: a good row is excluded with the probability of a
        ``outlier_k``-sigma normal deviation, ``2 Phi(-k)`` per row (5.7e-7 at the default 5,
        so 3.4e-5 for a 60-row session). The statistic is the studentised residual (the
        residual over what a good row's residual would be, with the noise estimated without
        that row), compared with the Student-t quantile of the same tail probability
        (``threshold``); with ``sigma`` given, with ``outlier_k`` itself. When any row
        exceeds it, a least-median-of-squares fit over random minimal subsets (seeded) gives
        an outlier-free start and the rows are reclassified until they settle.
    max_draws : int
        Maximum random subsets of the screen, 1..10_000_000.
    seed : int
        Seed of the subset generator (the result is deterministic).
    check_units : bool
        Refuse (CalibrationError naming the likely unit) a session whose norm constraint
        ``|f|^2 = A^2 + 1`` needs scale factors no triad reporting in g has (outside
        0.2..5): omega in rpm, deg/s or Hz, radius in mm or cm, outputs in m/s^2.
    labels : sequence of str (k,), optional
        Names of the rows for messages (e.g. ``"speed 1, position 5"``);
        :func:`calibrate_centrifuge_table` gives speed and position.

    Returns
    -------
    CentrifugeFit
    """
    conv = _outputs_conversion(outputs)
    out = real_array(outputs, "outputs", "g")
    if out.ndim != 2 or out.shape[1] != 3:
        raise CalibrationError(f"outputs must have shape (k, 3) in g; got {out.shape}")
    if out.shape[0] == 0:
        raise CalibrationError(
            "outputs have no rows (shape (0, 3)): give one mean output per position and speed "
            "(k, 3) in g, with at least two distinct speeds (rows at rest count as one)"
        )
    om = real_array(omega, "omega", "rad/s").reshape(-1)
    if om.shape[0] != out.shape[0]:
        raise CalibrationError(
            f"omega has {om.shape[0]} values but outputs have {out.shape[0]} rows"
        )
    r = number(radius, "radius", lo=0.0, lo_open=True, unit="m")
    gg = number(g, "g", lo=0.0, lo_open=True, unit="m/s^2")
    if conv is not None and conv[0] != gg:
        g_read, stated, axes = conv
        if stated:
            raise CalibrationError(
                f"the outputs were read in m/s^2 and divided by g = {g_read:g} m/s^2 "
                f"(read_centrifuge_table(..., g={g_read:g})), but the fit is given g = {gg:g}: "
                "one local gravity is both the unit of the outputs and the g of A = omega^2 R "
                f"/ g. Read the table with g={gg:g}, or fit with g={g_read:g}"
            )
        out = np.array(out, dtype=np.float64)  # converted again with the fit's own g
        out[:, axes] *= g_read / gg
    k_out = number(outlier_k, "outlier_k", lo=0.0, lo_open=True, unit="standard deviations")
    draws = number(max_draws, "max_draws", lo=1, hi=10_000_000, integer=True)
    sd = number(seed, "seed", lo=0, hi=2.0**53, integer=True)
    if method not in ("nls", "taylor-paper"):
        raise CalibrationError(f"unknown method {method!r}; use 'nls' or 'taylor-paper'")
    sa = None
    if spin_axis is not None:
        sa = real_array(spin_axis, "spin_axis")
        if sa.shape != out.shape:
            raise CalibrationError(f"spin_axis must have shape {out.shape}; got {sa.shape}")
    sg = None
    if sigma is not None:
        s_ = real_array(sigma, "sigma", "g")
        k = out.shape[0]
        if s_.ndim == 1 and s_.shape == (k,):
            s_ = s_[:, None]
        try:
            sg = np.broadcast_to(s_, out.shape)
        except ValueError:
            raise CalibrationError(
                f"sigma (per-axis output noise, g) must be a number, ({k},) or ({k}, 3); "
                f"got shape {s_.shape}"
            ) from None
    lab = None
    if labels is not None:
        lab = [str(x) for x in labels]
    if check_units:
        found = _core.centrifuge_unit_check_raw(out, om, r, gg, bool(robust), draws, sd)
        if found is not None:
            raise CalibrationError(_unit_message(found, "pass check_units=False"))
    fit = _core.centrifuge_fit_raw(
        out, om, r, gg, method, bool(k3), bool(misalignment), lever_arm, sa, sg,
        bool(robust), k_out, 1e-9, draws, sd, False, lab,
    )
    res = CentrifugeFit(fit)  # the same result as the Python type (arrays shared)
    if not res.converged:
        hz = ""
        if check_units:
            # omega in rev/s (Hz) read as rad/s: a low-g design passes the unit check and
            # then fails here. One more fit, only on this path, says whether omega * 2 pi
            # makes the data consistent.
            om2 = om * (2.0 * np.pi)
            try:
                alt = CentrifugeFit(_core.centrifuge_fit_raw(
                    out, om2, r, gg, method, bool(k3), bool(misalignment), lever_arm, sa, sg,
                    bool(robust), k_out, 1e-9, draws, sd, False, lab))
            except CalibrationError:
                alt = None
            if alt is not None and alt.converged and (
                    rel := _relative_rms(alt, om2)) < _MISFIT_RELATIVE:
                hz = (f"omega looks like rev/s (Hz), not rad/s: with omega * 2 pi the fit "
                      f"converges and leaves {rel:.2g} of the norm (rms); give omega in rad/s. "
                      "As given, ")
        raise CalibrationError(hz + _not_converged_text(res, om))
    if len(res.outliers):
        _quiet.warn(res.excluded_text(), CentrifugeOutlierWarning, stacklevel=2)
    if res.screen_kept_all:
        rel = _relative_rms(res, om)
        _quiet.warn("robust screen " + res.model_error_text()
                    + f"; the fit on every row leaves {rel:.2g} of the norm (rms)",
                    CentrifugeModelWarning, stacklevel=2)
        misfit = "kept all"
    else:
        misfit = _misfit_text(res, om)
        if method == "taylor-paper" and sg is not None:
            # One warning, naming the method's own error first: its parameters are not the
            # least-squares minimum, so the whitened rms is high even without a model error.
            misfit = _TAYLOR_STD_TEXT + (
                f". Here the whitened residual rms is {res.residual_rms:.3g} (about 1 for the "
                "least-squares minimum of a right model): fit with 'nls' to see whether a "
                "model error remains" if misfit else "")
        if misfit:
            _quiet.warn(misfit, CentrifugeModelWarning, stacklevel=2)
    weak = _weak_design_text(res, bias_std=not misfit)
    if weak:
        _quiet.warn(weak, WeakDesignWarning, stacklevel=2)
    return res


#: Why the std of method "taylor-paper" understate its error (warned when ``sigma`` makes them
#: absolute). Simulated paper sessions, 20 seeds, sigma given: z-rms (error / std) up to 14 (S_x),
#: 29 (S_y), 44 (S_z) at 1e-5 g noise and up to 58 (k2x) at 1e-7 g.
_TAYLOR_STD_TEXT = (
    "method 'taylor-paper': its std are those of the exact norm least squares evaluated at "
    "its parameters; they include neither the truncation error of its Taylor series (K2 "
    "biased by about 3e-5 relative on the paper's design, more for larger K2) nor the extra "
    "scatter of its unweighted regression on powers of the noisy outputs, so with sigma given "
    "they understate its errors (by factors of 10 to 50 on simulated paper sessions). Method "
    "'nls', the default for that reason, inverts each axis exactly, weighs the rows and "
    "states std that match its scatter; use 'taylor-paper' only to reproduce the paper"
)


#: Whitened residual rms above which a fit with the noise given leaves a misfit (with at least
#: :data:`_MISFIT_MIN_DOF` residual degrees of freedom), and the relative residual rms (of the
#: norm) above which a fit with the noise estimated does.
_MISFIT_WHITENED = 3.0
_MISFIT_MIN_DOF = 10
_MISFIT_RELATIVE = 1e-3
#: Condition number of the column-normalised Jacobian, and bias std (input-referred, g: the
#: std over the scale factor), above which the design is weak.
_WEAK_CONDITION = 1e4
_WEAK_BIAS_STD_G = 5e-3


def _used(res: CentrifugeFit) -> NDArray[np.bool_]:
    used = np.ones(len(res.residuals), dtype=bool)
    used[np.asarray(res.outliers, dtype=np.int64)] = False
    return used


def _relative_rms(res: CentrifugeFit, omega: NDArray[np.float64]) -> float:
    """RMS of the norm residuals of the rows used relative to the norm ``sqrt(A^2 + 1)``."""
    used = _used(res)
    a = omega[used] ** 2 * res.radius / res.g
    rel = np.asarray(res.residuals)[used] / np.sqrt(a * a + 1.0)
    return float(np.sqrt(np.mean(rel * rel))) if rel.size else 0.0


def _not_converged_text(res: CentrifugeFit, omega: NDArray[np.float64]) -> str:
    unit = "(whitened)" if res.noise_known else "g"
    return (
        f"the centrifuge fit did not converge ({res.iterations} iterations, residual rms "
        f"{res.residual_rms:.3g} {unit}, {_relative_rms(res, omega):.2g} of the norm): its "
        "parameters and std are not a least-squares solution. The model may not fit these "
        "data (a wrong radius, rate or g, a lever arm, misalignment, K3): keep the robust "
        "screen on (robust=True) and run diagnose_centrifuge"
    )


def _misfit_text(res: CentrifugeFit, omega: NDArray[np.float64]) -> str:
    """Words for a returned fit whose residuals are far above its noise, or ``""``."""
    rel = _relative_rms(res, omega)
    causes = ("a wrong radius, rate or g, a lever arm, misalignment, K3 or the Earth rate; "
              "accelcal.diagnose_centrifuge names the effect")
    if res.noise_known:
        dof = int(_used(res).sum()) - len(res.params)
        if dof < _MISFIT_MIN_DOF or not res.residual_rms > _MISFIT_WHITENED:
            return ""
        return (
            f"the model leaves a misfit: whitened residual rms {res.residual_rms:.3g} (about 1 "
            f"if the model and the given noise were right; {rel:.2g} of the norm), so the "
            f"parameters carry a model error and their std understate it: {causes}"
        )
    if not rel > _MISFIT_RELATIVE:
        return ""
    return (
        f"the model leaves a misfit: residual rms {res.residual_rms:.3g} g, {rel:.2g} of the "
        f"norm (above {_MISFIT_RELATIVE:g}), far above any accelerometer's noise on means: the "
        f"parameters carry a model error and their std (from the residual scatter) do not "
        f"describe it: {causes}"
    )


def _weak_design_text(res: CentrifugeFit, bias_std: bool = True) -> str:
    """Words for a design that determines the parameters only weakly, or ``""``. With
    ``bias_std`` False (the std are scaled by a misfit already warned of) only the condition
    number counts."""
    cond = float(res.condition_number)
    bstd = np.asarray(res.std)[3:6] / np.abs(np.asarray(res.scale))  # input-referred, g
    if not (cond > _WEAK_CONDITION or (bias_std and np.any(bstd > _WEAK_BIAS_STD_G))):
        return ""
    return (
        f"weak design: condition number {cond:.3g} (column-normalised Jacobian), bias std "
        f"({', '.join(f'{v:.2g}' for v in bstd)}) g: the rows barely separate some parameters "
        "(an axis that sees few distinct levels of specific force cannot tell bias from K2 or "
        "scale); the estimates along that combination follow the noise. Add positions where "
        "each axis sees more distinct inputs, or more speeds"
    )


# --------------------------------------------------------------------------- seed table I/O


@dataclass(frozen=True)
class CentrifugeTable:
    """A centrifuge table: per-position mean outputs in g at each angular rate (rad/s), with
    each row's speed index and position (the layout of the paper's Table 1)."""

    speed_index: NDArray[np.int64]
    omega: NDArray[np.float64]
    position: NDArray[np.int64]
    outputs: NDArray[np.float64]
    path: str = ""
    #: Local gravity (m/s^2) the output columns given in m/s^2 were divided by; None when
    #: every output column is in g or mg. :func:`fit_centrifuge` converts such outputs again
    #: with its own ``g`` (or refuses a ``g`` stated to the reader that differs from it).
    g_mps2: float | None = None
    #: The output axes (x, y, z) read in m/s^2.
    mps2_axes: tuple[bool, bool, bool] = (False, False, False)

    def __len__(self) -> int:
        return int(self.omega.shape[0])

    def labels(self) -> list[str]:
        """Name of each row by speed and position, e.g. ``"speed 1, position 5"``."""
        return [f"speed {s}, position {p}"
                for s, p in zip(self.speed_index, self.position, strict=True)]


#: Standard gravity (m/s^2): the default ``g`` of the reader and of the fit.
STANDARD_G = 9.80665


class _OutputsFromMps2(np.ndarray):  # type: ignore[type-arg]
    """Outputs (g) of a table whose columns in m/s^2 were divided by ``g_mps2``; the
    conversion travels with the array (and with arrays indexed from it) so that
    :func:`fit_centrifuge` can redo it with its own ``g``."""

    g_mps2: float
    g_stated: bool
    mps2_axes: tuple[bool, bool, bool]

    def __array_finalize__(self, obj: Any) -> None:
        self.g_mps2 = getattr(obj, "g_mps2", STANDARD_G)
        self.g_stated = getattr(obj, "g_stated", False)
        self.mps2_axes = getattr(obj, "mps2_axes", (False, False, False))


def _outputs_conversion(outputs: Any) -> tuple[float, bool, NDArray[np.bool_]] | None:
    """``(g_mps2, stated, axes)`` when ``outputs`` come from a table read in m/s^2."""
    if not isinstance(outputs, _OutputsFromMps2) or not any(outputs.mps2_axes):
        return None
    return outputs.g_mps2, outputs.g_stated, np.array(outputs.mps2_axes, dtype=bool)


def _table_columns(g: float) -> list[Col]:
    out_units = {"g": 1.0, "mg": 1e-3, "m/s2": 1.0 / g}
    cols = [
        Col("omega", "the angular rate (omega_rad_s, omega, rpm, ...)", {
            "omegarads": "rad/s", "omega": "", "w": "", "rate": "", "angularrate": "",
            "angularvelocity": "", "spinrate": "", "omegarpm": "rpm", "rpm": "rpm",
            "speedrpm": "rpm", "omegadegs": "deg/s", "ratedegs": "deg/s", "freq": "hz",
            "frequency": "hz", "freqhz": "hz", "spinhz": "hz", "omegahz": "hz"},
            RATE_UNITS, "rad/s"),
        Col("speed_index", "the speed index", dict.fromkeys(
            ("speedindex", "speedidx", "speedno", "speednumber", "run", "step"), ""),
            {"": 1.0}, required=False),
        Col("position", "the position", dict.fromkeys(
            ("position", "pos", "positionindex", "positionno", "orientation", "face"), ""),
            {"": 1.0}, required=False),
    ]
    for a in "xyz":
        names: dict[str, str] = {}
        for stem in ("na", "a", "acc", "accel", "f", "n", "out", "output", "sf"):
            names[f"{stem}{a}"] = ""
            for unit, tag in (("g", "g"), ("mg", "mg"), ("ms2", "m/s2"), ("mps2", "m/s2")):
                names[f"{stem}{a}{unit}"] = tag
        cols.append(Col(f"out_{a}", f"the mean {a} output (N_a{a}_g, a{a}, acc_{a}, ...)",
                        names, out_units, "g"))
    return cols


def _whole(path: str, x: NDArray[np.float64] | None, what: str) -> NDArray[np.int64] | None:
    if x is None:
        return None
    if not np.all(x == np.round(x)):
        raise CalibrationError(f"{path}: the {what} column must hold whole numbers")
    return x.astype(np.int64)


def _number_levels(omega: NDArray[np.float64]) -> NDArray[np.int64]:
    """1, 2, ... for the distinct rates in order of first appearance (relative 1e-9)."""
    levels: list[float] = []
    idx = np.empty(omega.shape[0], dtype=np.int64)
    for i, w in enumerate(omega):
        k = next((k for k, lv in enumerate(levels)
                  if abs(w - lv) <= 1e-9 * max(abs(lv), abs(w))), None)
        if k is None:
            levels.append(float(w))
            k = len(levels) - 1
        idx[i] = k + 1
    return idx


def read_centrifuge_table(path: str | os.PathLike[str], g: float | None = None) -> CentrifugeTable:
    """Read a centrifuge run's per-position table (delimited text, ``#`` comments).

    Columns are found by name, in any order, with the unit in brackets or implied by the name:

    - the angular rate: ``omega_rad_s``, ``omega``, ``w``, ``rate`` (rad/s unless stated),
      ``rpm``, ``omega [deg/s]``, ``freq [Hz]``;
    - the mean outputs x, y, z: ``N_ax_g`` ..., ``ax``, ``acc_x``, ``fx``, ``out_x`` (g unless
      stated: ``ax [mg]``, ``ax [m/s^2]``, ``ax_mps2``; m/s^2 are divided by ``g``, the local
      gravity in m/s^2, 9.80665 when not given);
    - optional ``speed_index`` (else the distinct rates are numbered in order of appearance)
      and ``position`` (else rows are numbered within each speed).

    A units row under the header (``-, rad/s, -, g, g, g``) gives the units as brackets would;
    one with units this reader does not know is refused. Rows that repeat a speed index and
    position warn (UserWarning), naming them: the fit counts each as a measurement of its own.

    The paper's Table 1 layout is ``speed_index, omega_rad_s, position, N_ax_g, N_ay_g,
    N_az_g``.

    The table remembers the ``g`` that m/s^2 outputs were divided by (``g_mps2``), and so do
    its ``outputs`` (and arrays indexed from them): :func:`fit_centrifuge` converts them again
    with its own ``g`` when this one was not given, and refuses a ``g`` given here that
    differs from the fit's (one local gravity is the unit of the outputs and of ``A``).
    """
    gv = STANDARD_G if g is None else number(g, "g", lo=0.0, lo_open=True, unit="m/s^2")
    p = str(path)
    d = read_table(path, _table_columns(gv), "centrifuge table", with_lines=True)
    # Which output columns were in m/s^2: read again with another g (tables are small).
    d2 = read_table(path, _table_columns(2.0 * gv), "centrifuge table")
    mps2 = tuple(bool(np.any(d[f"out_{a}"] != d2[f"out_{a}"])) for a in "xyz")
    omega = d["omega"]
    speed = _whole(p, d.get("speed_index"), "speed index")
    if speed is None:
        speed = _number_levels(omega)
    pos = _whole(p, d.get("position"), "position")
    if pos is None:
        pos = np.empty_like(speed)
        for s_ in np.unique(speed):
            at = np.flatnonzero(speed == s_)
            pos[at] = np.arange(1, at.size + 1)
    outputs = np.column_stack([d[f"out_{a}"] for a in "xyz"])
    repeated = _repeated_rows(speed, pos, omega, outputs, d["_line"].astype(np.int64))
    if repeated:
        warnings.warn(f"{p}: {repeated}", UserWarning, stacklevel=2)
    if not any(mps2):
        return CentrifugeTable(speed_index=speed, omega=omega, position=pos, outputs=outputs,
                               path=p)
    conv = outputs.view(_OutputsFromMps2)
    conv.g_mps2, conv.g_stated, conv.mps2_axes = gv, g is not None, mps2  # type: ignore[assignment]
    return CentrifugeTable(speed_index=speed, omega=omega, position=pos, outputs=conv, path=p,
                           g_mps2=gv, mps2_axes=mps2)  # type: ignore[arg-type]


def _repeated_rows(speed: NDArray[np.int64], pos: NDArray[np.int64], omega: NDArray[np.float64],
                   outputs: NDArray[np.float64], line: NDArray[np.int64]) -> str:
    """Words for the rows that repeat a speed index and position already in the table (by
    their line in the file and 0-based row), or ``""``: the fit counts each as a measurement
    of its own."""
    first: dict[tuple[int, int], int] = {}
    groups: dict[tuple[int, int], list[int]] = {}
    for i, key in enumerate(zip(speed.tolist(), pos.tolist(), strict=True)):
        if key in first:
            groups.setdefault(key, [first[key]]).append(i)
        else:
            first[key] = i
    if not groups:
        return ""
    same = {k: all(omega[r] == omega[rows[0]] and np.array_equal(outputs[r], outputs[rows[0]])
                   for r in rows[1:]) for k, rows in groups.items()}
    n, identical = len(groups), sum(same.values())
    parts = [f"speed {s_}, position {p_}: lines {', '.join(str(line[r]) for r in rows)} (rows "
             f"{', '.join(map(str, rows))})"
             + (", identical in every value" if same[(s_, p_)] and identical < n else "")
             for (s_, p_), rows in groups.items()]
    shown = "; ".join(parts[:8]) + (f"; ... ({n} in all)" if n > 8 else "")
    if identical == n:
        pasted = (" The repeated rows are identical in every value (speed, rate, position and "
                  "outputs): a pasted duplicate?")
    elif identical:
        pasted = f" {identical} of them are identical in every value: pasted duplicates?"
    else:
        pasted = ""
    return (f"{n} speed/position pair(s) appear in more than one row: {shown}. The fit counts "
            f"such rows twice (or more), as separate measurements, so the position weighs "
            f"double.{pasted} Remove the repeats unless they are separate measurements.")


def calibrate_centrifuge_table(
    path: str | os.PathLike[str], radius: float, g: float = 9.80665, **kwargs: Any
) -> CentrifugeFit:
    """Read a centrifuge table (:func:`read_centrifuge_table`) and run :func:`fit_centrifuge` on
    it, naming the rows by speed and position."""
    t = read_centrifuge_table(path, g=g)
    kwargs.setdefault("labels", t.labels())
    return fit_centrifuge(t.outputs, t.omega, radius, g=g, **kwargs)


# --------------------------------------------------------------------------- sensitivity


def paper_table2() -> dict[str, NDArray[np.float64]]:
    """The paper's Table 2 (its recovered values on its Table 1)."""
    return {k: v.copy() for k, v in _PAPER_TABLE2.items()}
