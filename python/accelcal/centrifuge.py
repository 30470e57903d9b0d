"""Centrifuge calibration with quadratic (K2) coefficients by norm observation (seed 004).

Model (g units): ``N = S Phi (f + K2 f^2 [+ K3 f^3]) + b``, constraint ``|f|^2 = A^2 + 1`` with
``A = omega^2 R / g``. See SPEC section 2 and ``docs/centrifuge-reproduction.md``.

Sign convention: the norm cannot tell ``S_i`` from ``-S_i`` (exactly so when K2 = 0); results
always have ``S_i > 0`` (with K2, misalignment and lever arm signs folded accordingly).
"""

from __future__ import annotations

import csv
import math
import os
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import _core
from ._core import CalibrationError

__all__ = [
    "EARTH_RATE",
    "SEED004_TRUTH",
    "CentrifugeDesign",
    "centrifuge_outputs",
    "paper_design",
    "paper_positions",
    "CentrifugeFit",
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

#: Truth of the seed-004 simulation (SPEC 2).
SEED004_TRUTH: dict[str, NDArray[np.float64]] = {
    "scale": np.array([1.29, 1.21, 1.26]),
    "bias": np.array([0.213, 0.256, 0.516]),
    "k2": np.array([0.57e-4, 0.31e-4, 0.45e-4]),
}


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
    """The seed paper's 20-position x 3-speed design (rows ordered speed-major like Table 1)."""
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
        w = w + np.sign(w) * EARTH_RATE * np.sin(np.radians(latitude_deg))
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



_PAPER_TABLE2 = {
    "k2": np.array([5.700684e-5, 3.100221e-5, 4.500459e-5]),
    "scale": np.array([1.28999, 1.21001, 1.25996]),
    "bias": np.array([0.212999, 0.256004, 0.515972]),
}


class CentrifugeOutlierWarning(UserWarning):
    """Rows inconsistent with the centrifuge model were excluded from the fit."""


@dataclass(frozen=True)
class CentrifugeFit:
    """Result of :func:`fit_centrifuge`.

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
        Parameter covariance (scaled by the residual variance unless ``sigma`` was given).
    std : ndarray (p,)
        Standard deviations, ``sqrt(diag(covariance))``.
    residuals : ndarray (k,)
        Norm residual per row, ``(|f|^2 - A^2 - 1) / (2 sqrt(A^2 + 1))`` ~ ``|f| - |f_true|``
        in g, outliers included (inf where a row cannot be inverted).
    outliers : ndarray int
        Rows excluded by the robust screen.
    residual_rms : float
        RMS of the (weighted) residuals of the rows used.
    observability : dict
        ``singular_values`` (column-normalised Jacobian), ``condition_number``, and
        ``unobservable`` (always empty: a singular design raises DegenerateDataError naming it).
    method : str
    taylor_coefficients : ndarray (13,) or None
        The regression coefficients ``[C0, C11..C13, C21..C23, C31..C33, C41..C43]``
        (taylor-paper only).
    extra : dict
        ``screen_sigma``: robust residual scale of the outlier screen (g; 0 when the plain fit
        was clean and no screen ran).
    """

    scale: NDArray[np.float64]
    bias: NDArray[np.float64]
    k2: NDArray[np.float64]
    k3: NDArray[np.float64] | None
    misalignment: NDArray[np.float64] | None
    lever_arm: NDArray[np.float64] | None
    params: NDArray[np.float64]
    names: list[str]
    covariance: NDArray[np.float64]
    std: NDArray[np.float64]
    residuals: NDArray[np.float64]
    outliers: NDArray[np.int64]
    residual_rms: float
    observability: dict[str, Any]
    method: str
    iterations: int
    converged: bool
    draws: int
    taylor_coefficients: NDArray[np.float64] | None = None
    radius: float = 1.0
    g: float = 9.80665
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def outlier_residuals(self) -> NDArray[np.float64]:
        """Residuals (g) of the excluded rows, in the order of :attr:`outliers`."""
        return np.asarray(self.residuals[self.outliers], dtype=np.float64)

    def correct(self, outputs: Any) -> NDArray[np.float64]:
        """Specific force (k, 3) in g from outputs (k, 3) in g by exact inversion of the model."""
        n = np.atleast_2d(np.asarray(outputs, dtype=np.float64))
        u = (n - self.bias) / self.scale
        if self.misalignment is not None:
            m1, m2, m3 = self.misalignment
            u = u.copy()
            u[:, 1] -= m1 * u[:, 0]
            u[:, 2] -= m2 * u[:, 0] + m3 * u[:, 1]
        disc = 1.0 + 4.0 * self.k2 * u
        if np.any(disc < 0):
            raise CalibrationError("outputs outside the invertible range of the fitted K2")
        f = 2.0 * u / (1.0 + np.sqrt(disc))
        if self.k3 is not None:
            for _ in range(30):
                hp = 1.0 + 2.0 * self.k2 * f + 3.0 * self.k3 * f**2
                f = f - (f + self.k2 * f**2 + self.k3 * f**3 - u) / hp
        return np.asarray(f, dtype=np.float64)

    def summary(self) -> str:
        """Human-readable table of parameters with standard deviations."""
        lines = [
            f"centrifuge fit ({self.method}): {len(self.residuals)} rows, "
            f"{len(self.outliers)} excluded, residual rms {self.residual_rms:.3g} g, "
            f"condition {self.observability['condition_number']:.3g}"
        ]
        for n, v, s in zip(self.names, self.params, self.std, strict=True):
            lines.append(f"  {n:<10} {v: .9g}  +- {s:.2g}")
        if len(self.outliers):
            lines.append(
                "  excluded rows: "
                + ", ".join(
                    f"{k} ({r:+.3g} g)"
                    for k, r in zip(self.outliers, self.outlier_residuals, strict=True)
                )
            )
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly dictionary (lists and floats)."""

        def conv(x: Any) -> Any:
            if isinstance(x, np.ndarray):
                return x.tolist()
            if isinstance(x, dict):
                return {k: conv(v) for k, v in x.items()}
            if isinstance(x, np.generic):
                return x.item()
            return x

        return {
            "method": self.method,
            "scale": conv(self.scale),
            "bias_g": conv(self.bias),
            "k2_g_per_g2": conv(self.k2),
            "k3_g_per_g3": conv(self.k3),
            "misalignment_rad": conv(self.misalignment),
            "lever_arm_m": conv(self.lever_arm),
            "names": list(self.names),
            "params": conv(self.params),
            "std": conv(self.std),
            "covariance": conv(self.covariance),
            "residuals_g": [float(v) if np.isfinite(v) else None for v in self.residuals],
            "outliers": conv(self.outliers),
            "residual_rms_g": self.residual_rms,
            "observability": conv(self.observability),
            "iterations": self.iterations,
            "converged": self.converged,
            "taylor_coefficients": conv(self.taylor_coefficients),
            "radius_m": self.radius,
            "g_mps2": self.g,
        }


def fit_centrifuge(
    outputs: Any,
    omega: Any,
    radius: float,
    *,
    g: float = 9.80665,
    method: str = "nls",
    k3: bool = False,
    misalignment: bool = False,
    lever_arm: str | None = None,
    spin_axis: Any = None,
    sigma: Any = None,
    robust: bool = True,
    outlier_k: float = 5.0,
    max_draws: int = 20000,
    seed: int = 0,
) -> CentrifugeFit:
    """Calibrate an accelerometer triad from centrifuge per-position mean outputs.

    Parameters
    ----------
    outputs : array_like (k, 3)
        Mean outputs per position and speed (g).
    omega : array_like (k,)
        Spin rate of each row (rad/s); at least two distinct non-zero speeds.
    radius : float
        Nominal radius (m).
    g : float
        Gravity (m/s^2) used to express ``A = omega^2 R / g`` in g.
    method : {"nls", "taylor-paper"}
        ``"nls"``: exact per-axis inversion and least squares on the norm (default).
        ``"taylor-paper"``: the paper's 13-coefficient regression with the corrected closed form
        of SPEC 2 (scale + bias + K2 only; D is biased by the truncated series).
    k3, misalignment : bool
        Add the cubic coefficient / the three observable small misalignment angles (nls only).
    lever_arm : {None, "along", "full"}
        Per-accelerometer offset along its own axis (3 params) or full vector (9 params),
        in m; needs ``spin_axis``. A design that cannot see a component raises
        DegenerateDataError naming it.
    spin_axis : array_like (k, 3), optional
        Spin-axis (up) unit vector in the body frame per row (lever-arm models).
    sigma : array_like (k,), optional
        Standard deviation of each row's norm (g); then the covariance is absolute.
    robust : bool
        Screen rows inconsistent with the model (least median of squares over random minimal
        subsets, seeded) when the plain fit shows outliers; excluded rows raise a
        :class:`CentrifugeOutlierWarning` naming them.
    outlier_k : float
        Threshold in robust standard deviations.
    max_draws : int
        Maximum random subsets of the screen.
    seed : int
        Seed of the subset generator (the result is deterministic).

    Returns
    -------
    CentrifugeFit
    """
    # Cheap checks here (clear messages); values (finite, speeds, design) are checked in Rust.
    # The core reads any strides, so no contiguous copies are made.
    out = np.asarray(outputs, dtype=np.float64)
    if out.ndim != 2 or out.shape[1] != 3:
        raise CalibrationError(f"outputs must have shape (k, 3) in g; got {out.shape}")
    om = np.asarray(omega, dtype=np.float64)
    if om.ndim != 1:
        om = om.ravel()
    if om.shape[0] != out.shape[0]:
        raise CalibrationError(
            f"omega has {om.shape[0]} values but outputs have {out.shape[0]} rows"
        )
    try:
        r = float(radius)
    except (TypeError, ValueError):
        raise CalibrationError(f"radius must be a number (m); got {radius!r}") from None
    if not (0.0 < r < math.inf):
        raise CalibrationError(f"radius must be positive and finite (m); got {radius!r}")
    try:
        gg = float(g)
    except (TypeError, ValueError):
        raise CalibrationError(f"g must be a number; got {g!r}") from None
    if not (0.0 < gg < math.inf):
        raise CalibrationError(f"g must be positive and finite (m/s^2); got {g!r}")
    sa = None
    if spin_axis is not None:
        sa = np.ascontiguousarray(spin_axis, dtype=np.float64)
        if sa.shape != out.shape:
            raise CalibrationError(f"spin_axis must have shape {out.shape}; got {sa.shape}")
    sg = None
    if sigma is not None:
        sg = np.ascontiguousarray(np.broadcast_to(np.asarray(sigma, np.float64), om.shape))
    d = _core.centrifuge_fit_raw(
        out, om, r, gg, method, k3, misalignment, lever_arm, sa, sg,
        robust, float(outlier_k), 1e-9, int(max_draws), int(seed),
    )
    return _build(d, method, r, gg, k3, misalignment, lever_arm, warn=True)


def _build(
    d: dict[str, Any], method: str, radius: float, g: float, k3: bool, mis: bool,
    lever: str | None, warn: bool,
) -> CentrifugeFit:
    # The core returns every array in its final dtype and shape (params, covariance (p, p),
    # std, residuals, int64 outliers, singular values): only views are taken here.
    p = d["params"]
    outliers = d["outliers"]
    res = d["residuals"]
    if warn and len(outliers):
        warnings.warn(
            f"excluded {len(outliers)} of {len(res)} rows inconsistent with |f|^2 = A^2 + 1 "
            f"(rows {outliers.tolist()}; residuals "
            + ", ".join(f"{v:+.3g}" for v in res[outliers])
            + " g)",
            CentrifugeOutlierWarning,
            stacklevel=3,
        )
    # Parameter order (ModelOptions::names): S, b, K2 [, K3] [, m_yx m_zx m_zy] [, lever].
    at = 12 if k3 else 9
    misv = None
    if mis:
        misv = p[at : at + 3]
        at += 3
    lev: NDArray[np.float64] | None = None
    if lever == "along":
        lev = p[at : at + 3]
    elif lever == "full":
        lev = p[at : at + 9].reshape(3, 3)
    # The core's dict keys are CentrifugeFit field names (params, names, covariance, std,
    # residuals, outliers, residual_rms, observability, iterations, converged, draws,
    # taylor_coefficients, extra): copy them and add the views and the settings.
    obj: CentrifugeFit = object.__new__(CentrifugeFit)
    f = obj.__dict__
    f.update(d)
    f["scale"] = p[0:3]
    f["bias"] = p[3:6]
    f["k2"] = p[6:9]
    f["k3"] = p[9:12] if k3 else None
    f["misalignment"] = misv
    f["lever_arm"] = lev
    f["method"] = method
    f["radius"] = radius
    f["g"] = g
    return obj


# --------------------------------------------------------------------------- seed table I/O


@dataclass(frozen=True)
class CentrifugeTable:
    """A centrifuge table in the seed-004 CSV format (per-position mean outputs in g)."""

    speed_index: NDArray[np.int64]
    omega: NDArray[np.float64]
    position: NDArray[np.int64]
    outputs: NDArray[np.float64]
    path: str = ""

    def __len__(self) -> int:
        return int(self.omega.shape[0])


_COLUMNS = ("speed_index", "omega_rad_s", "position", "N_ax_g", "N_ay_g", "N_az_g")


def read_centrifuge_table(path: str | os.PathLike[str]) -> CentrifugeTable:
    """Read a CSV with columns speed_index, omega_rad_s, position, N_ax_g, N_ay_g, N_az_g."""
    try:
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except OSError as e:
        raise CalibrationError(f"cannot read centrifuge table {path}: {e}") from None
    if not rows:
        raise CalibrationError(f"{path}: empty file")
    head = [h.strip() for h in rows[0]]
    missing = [c for c in _COLUMNS if c not in head]
    if missing:
        raise CalibrationError(f"{path}: missing column(s) {missing}; expected {list(_COLUMNS)}")
    col = {c: head.index(c) for c in _COLUMNS}
    body = [r for r in rows[1:] if any(x.strip() for x in r)]
    if not body:
        raise CalibrationError(f"{path}: no data rows")
    try:
        vals = {c: np.array([float(r[col[c]]) for r in body]) for c in _COLUMNS}
    except (ValueError, IndexError) as e:
        raise CalibrationError(f"{path}: malformed row ({e})") from None
    return CentrifugeTable(
        speed_index=vals["speed_index"].astype(np.int64),
        omega=vals["omega_rad_s"],
        position=vals["position"].astype(np.int64),
        outputs=np.c_[vals["N_ax_g"], vals["N_ay_g"], vals["N_az_g"]],
        path=str(path),
    )


def calibrate_centrifuge_table(
    path: str | os.PathLike[str], radius: float, g: float = 9.80665, **kwargs: Any
) -> CentrifugeFit:
    """Read a seed-004-format table and run :func:`fit_centrifuge` on it (CLI entry point)."""
    t = read_centrifuge_table(path)
    return fit_centrifuge(t.outputs, t.omega, radius, g=g, **kwargs)


# --------------------------------------------------------------------------- sensitivity


def paper_table2() -> dict[str, NDArray[np.float64]]:
    """The paper's Table 2 (its recovered values on its Table 1)."""
    return {k: v.copy() for k, v in _PAPER_TABLE2.items()}
