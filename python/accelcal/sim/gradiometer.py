"""Rotating-accelerometer gravity gradiometer start-up simulator, with known truth.

Four accelerometers on a disc of radius R spinning at omega about the platform z axis, sensing
axes tangential. Accelerometer i (0..3) sits at phase ``phi_i = phi + i pi / 2`` at
``r_i = R (cos phi_i, sin phi_i, 0)`` with axis ``t_i = (-sin phi_i, cos phi_i, 0)`` in the
platform frame. Its specific force is computed physically::

    f_i = t_i . [f0 + omega_dot x r_i - (Gamma_p - Omega^2) r_i]

where ``Gamma_p`` is the gravity-gradient tensor in the platform frame and ``Omega^2 = W W^T -
|W|^2 I`` the centripetal term of the disc's total angular rate ``W = (Wx, Wy, omega)``. Hence
``f_i = R [I' sin 2phi_i - C' cos 2phi_i] + R omega_dot + t_i . f0`` with the effective gradient
``I' = I_p - (Wx^2 - Wy^2)/2``, ``C' = C_p - Wx Wy``. The per-startup bias (and drift)
enters as an instrument-fixed 2-omega signal ``R [b_I sin 2phi_i - b_C cos 2phi_i]``. Each
accelerometer then has a scale error ``(1 + k_i)`` and white noise.

Frames: navigation x north, y east, z down; the platform x axis at azimuth theta, so
``Gamma_p = Rz(theta)^T Gamma Rz(theta)`` and ``(I_p, C_p) = R(2 theta) (I, C)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._core import CalibrationError

__all__ = ["GradiometerSession", "GradiometerTruth", "gradiometer_session"]

EOTVOS = 1e-9
_F64 = NDArray[np.float64]


def _rz(theta_rad: float) -> _F64:
    c, s = np.cos(theta_rad), np.sin(theta_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ic(g: _F64) -> _F64:
    return np.array([(g[0, 0] - g[1, 1]) / 2.0, g[0, 1]])


@dataclass(frozen=True)
class GradiometerTruth:
    """What the simulator used (gradients and biases in E, rates in rad/s).

    ``gradient_E`` is the navigation-frame ``(I, C)`` of ``tensor_E``; ``sensor_gradient_E``
    (m, 2) the platform-frame ``(I, C)`` at each true azimuth; ``rate_terms_E`` (m, 2) the
    formula ``(-(Wx^2 - Wy^2)/2, -Wx Wy)`` with the platform-frame rates of each dwell;
    ``channels_E`` (m, 2) what a perfect demodulator returns: ``gain * (sensor + rates + bias at
    the dwell's mid time)`` with ``gain`` the mean accelerometer scale. The effective start-up
    unknowns are ``effective_bias_E`` (bias plus rate terms fixed in the platform frame) and
    ``effective_gradient_E`` (gradient plus rate terms fixed in the navigation frame).
    """

    tensor_E: _F64
    gradient_E: _F64
    bias_E: _F64
    drift_E_per_s: _F64
    azimuth_true_deg: _F64
    rates_rad_s: _F64
    rates_frame: str
    platform_rates_rad_s: _F64
    sensor_gradient_E: _F64
    rate_terms_E: _F64
    channels_E: _F64
    dwell_t_mid: _F64
    scale: _F64
    gain: float
    effective_bias_E: _F64
    effective_gradient_E: _F64

    def bias_at(self, t: float | ArrayLike) -> _F64:
        """Bias (E) at time(s) ``t`` (s): ``bias + drift t``."""
        tt = np.asarray(t, dtype=np.float64)
        return self.bias_E + np.multiply.outer(tt, self.drift_E_per_s)


@dataclass(frozen=True)
class GradiometerSession:
    """A simulated start-up: raw streams, spin phase, dwell bounds and truth."""

    accel: _F64
    phase: _F64
    t: _F64
    bounds: NDArray[np.int64]
    fs: float
    radius_m: float
    omega_rad_s: float
    azimuth_deg: _F64
    truth: GradiometerTruth

    def __repr__(self) -> str:
        return (
            f"GradiometerSession({len(self.azimuth_deg)} azimuths, {self.accel.shape[0]} samples "
            f"at {self.fs:g} Hz, R = {self.radius_m:g} m, spin {self.omega_rad_s / 2 / np.pi:g} Hz)"
        )


def _vec(x: Any, n: int, name: str) -> _F64:
    a = np.asarray(x, dtype=np.float64).reshape(-1)
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise CalibrationError(f"{name} must be {n} finite numbers; got {x!r}")
    return a


def gradiometer_session(
    azimuth_deg: ArrayLike = (0.0, 90.0, 90.0, 0.0),
    *,
    gradient_E: ArrayLike = (40.0, -25.0),
    tensor_E: ArrayLike | None = None,
    bias_E: ArrayLike = (12.0, -7.0),
    drift_E_per_s: ArrayLike | None = None,
    rates_rad_s: ArrayLike = (0.0, 0.0),
    rates_frame: str = "nav",
    radius_m: float = 0.1,
    spin_hz: float = 0.5,
    fs: float = 1000.0,
    dwell_s: float = 60.0,
    slew_s: float = 20.0,
    noise_mps2: float = 0.0,
    scale_mismatch: float | ArrayLike = 0.0,
    tilt_mps2: ArrayLike = (0.0, 0.0),
    spin_jitter: tuple[float, float] = (0.0, 1.0),
    azimuth_error_deg: float | ArrayLike = 0.0,
    azimuth_offset_deg: float = 0.0,
    phase0_rad: float = 0.0,
    seed: int | np.random.Generator | None = 0,
) -> GradiometerSession:
    """Simulate a gradiometer start-up: raw a1..a4 at ``fs`` over one dwell per azimuth.

    Parameters
    ----------
    azimuth_deg : (m,) float
        Commanded platform azimuths, deg, in dwell order.
    gradient_E : (2,) float
        Navigation-frame ``(I, C)``, E (ignored when ``tensor_E`` is given).
    tensor_E : (3, 3) float, optional
        Full navigation-frame gravity-gradient tensor, E (symmetric).
    bias_E : (2,) float
        Per-startup bias of the inline and cross channels at t = 0, E.
    drift_E_per_s : (2,) float, optional
        Linear bias drift, E/s.
    rates_rad_s : (2,) float or (m, 2)
        Residual horizontal rates ``(Wx, Wy)``, rad/s, per dwell when 2-D.
    rates_frame : {"nav", "platform"}
        "nav": the rates are fixed in the navigation frame (e.g. Earth rate) and rotate with the
        platform, so their terms act like a gradient; "platform": fixed in the platform frame
        (control residuals), so they act like a bias.
    radius_m, spin_hz, fs : float
        Disc radius (m), spin rate (Hz), sample rate (Hz).
    dwell_s, slew_s : float
        Length of each dwell and the unrecorded slew time between dwells, s.
    noise_mps2 : float
        White noise std of each accelerometer sample, m/s^2.
    scale_mismatch : float or (4,) float
        Std of the relative scale errors (drawn, then made zero-mean), or the four errors.
    tilt_mps2 : (2,) or (3,) float
        Horizontal specific force in the platform frame (a tilt), m/s^2.
    spin_jitter : (amplitude rad/s^2, frequency Hz)
        Sinusoidal spin acceleration ``omega_dot = A sin(2 pi f t)``.
    azimuth_error_deg : float or (m,) float
        Std of independent azimuth errors (drawn), or the errors themselves, deg.
    azimuth_offset_deg : float
        Common azimuth offset, deg.
    phase0_rad : float
        Spin phase at t = 0.
    seed : int or Generator
        Random generator seed.
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    az = np.asarray(azimuth_deg, dtype=np.float64).reshape(-1)
    m = az.size
    if m == 0 or not np.all(np.isfinite(az)):
        raise CalibrationError("azimuth_deg must be finite numbers (deg)")
    if tensor_E is None:
        gi, gc = _vec(gradient_E, 2, "gradient_E")
        tens = np.array([[gi, gc, 0.0], [gc, -gi, 0.0], [0.0, 0.0, 0.0]])
    else:
        tens = np.asarray(tensor_E, dtype=np.float64)
        if tens.shape != (3, 3) or not np.allclose(tens, tens.T):
            raise CalibrationError("tensor_E must be a symmetric (3, 3) tensor in E")
    gamma = _ic(tens)
    b0 = _vec(bias_E, 2, "bias_E")
    bd = np.zeros(2) if drift_E_per_s is None else _vec(drift_E_per_s, 2, "drift_E_per_s")
    rates_in = np.asarray(rates_rad_s, dtype=np.float64)
    if rates_in.shape not in ((2,), (m, 2)) or not np.all(np.isfinite(rates_in)):
        raise CalibrationError(f"rates_rad_s must be finite with shape (2,) or ({m}, 2)")
    rates = np.broadcast_to(rates_in, (m, 2)).copy()
    if rates_frame not in ("nav", "platform"):
        raise CalibrationError("rates_frame must be 'nav' or 'platform'")
    for v, nm in ((radius_m, "radius_m"), (spin_hz, "spin_hz"), (fs, "fs"), (dwell_s, "dwell_s")):
        if not (np.isfinite(v) and v > 0):
            raise CalibrationError(f"{nm} must be positive")
    omega = 2.0 * np.pi * spin_hz
    sm = np.asarray(scale_mismatch, dtype=np.float64)
    if sm.ndim == 0:
        k = rng.normal(0.0, float(sm), 4) if sm > 0 else np.zeros(4)
        k -= k.mean()
    else:
        k = _vec(sm, 4, "scale_mismatch")
    scale = 1.0 + k
    tilt = np.zeros(3)
    tv = np.asarray(tilt_mps2, dtype=np.float64).reshape(-1)
    tilt[: tv.size] = tv[:3]
    ae = np.asarray(azimuth_error_deg, dtype=np.float64)
    if ae.ndim == 0:
        err = rng.normal(0.0, float(ae), m) if ae > 0 else np.zeros(m)
    else:
        err = _vec(ae, m, "azimuth_error_deg")
    az_true = az + float(azimuth_offset_deg) + err
    jit_a, jit_f = float(spin_jitter[0]), float(spin_jitter[1])
    wj = 2.0 * np.pi * jit_f

    n_d = int(round(dwell_s * fs))
    accel = np.empty((m * n_d, 4))
    phase = np.empty(m * n_d)
    tt = np.empty(m * n_d)
    bounds = np.zeros((m, 2), dtype=np.int64)
    sens = np.zeros((m, 2))
    rterm = np.zeros((m, 2))
    chan = np.zeros((m, 2))
    prates = np.zeros((m, 2))
    tmid = np.zeros(m)
    for j in range(m):
        t0 = j * (dwell_s + slew_s)
        t = t0 + np.arange(n_d) / fs
        sl = slice(j * n_d, (j + 1) * n_d)
        bounds[j] = (j * n_d, (j + 1) * n_d)
        th = np.radians(az_true[j])
        rz = _rz(th)
        gp = rz.T @ tens @ rz * EOTVOS  # platform-frame tensor, s^-2
        w_xy = rates[j] if rates_frame == "platform" else (rz.T @ np.r_[rates[j], 0.0])[:2]
        prates[j] = w_xy
        w = np.array([w_xy[0], w_xy[1], omega])
        # Omega^2 = W W^T - |W|^2 I; the isotropic part gives no tangential force (t_i . r_i = 0),
        # so it is left out exactly (it would only add rounding of omega^2 R ~ 1 m/s^2).
        om2 = np.outer(w, w)
        geff = gp - om2
        if jit_a > 0:
            ph = phase0_rad + omega * t - jit_a / wj**2 * np.sin(wj * t)
            wdot = jit_a * np.sin(wj * t)
        else:
            ph = phase0_rad + omega * t
            wdot = np.zeros_like(t)
        bias_t = b0[:, None] + bd[:, None] * t[None, :]  # (2, n) E
        noise = rng.normal(0.0, noise_mps2, (n_d, 4)) if noise_mps2 > 0 else 0.0
        for i in range(4):
            p = ph + i * np.pi / 2.0
            c, s = np.cos(p), np.sin(p)
            # t_i . (f0 + wdot x r_i - Geff r_i); wdot x r_i = wdot R (-s, c, 0).
            gr_x = geff[0, 0] * c + geff[0, 1] * s
            gr_y = geff[1, 0] * c + geff[1, 1] * s
            f = (-s * tilt[0] + c * tilt[1]) + radius_m * wdot
            f -= radius_m * (-s * gr_x + c * gr_y)
            s2, c2 = 2.0 * s * c, c * c - s * s
            f += radius_m * EOTVOS * (bias_t[0] * s2 - bias_t[1] * c2)
            accel[sl, i] = scale[i] * f
        accel[sl] += noise
        phase[sl] = ph
        tt[sl] = t
        sens[j] = _ic(gp) / EOTVOS
        rterm[j] = np.array([-(w_xy[0] ** 2 - w_xy[1] ** 2) / 2.0, -w_xy[0] * w_xy[1]]) / EOTVOS
        tmid[j] = 0.5 * (t[0] + t[-1])
        chan[j] = scale.mean() * (sens[j] + rterm[j] + b0 + bd * tmid[j])
    if rates_frame == "platform" and np.allclose(rates, rates[0]):
        eff_b = b0 + rterm[0]
        eff_g = gamma.copy()
    elif rates_frame == "nav" and np.allclose(rates, rates[0]):
        wx, wy = rates[0]
        eff_b = b0.copy()
        eff_g = gamma + np.array([-(wx**2 - wy**2) / 2.0, -wx * wy]) / EOTVOS
    else:
        eff_b, eff_g = b0.copy(), gamma.copy()
    truth = GradiometerTruth(
        tensor_E=tens,
        gradient_E=gamma,
        bias_E=b0,
        drift_E_per_s=bd,
        azimuth_true_deg=az_true,
        rates_rad_s=rates,
        rates_frame=rates_frame,
        platform_rates_rad_s=prates,
        sensor_gradient_E=sens,
        rate_terms_E=rterm,
        channels_E=chan,
        dwell_t_mid=tmid,
        scale=scale,
        gain=float(scale.mean()),
        effective_bias_E=eff_b,
        effective_gradient_E=eff_g,
    )
    return GradiometerSession(
        accel=accel,
        phase=phase,
        t=tt,
        bounds=bounds,
        fs=float(fs),
        radius_m=float(radius_m),
        omega_rad_s=float(omega),
        azimuth_deg=az,
        truth=truth,
    )
