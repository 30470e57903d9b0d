"""Experiment design before any test is run: which poses, azimuths or error budgets give the
accuracy a user needs.

- Static field calibration: :func:`predict_accuracy` (Cramer-Rao bound of a pose set) and
  :func:`plan_poses` (D-optimal attitudes within a platform's reach).
- Gradiometer start-up: :func:`plan_azimuths` (balanced / time-symmetric azimuth sequences)
  and :func:`predict_startup_accuracy`.
- Centrifuge: :func:`centrifuge_sensitivity` (parameter shifts caused by an error source the
  fit does not model).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._core import CalibrationError, DegenerateDataError
from ._triad import PARAM_NAMES, attitudes_to_force, fibonacci_sphere, n_params
from ._validate import number, real_array
from .centrifuge import CENTRIFUGE_TRUTH, CentrifugeMethod, centrifuge_outputs, paper_design
from .gradiometer import _F64, _azimuths, _dwell_std, _times

__all__ = [
    "CentrifugeSensitivity",
    "PosePlan",
    "Prediction",
    "SENSITIVITY_SOURCES",
    "StartupPrediction",
    "centrifuge_sensitivity",
    "plan_azimuths",
    "plan_poses",
    "predict_accuracy",
    "predict_startup_accuracy",
]


# ------------------------------------------------------------------------------------------
# Static field calibration: pose design
# ------------------------------------------------------------------------------------------
def _default_truth(model: str, truth: ArrayLike | None) -> NDArray[np.float64]:
    p = n_params(model)
    if truth is None:
        return np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])[:p]
    v = np.asarray(truth, dtype=np.float64).reshape(-1)
    if v.size < p:
        raise CalibrationError(f"truth needs {p} values for model {model!r}; got {v.size}")
    return v[:p]


class Prediction(_core.Prediction):
    """Cramer-Rao bound of a pose design (computed in Rust): ``std`` (p,) and ``covariance``
    (p, p) in output units, ``singular`` when some combination is undetermined (``combination``
    names it), ``condition`` of the whitened Jacobian in comparable units, ``force`` (n, 3)
    the specific force at each pose."""

    @property
    def names(self) -> tuple[str, ...]:
        return PARAM_NAMES[: self.std.size]

    def table(self) -> str:
        return "\n".join(f"  {n:<4} +-{s:.3g}" for n, s in zip(self.names, self.std, strict=True))

    def __repr__(self) -> str:
        return (
            f"Prediction(model={self.model!r}, poses={len(self.force)}, singular={self.singular}, "
            f"std={np.array2string(self.std, precision=3)})"
        )


def predict_accuracy(
    attitudes: ArrayLike,
    sigma: float,
    model: str = "lower",
    *,
    g: float = 9.80665,
    truth: ArrayLike | None = None,
    sigma_g: float | None = None,
) -> Prediction:
    """Cramer-Rao bound of a pose design before any test is run.

    Parameters
    ----------
    attitudes : (n, 2) platform tilts (tx, ty) in degrees, or (n, 3) gravity directions
        (n >= 1; fewer poses than parameters give an infinite, singular bound)
    sigma : std of each dwell mean per axis (output units), positive
    model : "lower", "diag" or "upper";  g : gravity (units of the calibrated output), positive
    truth : parameter vector at which to evaluate (default K = I, b = 0)
    sigma_g : std of the reference gravity (units of g), optional: its covariance
        ``sigma_g^2 j j^T`` (``j = dp/dg = -p / g`` for the entries of K, 0 for the biases) is
        added to ``covariance`` and ``std``, as :func:`~accelcal.fit_static` does; the
        singularity report (``singular``, ``condition``, ``combination``) leaves it out.
        Non-negative, finite, at most 1 % of g.
    """
    n_params(model)
    gv = number(g, "g", lo=0.0, lo_open=True, unit="(reference gravity)")
    sv = number(sigma, "sigma", lo=0.0, lo_open=True, unit="(std of a dwell mean, output units)")
    v = _default_truth(model, truth)
    force = attitudes_to_force(attitudes, gv)
    return Prediction(force, sv, cast(Any, model), g=gv, truth=v.tolist(), sigma_g=sigma_g)


def design_rows(
    force: NDArray[np.float64], truth: NDArray[np.float64], model: str, sigma: float
) -> NDArray[np.float64]:
    """Fisher-information rows (n, p) of poses with specific force ``force`` (n, 3) at the
    parameters ``truth``, dwell-mean noise ``sigma`` per axis (computed in Rust)."""
    return _core.static_design_rows(  # type: ignore[no-any-return]
        np.asarray(force, dtype=np.float64), list(map(float, truth)), cast(Any, model), sigma
    )


@dataclass
class PosePlan:
    """D-optimal pose set from :func:`plan_poses`.

    tilts_deg : (n, 2) platform tilts (tx, ty), or None for the full sphere;
    directions : (n, 3) unit gravity directions in the sensor frame (the specific force at
    rest, pointing up); prediction : Cramer-Rao bound of the plan; logdet : log det of the
    information matrix. :meth:`pose_names` says how to place the sensor for each pose.
    """

    tilts_deg: NDArray[np.float64] | None
    directions: NDArray[np.float64]
    prediction: Prediction
    logdet: float
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def std(self) -> NDArray[np.float64]:
        return self.prediction.std

    @property
    def attitudes(self) -> NDArray[np.float64]:
        return self.tilts_deg if self.tilts_deg is not None else self.directions

    def pose_names(self) -> list[str]:
        """How a person places the sensor for each pose, e.g. "bottom down, nose up 30 deg,
        left side down 12 deg" (axes: x nose, y left side, z top)."""
        return [pose_name(d) for d in self.directions]

    def to_csv(self, path: str | None = None) -> str:
        """The poses as CSV, one row per pose in order: ``pose`` (1-based), the platform tilts
        ``tilt_x_deg, tilt_y_deg`` when planned for a two-axis platform, the unit gravity
        direction in the sensor frame ``gx, gy, gz``, and the placement in words. Written
        atomically to ``path`` when given; the text is returned either way."""
        import csv
        import io

        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        tilt = self.tilts_deg is not None
        w.writerow(["pose", *(["tilt_x_deg", "tilt_y_deg"] if tilt else []), "gx", "gy", "gz",
                    "placement"])
        for i, (d, nm) in enumerate(zip(self.directions, self.pose_names(), strict=True)):
            t = [f"{v:.6g}" for v in self.tilts_deg[i]] if self.tilts_deg is not None else []
            w.writerow([i + 1, *t, *(f"{(0.0 if abs(v) < 5e-10 else v):.9f}" for v in d), nm])
        text = buf.getvalue()
        if path is not None:
            from ._files import atomic_write

            atomic_write(path, text)
        return text

    def checklist(self) -> str:
        """Numbered checklist of the poses in order, with the platform tilts when planned
        for a two-axis platform."""
        lines = [
            "axes: x = nose (forward), y = left side, z = top; 'down' is the face towards the "
            "ground"
        ]
        for i, nm in enumerate(self.pose_names(), start=1):
            extra = ""
            if self.tilts_deg is not None:
                tx, ty = self.tilts_deg[i - 1]
                extra = f"  (platform tilt x {tx:+.1f} deg, y {ty:+.1f} deg)"
            lines.append(f"[ ] {i:>2}. {nm}{extra}")
        return "\n".join(lines)


_AXIS_END = {(0, 1): "nose", (0, -1): "tail", (1, 1): "left side", (1, -1): "right side",
             (2, 1): "top", (2, -1): "bottom"}


def pose_name(direction: ArrayLike, min_deg: float = 0.5) -> str:
    """Name the pose whose specific force at rest (gravity direction, pointing up) is
    ``direction`` in the sensor frame (x nose, y left side, z top): the face towards the
    ground, then how far each other axis end is raised above (or lowered below) the
    horizontal, as an inclinometer laid along that axis reads it, e.g. "bottom down, nose up
    30 deg" or "left side down, level"."""
    d = np.asarray(direction, dtype=np.float64).reshape(3)
    nrm = float(np.linalg.norm(d))
    if not (nrm > 0 and math.isfinite(nrm)):
        raise CalibrationError(f"a pose direction must be a finite non-zero vector; got {d}")
    d = d / nrm
    k = int(np.argmax(np.abs(d)))
    # The face towards the ground is the axis end opposite to the (upward) specific force.
    face = _AXIS_END[(k, -1 if d[k] > 0 else 1)]
    parts = [f"{face} down"]
    for i in range(3):
        if i == k:
            continue
        ang = math.degrees(math.asin(min(1.0, abs(d[i]))))
        if ang >= min_deg:
            parts.append(f"{_AXIS_END[(i, 1)]} {'up' if d[i] > 0 else 'down'} {ang:.0f} deg")
    if len(parts) == 1:
        parts.append("level")
    return ", ".join(parts)


def _fedorov(
    F: NDArray[np.float64], n: int, gen: np.random.Generator,
    start: NDArray[np.int64] | None = None,
) -> tuple[NDArray[np.int64], float]:
    """Fedorov exchange for D-optimality over candidate rows F (C, p); repeats allowed. From
    ``start`` (candidate indices) or a random draw; at most 200 exchanges."""
    C, p = F.shape
    idx = gen.choice(C, size=n, replace=C < n) if start is None else start.copy()
    ridge = 1e-10 * np.trace(F.T @ F) / C
    for _ in range(200):
        M = F[idx].T @ F[idx] + ridge * np.eye(p)
        Mi = np.linalg.inv(M)
        G = F @ Mi  # (C, p)
        dc = np.einsum("ij,ij->i", G, F)  # d(c)
        di = dc[idx]  # d(i)
        dic = G[idx] @ F.T  # (n, C): d(i, c)
        delta = (1 + dc[None, :]) * (1 - di[:, None]) + dic**2 - 1
        i, c = np.unravel_index(int(np.argmax(delta)), delta.shape)
        if delta[i, c] <= 1e-10:
            break
        idx[i] = c
    M = F[idx].T @ F[idx]
    sign, logdet = np.linalg.slogdet(M)
    return idx, float(logdet) if sign > 0 else -np.inf


#: Above this many poses, plan_poses starts its exchanges from a plan of this many repeated.
_BASE_POSES = 60
#: A predicted std (relative units) above which the fit counts a combination undetermined
#: (fit_static's default degenerate_std).
_UNDETERMINED_STD = 3.0


def plan_poses(
    n: int,
    max_tilt_deg: float | None = 30.0,
    *,
    sigma: float = 1e-3,
    model: str = "lower",
    g: float = 9.80665,
    truth: ArrayLike | None = None,
    grid_step_deg: float | None = None,
    restarts: int = 4,
    rng: int | np.random.Generator | None = 0,
) -> PosePlan:
    """Choose ``n`` attitudes minimising the predicted covariance (D-optimal).

    ``max_tilt_deg`` in (0, 90] bounds both tilts of a two-axis platform (candidates on a
    grid of ``grid_step_deg``, default max_tilt/20; 90 therefore reaches only the upper
    hemisphere with z up or level); ``None`` plans over the whole sphere (2000 near-uniform
    directions). ``n`` is an integer in [p, 10000] (p = 9, or 6 for ``model="diag"``).
    Returns the plan with the Cramer-Rao std of every parameter for dwell-mean noise
    ``sigma`` (output units). Attitudes may repeat (that is what a D-optimal design does
    when n exceeds the number of distinct useful poses).
    """
    p = n_params(model)
    ni = number(n, "n", lo=1, hi=10_000, integer=True, unit="poses")
    if ni < p:
        raise DegenerateDataError(
            f"n = {ni} poses cannot determine the {p} parameters of model {model!r} "
            f"(need n >= {p})"
        )
    sv = number(sigma, "sigma", lo=0.0, lo_open=True, unit="(std of a dwell mean, output units)")
    gv = number(g, "g", lo=0.0, lo_open=True, unit="(reference gravity)")
    rs = number(restarts, "restarts", lo=1, hi=1000, integer=True, unit="exchange restarts")
    v = _default_truth(model, truth)
    gen = np.random.default_rng(rng)
    if max_tilt_deg is None:
        cand_dirs = fibonacci_sphere(2000)
        tilts = None
        force = gv * cand_dirs
    else:
        mt = number(max_tilt_deg, "max_tilt_deg", lo=1.0, hi=90.0,
                    unit="deg (None for the full sphere)")
        step = mt / 20.0
        if grid_step_deg is not None:
            step = number(grid_step_deg, "grid_step_deg", lo=mt / 200.0, hi=mt, unit="deg")
        # Grid points -mt, -mt + step, ..., up to +mt (both ends when step divides 2 mt).
        n_ax = int(np.floor(2.0 * mt / step * (1.0 + 1e-12))) + 1
        ax = -mt + step * np.arange(n_ax)
        if ax[-1] < mt * (1.0 - 1e-9):  # a step that does not divide 2 mt: +mt all the same
            ax = np.append(ax, mt)
        tx, ty = np.meshgrid(ax, ax, indexing="ij")
        tilts = np.stack([tx.ravel(), ty.ravel()], axis=1)
        force = attitudes_to_force(tilts, gv)
        cand_dirs = force / gv
    F = design_rows(force, v, model, sv)
    best: tuple[NDArray[np.int64], float] | None = None
    for _ in range(rs):
        start = None
        if ni > _BASE_POSES:
            # 200 exchanges from a random draw of hundreds of poses stop short of the optimum
            # (n = 2000: log det 2.9 below the n = 20 plan repeated): start from a plan of
            # fewer poses repeated, which the exchanges then only improve.
            base, _ = _fedorov(F, _BASE_POSES, gen)
            start = np.resize(base, ni)
        idx, ld = _fedorov(F, ni, gen, start)
        if best is None or ld > best[1]:
            best = (idx.copy(), ld)
    assert best is not None
    idx = best[0]
    dirs = cand_dirs[idx]
    tl = None if tilts is None else tilts[idx]
    pred = predict_accuracy(dirs, sv, model, g=gv, truth=v)
    rel = np.asarray(pred.std, dtype=np.float64) / np.array(
        [1.0, 1.0, 1.0, gv, gv, gv, 1.0, 1.0, 1.0][:p])
    worst = int(np.argmax(rel)) if np.all(np.isfinite(rel)) else -1
    if worst < 0 or rel[worst] > _UNDETERMINED_STD:
        from .static import WeakDesignWarning

        where = ("the whole sphere" if tilts is None else f"tilts within +-{mt:g} deg")
        said = ("some parameter has no finite std" if worst < 0 else
                f"{PARAM_NAMES[worst]} is left at a predicted std of {rel[worst]:.3g} "
                f"relative{' (in g)' if 3 <= worst < 6 else ''}")
        warnings.warn(
            f"the best {ni} poses over {where} cannot determine model {model!r} at dwell-mean "
            f"noise {sv:g}: {said}, above {_UNDETERMINED_STD:g}, where fit_static refuses "
            "as undetermined; plan larger tilts, lower noise (longer dwells) or model 'diag'",
            WeakDesignWarning, stacklevel=2)
    return PosePlan(tl, dirs, pred, best[1], {"candidates": F.shape[0], "model": model})


# ------------------------------------------------------------------------------------------
# Gradiometer start-up: azimuth sequence design
# ------------------------------------------------------------------------------------------
def plan_azimuths(m: int, drift: bool = False) -> _F64:
    """Azimuth sequence (deg, in [0, 180)) of ``m`` dwells for the bias.

    Without drift: the balanced set ``theta_k = 180 k / m`` (``sum exp(2i theta_k) = 0``), for
    which the bias is the plain mean and ``Var(bias_j) = sigma^2 / m``. With drift: a
    palindromic (time-symmetric, return-to-start) sequence, which with equally spaced dwells
    decorrelates the drift from bias and gradient; for even ``m`` it repeats a balanced set
    forwards then backwards (ABBA for ``m = 4``), for odd ``m >= 5`` the angles are chosen so the
    set is still balanced, and each reaches the no-drift minimum ``sigma^2 / m`` of the bias
    variance (``m >= 4``). ``m = 3`` gives the return-to-start 0/90/0: bias variance 3/8, gradient
    3/8, drift 1/2 (in sigma^2, unit dwell spacing); 0/60/120 would give the bias 1/3 but the
    gradient 2/3 and the drift 1.
    """
    m = number(m, "m", lo=1, hi=100_000, integer=True, unit="dwells")
    if not drift:
        if m < 2:
            raise DegenerateDataError(
                "at least 2 azimuths 90 deg apart are needed to separate bias and gradient"
            )
        return 180.0 * np.arange(m) / m
    if m < 3:
        raise DegenerateDataError(
            "the drift model needs at least 3 dwells (e.g. the return-to-start sequence 0/90/0)"
        )
    if m == 3:
        return np.array([0.0, 90.0, 0.0])
    if m % 2 == 0:
        half = 180.0 * np.arange(m // 2) / (m // 2)
        return np.concatenate([half, half[::-1]])
    # Odd m = 2n + 1: pairs (2 theta = +-alpha) plus a centre at 0 deg, balanced:
    # 2 sum(pairs) + 1 = 0.
    n = (m - 1) // 2
    if n % 2 == 0:
        alpha = np.degrees(np.arccos(-1.0 / (2 * n)))
        pairs2 = np.tile([alpha, -alpha], n // 2)
    else:
        alpha = np.degrees(np.arccos(1.0 / (2 * (n - 1))))
        pairs2 = np.concatenate([[180.0], np.tile([alpha, -alpha], (n - 1) // 2)])
    pairs = np.mod(pairs2 / 2.0, 180.0)
    return np.concatenate([pairs, [0.0], pairs[::-1]])


class StartupPrediction(_core.StartupPredictionCore):
    """Predicted accuracy of a start-up sequence before it is run (the data live in the Rust
    result; arrays are read-only; pickles).

    Attributes
    ----------
    covariance : (p, p)
        From the noise alone (``sigma`` per average), order ``[bias_I, bias_C, I, C, (drift)]``.
    azimuth_covariance : (p, p)
        From independent azimuth errors ``sigma_theta`` (first order).
    total_covariance : (p, p)
        Their sum.
    std : (p,)
        Square roots of the total covariance diagonal.
    closed_form_variance : float
        Closed form ``sigma^2 m / (m^2 - |U|^2)`` with ``U = sum exp(-2i theta_k)`` (equal
        weights, no drift; ``sigma`` the mean noise std).
    condition : float
        Condition number of the design.
    names : list of str
    """

    __slots__ = ()

    @property
    def bias_std(self) -> _F64:
        """Predicted std of the bias, E."""
        return self.std[:2]

    @property
    def gradient_std(self) -> _F64:
        """Predicted std of the gradient, E."""
        return self.std[2:4]

    @property
    def drift_std(self) -> _F64 | None:
        """Predicted std of the drift, E/s (drift model only)."""
        return self.std[4:6] if self.std.size == 6 else None


def predict_startup_accuracy(
    azimuths: ArrayLike,
    times: ArrayLike | None = None,
    sigma: float | ArrayLike = 1.0,
    sigma_theta: float = 0.0,
    *,
    gradient: float | ArrayLike | None = None,
    drift: bool | None = None,
    t_ref: float | None = None,
) -> StartupPrediction:
    """Covariance of the start-up estimate for a planned sequence.

    Parameters
    ----------
    azimuths : (m,) float
        Planned azimuths, deg.
    times : (m,) float, optional
        Planned dwell mid times, s; the drift model is used when given (unless ``drift``).
    sigma : float or (m,) float
        Noise std of one average, E.
    sigma_theta : float
        Std of independent azimuth errors, deg (a common offset does not affect the bias).
    gradient : float or (2,) float, optional
        Navigation-frame gradient ``(I, C)`` in E for the exact azimuth-error effect, or its
        magnitude (effect averaged over the direction: ``Var(bias_j) ~ 2 sigma_theta^2
        |gamma|^2 / m`` for balanced sets). Required when ``sigma_theta > 0``.
    drift : bool, optional
        Force the drift model on or off (default: on when ``times`` are given).
    t_ref : float, optional
        Reference time of the bias with drift (default the mean time).
    """
    az = _azimuths(azimuths)
    m = az.size
    tt = _times(times, m, "times")
    use_drift = tt is not None if drift is None else bool(drift)
    if use_drift and tt is None:
        raise CalibrationError("the drift model needs the planned dwell times")
    sd = _dwell_std(sigma, m)
    st = number(sigma_theta, "sigma_theta", lo=0.0, unit="deg")
    gvec = None
    gmag = 0.0
    if gradient is not None:
        g = real_array(gradient, "gradient", "E").reshape(-1)
        if g.size == 1 and np.isfinite(g[0]):
            gmag = float(abs(g[0]))
        elif g.size == 2 and np.all(np.isfinite(g)):
            gvec = [float(g[0]), float(g[1])]
        else:
            raise CalibrationError(
                f"gradient must be a finite magnitude or (I, C) in E; got {gradient!r}"
            )
    elif st > 0:
        raise CalibrationError(
            "sigma_theta > 0 needs the gradient (E): its effect on the bias scales with |gamma|"
        )
    tref = None if t_ref is None or not use_drift else number(t_ref, "t_ref", unit="s")
    raw = _core.startup_predict_raw(az, sd, tt if use_drift else None, tref, gvec, gmag, st)
    return StartupPrediction(*raw.__reduce__()[1])


# ------------------------------------------------------------------------------------------
# Centrifuge: sensitivity to unmodelled error sources
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CentrifugeSensitivity:
    """Parameter shifts caused by an unmodelled error source.

    Attributes
    ----------
    source : str
    magnitudes : ndarray (m,)
    names : list of str
        ``sx, sy, sz, bx, by, bz, k2x, k2y, k2z``.
    shifts : ndarray (m, 9)
        Fitted minus fitted-without-the-error (so the method's own bias cancels).
    baseline : ndarray (9,)
        Fit on the error-free outputs.
    method : str
    """

    source: str
    magnitudes: NDArray[np.float64]
    names: list[str]
    shifts: NDArray[np.float64]
    baseline: NDArray[np.float64]
    method: str

    def table(self) -> str:
        """Text table: one row per magnitude."""
        head = f"{'magnitude':>10} " + " ".join(f"{n:>10}" for n in self.names)
        lines = [f"source {self.source} ({self.method})", head]
        for m, row in zip(self.magnitudes, self.shifts, strict=True):
            lines.append(f"{m:>10.3g} " + " ".join(f"{v:>10.3g}" for v in row))
        return "\n".join(lines)


SENSITIVITY_SOURCES = (
    "misalignment",
    "lever_along_x", "lever_along_y", "lever_along_z",
    "lever_<accel>_<dir>  (accel, dir in x, y, z; e.g. lever_x_z: x accelerometer moved along z)",
    "radius", "rate", "earth_rate",
)


def _error_kwargs(source: str, mag: float) -> dict[str, Any]:
    axes = "xyz"
    if source == "misalignment":
        gm = mag
        return {"misalignment": np.array([[0, -gm, gm], [gm, 0, -gm], [-gm, gm, 0]], float)}
    parts = source.split("_")
    if len(parts) == 3 and parts[0] == "lever":
        if parts[1] == "along" and parts[2] in axes:
            i = j = axes.index(parts[2])
        elif parts[1] in axes and parts[2] in axes:
            i, j = axes.index(parts[1]), axes.index(parts[2])
        else:
            raise CalibrationError(f"unknown lever-arm source {source!r}")
        lev = np.zeros((3, 3))
        lev[i, j] = mag
        return {"lever_arm": lev}
    if source == "radius":
        return {"radius_error": mag}
    if source == "rate":
        return {"rate_error": mag}
    if source == "earth_rate":
        return {"latitude_deg": mag}
    raise CalibrationError(f"unknown error source {source!r}; choose from {SENSITIVITY_SOURCES}")


def centrifuge_sensitivity(
    design: Any = None,
    truth: dict[str, Any] | None = None,
    source: str = "lever_along_x",
    magnitudes: Any = (0.02,),
    *,
    method: CentrifugeMethod = "taylor-paper",
    g: float = 9.8,
) -> CentrifugeSensitivity:
    """Shift of the fitted S, b, K2 caused by an error source the fit does not model.

    Parameters
    ----------
    design : CentrifugeDesign, optional
        Default: the paper's 20 positions x 3 speeds, R = 1 m.
    truth : dict, optional
        ``scale``, ``bias`` (g), ``k2`` (g/g^2); default the paper's truth.
    source : str
        ``misalignment`` (all six paper angles = magnitude, rad); ``lever_along_<axis>``
        (accelerometer <axis> displaced along its own axis, m); ``lever_<accel>_<dir>``
        (accelerometer <accel> displaced along body axis <dir>, m; in the paper's design the
        body y axis is always horizontal, so e.g. ``lever_x_y`` has exactly no first-order
        effect while ``lever_x_z`` does); ``radius`` (true - nominal, m); ``rate`` (relative
        rate error); ``earth_rate`` (magnitude = latitude, deg).
    magnitudes : array_like (m,)
    method : {"taylor-paper", "nls"}
        The paper's analysis (Table 3 / Fig. 4) used its closed form: the default.
    g : float
        Gravity (m/s^2) of the simulation and the fit.

    Returns
    -------
    CentrifugeSensitivity
    """
    des = design if design is not None else paper_design()
    tr = dict(CENTRIFUGE_TRUTH)
    if truth:
        tr.update({k: np.asarray(v, float) for k, v in truth.items()})
    kw: dict[str, Any] = {"scale": tr["scale"], "bias": tr["bias"], "k2": tr["k2"], "g": g}
    mags = np.atleast_1d(real_array(magnitudes, "magnitudes")).reshape(-1)
    if not np.all(np.isfinite(mags)):
        raise CalibrationError(f"magnitudes must be finite; got {magnitudes!r}")
    if method not in ("nls", "taylor-paper"):
        raise CalibrationError(f"unknown method {method!r}; use 'taylor-paper' or 'nls'")
    _error_kwargs(source, 0.0)  # validate the name first
    if source == "radius" and np.any(mags <= -des.radius):
        raise CalibrationError(
            f"magnitudes for source 'radius' are radius errors in m (true - nominal) and must "
            f"exceed -{des.radius:g} m (the nominal radius); got {mags.tolist()}"
        )
    if source == "rate" and np.any(mags <= -1.0):
        raise CalibrationError(
            f"magnitudes for source 'rate' are relative rate errors and must exceed -1; "
            f"got {mags.tolist()}"
        )

    def run(n: NDArray[np.float64]) -> NDArray[np.float64]:
        # The error is injected on purpose: the unit check must not refuse what it does.
        fit = _core.centrifuge_fit_raw(n, des.omega, des.radius, g, method, robust=False,
                                       check_units=False)
        return np.asarray(fit.params)

    def shifted(m: float) -> NDArray[np.float64]:
        try:
            return run(centrifuge_outputs(des, **kw, **_error_kwargs(source, m))) - base
        except CalibrationError as e:
            raise type(e)(
                f"source {source!r} with magnitude {m!r}: the perturbed outputs cannot be "
                f"fitted ({e}); the magnitude is far beyond a sensitivity analysis' range"
            ) from None

    base = run(centrifuge_outputs(des, **kw))
    shifts = np.array([shifted(float(m)) for m in mags])
    return CentrifugeSensitivity(
        source=source,
        magnitudes=mags,
        names=["sx", "sy", "sz", "bx", "by", "bz", "k2x", "k2y", "k2z"],
        shifts=shifts,
        baseline=base,
        method=method,
    )
