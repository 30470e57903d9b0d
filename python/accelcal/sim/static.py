"""Dwell means of a static session with known truth, as simulated by the norm-observation
paper (Huang et al., field calibration of an atomic gravimeter's accelerometer; its sec. 3).

Attitudes are platform tilts ``(tx, ty)`` in degrees, giving the specific force
``a = [-g sin ty, g sin tx cos ty, g cos tx cos ty]``, or unit gravity directions (n, 3) for
the full sphere. Raw output ``am = K a + b + N(0, sigma^2)`` per axis, ``K = S + M`` lower
triangular (the paper's model) or upper / diagonal.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._core import CalibrationError
from .._triad import attitudes_to_force, k_matrix
from ..dwell import DwellSet
from .field import FIELD_TRUTH, SEED000_TRUTH

__all__ = [
    "G0",
    "FIELD_TRUTH",
    "SEED000_TRUTH",
    "StaticSession",
    "attitudes_to_force",
    "sphere_attitudes",
    "static_dwell_means",
    "uniform_attitudes",
]

#: Standard gravity, m/s^2 (the simulations' true g).
G0 = 9.80665


def _gen(rng: int | np.random.Generator | None) -> np.random.Generator:
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


def uniform_attitudes(
    n: int, max_tilt_deg: float = 30.0, rng: int | np.random.Generator | None = None
) -> NDArray[np.float64]:
    """``n`` platform tilts ``(tx, ty)`` uniform in +-``max_tilt_deg`` (degrees), shape (n, 2)."""
    return _gen(rng).uniform(-max_tilt_deg, max_tilt_deg, size=(int(n), 2))


def sphere_attitudes(
    n: int, rng: int | np.random.Generator | None = None
) -> NDArray[np.float64]:
    """``n`` gravity directions uniform on the whole sphere (unit vectors), shape (n, 3)."""
    v = _gen(rng).normal(size=(int(n), 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)




@dataclass
class StaticSession:
    """A simulated set of dwell means with its truth.

    means : (n, 3) raw dwell means (output units; m/s^2 for the paper's truth, :data:`FIELD_TRUTH`).
    g_true : true gravity, m/s^2.  g_measured : the gravimeter's value g_true + N(0, sigma_g).
    force : (n, 3) true specific force per dwell.  attitudes : what was asked for.
    truth : parameter vector.  sigma : std of each dwell mean per axis.
    """

    means: NDArray[np.float64]
    g_true: float
    g_measured: float
    force: NDArray[np.float64]
    attitudes: NDArray[np.float64]
    truth: NDArray[np.float64]
    sigma: float
    model: str = "lower"

    def dwellset(self) -> DwellSet:
        """The means as a :class:`DwellSet` whose var/count give ``sigma`` per mean."""
        k = self.means.shape[0]
        return DwellSet(self.means, np.full((k, 3), self.sigma**2), np.ones(k, dtype=np.int64))


def static_dwell_means(
    n_or_attitudes: int | ArrayLike = 20,
    truth: ArrayLike = FIELD_TRUTH,
    g: float = G0,
    sigma: float = 1e-3,
    sigma_g: float = 1e-5,
    max_tilt_deg: float | None = 30.0,
    rng: int | np.random.Generator | None = None,
    *,
    model: str = "lower",
) -> StaticSession:
    """Simulate dwell means with the norm-observation paper's settings.

    Parameters
    ----------
    n_or_attitudes : int or (n, 2) tilts in degrees or (n, 3) directions
        Number of dwells (tilts uniform in +-``max_tilt_deg``; ``max_tilt_deg=None`` draws
        directions uniform on the whole sphere), or the attitudes themselves.
    truth : (9,) or (6,) [sx, sy, sz, bx, by, bz, m1, m2, m3]
    g : true gravity, m/s^2.
    sigma : std of each dwell mean per axis (output units).
    sigma_g : std of the reference gravimeter (the fit's ``g`` is ``g_measured``).
    """
    gen = _gen(rng)
    v = np.asarray(truth, dtype=np.float64).reshape(-1)
    if v.size not in (6, 9):
        raise CalibrationError(f"truth must have 6 or 9 values; got {v.size}")
    if np.ndim(n_or_attitudes) == 0:
        n = int(n_or_attitudes)  # type: ignore[arg-type]
        if n < 1:
            raise CalibrationError("need at least one dwell")
        att = (
            sphere_attitudes(n, gen)
            if max_tilt_deg is None
            else uniform_attitudes(n, max_tilt_deg, gen)
        )
    else:
        att = np.asarray(n_or_attitudes, dtype=np.float64)
    a = attitudes_to_force(att, g)
    K = k_matrix(v, model)
    means = a @ K.T + v[3:6] + gen.normal(0.0, sigma, size=a.shape)
    gm = float(g + gen.normal(0.0, sigma_g)) if sigma_g > 0 else float(g)
    return StaticSession(means, float(g), gm, a, att, v, float(sigma), model)
