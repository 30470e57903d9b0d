"""Centrifuge session simulator (seed 004) with known truth and unmodelled error sources.

Geometry. Every row is one static position of the triad on the centrifuge arm at one speed.
In the body frame, the specific force at the triad centre is ``f = A c1 + c3`` (g units) with
``c1`` the inward radial direction, ``c3`` the spin-axis (up) direction and
``A = omega^2 R / g``. The paper's design (its Fig. 3, recovered exactly from its Table 1) is
``c1 = (cos a cos t, -sin a, -cos a sin t)``, ``c3 = (sin t, 0, cos t)`` with
``a = 0, 45, 90, 135, 180`` deg (position groups of four) and ``t = 180, 120, 60, 0`` deg,
run at 2pi, 4pi and 6pi rad/s.

Error sources: misalignment ``Phi = I + M`` (small angles, any off-diagonal pattern), lever
arms (one body-frame offset vector per accelerometer, m), radius and rate errors, Earth rate
at a latitude (adds ``Omega_ie sin(lat)`` to the spin rate), output noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ._core import CalibrationError

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


@dataclass(frozen=True)
class CentrifugeSession:
    """Simulated per-position mean outputs with their truth.

    Attributes
    ----------
    outputs : ndarray (k, 3)
        Accelerometer outputs (g).
    omega : ndarray (k,)
        Commanded spin rate (rad/s) -- what the user knows.
    radius : float
        Nominal radius (m) -- what the user knows.
    spin_axis : ndarray (k, 3)
        Spin-axis direction in the body frame (for lever-arm fits).
    position, speed_index : ndarray (k,) int
    g : float
        Gravity used to express A in g (m/s^2).
    truth : dict
        Every parameter and error source used.
    """

    outputs: NDArray[np.float64]
    omega: NDArray[np.float64]
    radius: float
    spin_axis: NDArray[np.float64]
    position: NDArray[np.int64]
    speed_index: NDArray[np.int64]
    g: float
    truth: dict[str, Any] = field(default_factory=dict)


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


def centrifuge_session(
    design: CentrifugeDesign | None = None,
    *,
    scale: Any = None,
    bias: Any = None,
    k2: Any = None,
    k3: Any = None,
    misalignment: Any = None,
    lever_arm: Any = None,
    radius: float = 1.0,
    radius_error: float = 0.0,
    rate_error: float = 0.0,
    latitude_deg: float | None = None,
    noise_g: float = 0.0,
    g: float = 9.8,
    rng: int | np.random.Generator | None = None,
) -> CentrifugeSession:
    """Simulate a centrifuge calibration session (per-position mean outputs).

    Parameters
    ----------
    design : CentrifugeDesign, optional
        Default: the paper's 20 positions x (2pi, 4pi, 6pi) rad/s at ``radius``.
    scale, bias, k2, k3 : array_like (3,), optional
        Truth per axis; bias in g, k2 in g/g^2, k3 in g/g^3. Default: the seed-004 truth
        (S = 1.29, 1.21, 1.26; b = 0.213, 0.256, 0.516 g; K2 = 0.57, 0.31, 0.45 x 1e-4) and
        no K3.
    misalignment : array_like (3, 3), optional
        Off-diagonal small angles (rad) of ``Phi = I + M``; the paper's
        ``[[0, -g_xz, g_xy], [g_yz, 0, -g_yx], [-g_zy, g_zx, 0]]``.
    lever_arm : array_like (3, 3), optional
        Row i: body-frame offset (m) of accelerometer i from the nominal centre.
    radius : float
        Nominal radius (m); the design's own radius when a design is given.
    radius_error : float
        True radius minus nominal (m).
    rate_error : float
        Relative spin-rate error (true = commanded x (1 + rate_error)).
    latitude_deg : float, optional
        Adds the vertical Earth rate ``Omega_ie sin(lat)`` to the spin rate.
    noise_g : float
        Standard deviation of white noise on every output (g).
    g : float
        Gravity (m/s^2) used to express the centripetal acceleration in g.
    rng : int or Generator, optional
        Seed for the noise.

    Returns
    -------
    CentrifugeSession
    """
    des = design if design is not None else paper_design(radius=radius)
    truth = {
        "scale": _vec3(scale, "scale", SEED004_TRUTH["scale"]),
        "bias": _vec3(bias, "bias", SEED004_TRUTH["bias"]),
        "k2": _vec3(k2, "k2", SEED004_TRUTH["k2"]),
        "k3": _vec3(k3, "k3", np.zeros(3)),
        "misalignment": np.zeros((3, 3)) if misalignment is None else np.asarray(misalignment),
        "lever_arm": np.zeros((3, 3)) if lever_arm is None else np.asarray(lever_arm),
        "radius_error": float(radius_error),
        "rate_error": float(rate_error),
        "latitude_deg": latitude_deg,
        "noise_g": float(noise_g),
    }
    out = centrifuge_outputs(
        des,
        scale=truth["scale"],
        bias=truth["bias"],
        k2=truth["k2"],
        k3=truth["k3"],
        misalignment=truth["misalignment"],
        lever_arm=truth["lever_arm"],
        radius_error=radius_error,
        rate_error=rate_error,
        latitude_deg=latitude_deg,
        g=g,
    )
    if noise_g > 0:
        gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        out = out + gen.normal(0.0, noise_g, out.shape)
    return CentrifugeSession(
        outputs=out,
        omega=des.omega.copy(),
        radius=des.radius,
        spin_axis=des.spin_axis.copy(),
        position=des.position.copy(),
        speed_index=des.speed_index.copy(),
        g=g,
        truth=truth,
    )
