"""Centrifuge session simulator (the paper's design) with known truth and unmodelled error sources.

Geometry. Every row is one static position of the triad on the centrifuge arm at one speed.
In the body frame, the specific force at the triad centre is ``f = A c1 + c3`` (g units) with
``c1`` the inward radial direction, ``c3`` the spin-axis (up) direction and
``A = omega^2 R / g``. The paper's design (its Fig. 3, recovered exactly from its Table 1) is
``c1 = (cos a cos t, -sin a, -cos a sin t)``, ``c3 = (sin t, 0, cos t)`` with
``a = 0, 45, 90, 135, 180`` deg (position groups of four) and ``t = 180, 120, 60, 0`` deg,
run at 2pi, 4pi and 6pi rad/s.

Error sources: misalignment ``Phi = I + M`` (small angles, any off-diagonal pattern), lever
arms (one body-frame offset vector per accelerometer, m), radius and rate errors, Earth rate
at a latitude (the platform's inertial rate about the vertical is ``omega + Omega_ie sin(lat)``
for a signed spin rate ``omega``, positive counter-clockwise seen from above), output noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..centrifuge import (
    CENTRIFUGE_TRUTH,
    CentrifugeDesign,
    _vec3,
    centrifuge_outputs,
    paper_design,
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
        Truth per axis; bias in g, k2 in g/g^2, k3 in g/g^3. Default: the paper's truth
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
        Adds the vertical Earth rate ``Omega_ie sin(lat)`` to the signed spin rate (rad/s,
        positive counter-clockwise seen from above): a forward run spins ``Omega_ie sin(lat)``
        faster in inertial space, a reverse run (negative omega) as much slower, so
        ``dA/A = +-2 Omega_ie sin(lat) / |omega|`` (1.5e-5 at 1 rev/s and 39 deg) and a
        forward/reverse pair cancels it to first order.
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
        "scale": _vec3(scale, "scale", CENTRIFUGE_TRUTH["scale"]),
        "bias": _vec3(bias, "bias", CENTRIFUGE_TRUTH["bias"]),
        "k2": _vec3(k2, "k2", CENTRIFUGE_TRUTH["k2"]),
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
