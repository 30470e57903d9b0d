"""The calibration a static fit exports: :class:`TriadModel`, its versioned JSON file and a
look-up of the calibration valid at a time."""

from __future__ import annotations

import datetime as _dt
import errno
import hashlib
import json
import math
import os
import stat
from dataclasses import dataclass
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Any, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core, _quiet
from ._core import CalibrationError
from ._files import atomic_create, atomic_write, file_kind, read_small_text
from ._plain import plain
from ._triad import MODELS, PARAM_NAMES, k_matrix, n_params, vector_from_k
from ._validate import numeric_array, samples_array

__all__ = ["CalibrationComparison", "TriadModel", "accelcal_version", "dwell_fingerprints",
           "iso_utc"]


def accelcal_version() -> str:
    """The installed accelcal's version (what a calibration file records it was made by)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("accelcal")
    except PackageNotFoundError:  # pragma: no cover - run from a source tree
        from . import __version__

        return str(__version__)


def dwell_fingerprints(means: ArrayLike) -> list[str]:
    """A short hash (12 hex digits of SHA-256) of each dwell mean's three float64 values, in
    order: what a calibration records of the dwells it was fitted to, so that checking it
    against a session can tell when that session is its own."""
    m = np.ascontiguousarray(np.asarray(means, dtype="<f8").reshape(-1, 3))  # any platform
    return [hashlib.sha256(r.tobytes()).hexdigest()[:12] for r in m]


#: Largest condition number of a triad's K (a triad's scale factors differ by a few per cent
#: and its misalignments are small: cond(K) is close to 1).
MAX_CONDITION = 1e6


def _check_covariances(m: TriadModel, source: str) -> None:
    """The two stored covariances are one fit's: the scaled one is the noise-model one times
    ``metadata.chi2_dof`` (noise given), or equal to it (noise estimated from the residuals)."""
    cn, cs = m.covariance_noise_model, m.covariance_scaled
    chi2 = (m.metadata or {}).get("chi2_dof")
    if cn is None or cs is None or not isinstance(chi2, (int, float)) or isinstance(chi2, bool):
        return
    if not math.isfinite(chi2) or chi2 <= 0:
        raise CalibrationError(f"{source}: field 'metadata.chi2_dof' must be a positive number; "
                               f"got {chi2}")
    sg = (m.metadata or {}).get("sigma_g")
    if isinstance(sg, (int, float)) and not isinstance(sg, bool) and sg > 0 and m.g:
        # Both include the reference gravity's term sigma_g^2 j j^T (j = -p / g for the
        # entries of K, 0 for the biases): compare what the noise gives.
        j = -m.vector / m.g
        j[3:6] = 0.0
        cg = sg * sg * np.outer(j, j)
        cn, cs = cn - cg, cs - cg
    scale = float(np.abs(cs).max()) or 1.0
    if not (np.allclose(cs, chi2 * cn, rtol=1e-6, atol=1e-12 * scale)
            or np.allclose(cs, cn, rtol=1e-6, atol=1e-12 * scale)):
        raise CalibrationError(
            f"{source}: fields 'covariance_scaled' and 'covariance_noise_model' disagree: the "
            f"scaled covariance must be the noise-model one times metadata.chi2_dof ({chi2:.6g}) "
            "or, when the noise was estimated, equal to it; one of them was changed"
        )


def iso_utc(when: str | _dt.datetime | _dt.date | None = None) -> str:
    """ISO 8601 UTC timestamp ``YYYY-MM-DDTHH:MM:SSZ`` of ``when`` (now when None; naive
    datetimes and date-only strings are taken as UTC)."""
    return _to_datetime(when).strftime("%Y-%m-%dT%H:%M:%SZ")


def _to_datetime(when: str | _dt.datetime | _dt.date | None) -> _dt.datetime:
    if when is None:
        d = _dt.datetime.now(_dt.timezone.utc)
    elif isinstance(when, _dt.datetime):
        d = when
    elif isinstance(when, _dt.date):
        d = _dt.datetime(when.year, when.month, when.day)
    elif isinstance(when, str):
        s = when.strip()
        if s.endswith("Z"):
            s = s[:-1] + "+00:00"
        try:
            d = _dt.datetime.fromisoformat(s)
        except ValueError:
            raise CalibrationError(
                f"date must be an ISO 8601 timestamp such as 2026-11-23T10:15:00Z; got {when!r}"
            ) from None
    else:
        raise CalibrationError(
            f"date must be an ISO 8601 string or a datetime; got {type(when).__name__}"
        )
    if d.tzinfo is None:
        d = d.replace(tzinfo=_dt.timezone.utc)
    return d.astimezone(_dt.timezone.utc).replace(microsecond=0)


@cache
def _schema() -> dict[str, Any]:
    text = (resources.files("accelcal") / "schemas" / "triad-model.schema.json").read_text(
        encoding="utf-8"
    )
    return json.loads(text)  # type: ignore[no-any-return]


def schema() -> dict[str, Any]:
    """The published JSON schema of a TriadModel file (a copy)."""
    return json.loads(json.dumps(_schema()))  # type: ignore[no-any-return]


def _field(path: Any) -> str:
    parts = [str(p) for p in path]
    return "/".join(parts) if parts else "(top level)"


def _finite_array(x: Any, name: str, shape: tuple[int, ...] | None = None) -> NDArray[np.float64]:
    """``x`` as a finite float64 array of ``shape``; booleans, text and ragged lists refused."""
    try:
        a = np.asarray(x)
    except ValueError:
        raise CalibrationError(f"{name} must be a rectangular array of numbers") from None
    if a.dtype == np.bool_ or a.dtype.kind not in "fiu":
        raise CalibrationError(f"{name} must hold numbers; got {a.dtype} values")
    a = a.astype(np.float64)
    if shape is not None and a.shape != shape:
        raise CalibrationError(f"{name} must have shape {shape}; got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise CalibrationError(f"{name} contains NaN or infinite values")
    return a


def _covariance(x: Any, name: str, p: int) -> NDArray[np.float64] | None:
    if x is None:
        return None
    c = _finite_array(x, name)
    if c.shape != (p, p):
        raise CalibrationError(
            f"{name} must be ({p}, {p}) (the model's {p} parameters); got shape {c.shape}"
        )
    scale = max(float(np.max(np.abs(c))), 1e-300)
    if np.max(np.abs(c - c.T)) > 1e-8 * scale:
        raise CalibrationError(f"{name} is not symmetric")
    if np.any(np.diag(c) < 0):
        raise CalibrationError(f"{name} has a negative variance on its diagonal")
    return c


#: The output units of g: each spelling a file may name in 'units.output', gravity (the
#: standard 9.80665 m/s^2) in it, and the reference gravities g that :func:`units_of_g` names
#: by it (inclusive; tried in this order, so that 990 is mg; None: a spelling never inferred).
_G_UNITS: tuple[tuple[str, float, tuple[float, float] | None], ...] = (
    ("m/s^2", 9.80665, (9.0, 10.5)), ("g", 1.0, (0.9, 1.1)),
    ("mg", 1000.0, (990.0, 1100.0)), ("cm/s^2", 980.665, (900.0, 990.0)),
    ("g0", 1.0, None), ("m/s2", 9.80665, None), ("ms^-2", 9.80665, None),
    ("cm/s2", 980.665, None), ("gal", 980.665, None), ("Gal", 980.665, None),
    ("mm/s^2", 9806.65, None), ("mm/s2", 9806.65, None), ("mGal", 980665.0, None),
    ("ft/s^2", 9.80665 / 0.3048, None), ("ft/s2", 9.80665 / 0.3048, None),
)
#: The table as a lookup: gravity in each output unit a file may name (the consistency check
#: of 'units.output' against 'g').
_UNIT_G = {unit: g for unit, g, _ in _G_UNITS}


def _unit_key(unit: str) -> str:
    """A unit's spelling as :data:`_UNIT_G` keys it (no spaces, ``²`` as ``^2``)."""
    return unit.replace(" ", "").replace("²", "^2")


def _check_units_g(units: str, g: float | None, said: str, given: str) -> float | None:
    """The output unit ``units`` against the reference gravity ``g`` (the calibrated output
    is in the units of g): a CalibrationError when ``g`` is not gravity in ``units`` (a
    model labelled "g" with g = 9.81 would label every calibrated value wrongly). ``said``
    and ``given`` word the two values (the constructor's arguments or a file's fields).
    Returns gravity in ``units`` (None for a unit the table does not know)."""
    unit_g = _UNIT_G.get(_unit_key(units))
    if g is not None and unit_g is not None and not 0.9 < g / unit_g < 1.1:
        raise CalibrationError(
            f"{said} says {units!r} but {given} is {g!r}, not gravity in {units} (about "
            f"{unit_g:g}): one of them is wrong (the calibrated output is in the units of g"
            + (f": {units_of_g(g)!r} for g = {g:g})" if units_of_g(g) else ")"))
    return unit_g


def _file_g(g: Any) -> float | None:
    """A file's 'g' when it is a positive number (the constructor words any other)."""
    ok = isinstance(g, (int, float)) and not isinstance(g, bool) and g > 0
    return float(g) if ok else None


#: How accelcal words the raw (input) units in a file's 'units.K' and 'units.bias' (what it
#: writes first; the others are accepted as saying the same).
_RAW_WORDS = ("input units", "raw units", "raw (input) units")


def _check_unit_labels(d: dict[str, Any], model: str, source: str) -> None:
    """A file's 'units.K', 'units.bias' and 'parameter_names', when present, must state
    accelcal's convention: K maps calibrated to raw (raw units per unit of g), the bias is in
    raw units, the parameters in accelcal's order. A hand-written file in another convention
    (imu_tk's K in m/s^2 per count, a bias in m/s^2, biases listed first) would otherwise load
    as a wrong calibration and have its labels overwritten on save."""
    units = d.get("units") or {}
    out = str(units.get("output", "m/s^2"))
    inp = str(units.get("input", "")).strip()
    raw = _RAW_WORDS + ((inp.lower(),) if inp else ())
    want_k = f"input units per {out}"
    k_label = units.get("K")
    if k_label is not None:
        text = " ".join(k_label.split())
        head, sep, tail = text.rpartition(" per ")
        tail_g, out_g = _UNIT_G.get(_unit_key(tail)), _UNIT_G.get(_unit_key(out))
        same_out = (_unit_key(tail) == _unit_key(out) or tail.lower() == "unit of g"
                    or (tail_g is not None and tail_g == out_g))
        if not (sep and head.lower() in raw and same_out):
            raise CalibrationError(
                f"{source}: field 'units.K' says {k_label!r}, but accelcal's K maps the "
                f"calibrated output to the raw output (am = K a + b): it is in raw (input) "
                f"units per unit of g, here {want_k!r}" + (f" ({inp} per {out})" if inp else "")
                + ". A K that maps raw to calibrated (imu_tk's, a six-position W) is the "
                "inverse of accelcal's: convert it (K = W^-1, bias = -K o for an offset o added "
                "to the output) and write the labels accelcal writes")
    b_label = units.get("bias")
    if b_label is not None and " ".join(b_label.split()).lower() not in raw:
        raise CalibrationError(
            f"{source}: field 'units.bias' says {b_label!r}, but accelcal's bias is in raw "
            f"(input) units, the raw output at zero specific force ('input units'"
            + (f": {inp}" if inp else "") + "). A bias in the calibrated output's units (an "
            "offset o added to the output, a = W am + o) is b = -K o in accelcal's terms: "
            "convert it and write 'input units'")
    names = d.get("parameter_names")
    if names is not None and model in MODELS:
        want = list(PARAM_NAMES[: n_params(model)])
        if list(names) != want:
            raise CalibrationError(
                f"{source}: field 'parameter_names' says {list(names)}, but accelcal's "
                f"parameter vector of the {model!r} model is in the order {want} (scales, "
                "biases, then the triangle's entries): 'vector' and the covariances would be "
                "read in another order than the file's; reorder them and write that order")


def units_of_g(g: float) -> str:
    """The unit a reference gravity ``g`` is expressed in: m/s^2, g, cm/s^2 or mg (else "").
    Local gravity is 976-983 cm/s^2 and 995-1003 mg: 990 splits them (g = 1000 labelled
    cm/s^2 an output in mg)."""
    return next((unit for unit, _, r in _G_UNITS if r is not None and r[0] <= g <= r[1]), "")


def _check_session(m: TriadModel, source: str) -> None:
    """The parameters against the session they were fitted to: a file that records its dwell
    means (``metadata.fit_session``) and the residual RMS of its fit reproduces that RMS to
    rounding; an edit of the bias or K together with 'vector' (which the other checks see
    as consistent) does not (a bias moved by 0.05 gave an RMS 100 times the recorded)."""
    md = m.metadata
    sess, rms = md.get("fit_session"), md.get("residual_rms")
    if (m.g is None or not isinstance(sess, dict) or isinstance(rms, bool)
            or not isinstance(rms, (int, float)) or not math.isfinite(rms)):
        return
    try:
        means = np.asarray(sess["means"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        return
    if means.ndim != 2 or means.shape[1] != 3 or not np.all(np.isfinite(means)):
        return
    cal = m.apply(means, check_units=False)
    got = float(np.sqrt(np.mean((np.linalg.norm(cal, axis=1) - m.g) ** 2)))
    if abs(got - rms) > 1e-6 * rms + 1e-9 * m.g:
        raise CalibrationError(
            f"{source}: K and bias do not reproduce the fit they record: on the dwell means "
            f"of metadata.fit_session they leave a residual RMS of {got:.6g}, the file says "
            f"{rms:.6g} (metadata.residual_rms): edited by hand?")


def median_norm(rows: NDArray[np.float64], *, finite: bool = False) -> float:
    """The median norm of calibrated rows (n, 3) (the norm of gravity in a recording mostly at
    rest): NaN when a row is NaN, or with ``finite`` of the finite norms only (dropouts left
    out; NaN when none is left)."""
    if rows.shape[0] <= _FEW_ROWS:  # a service applying row by row: NumPy's median costs 35 us
        few = [math.sqrt(x * x + y * y + z * z) for x, y, z in rows.tolist()]
        if finite:
            few = [v for v in few if math.isfinite(v)]
        elif any(math.isnan(v) for v in few):
            return math.nan
        few.sort()
        k = len(few)
        return (few[k // 2] if k % 2 else 0.5 * (few[k // 2 - 1] + few[k // 2])) if k else math.nan
    norms = np.sqrt(np.einsum("ij,ij->i", rows, rows))
    if finite:
        norms = norms[np.isfinite(norms)]
    return float(np.median(norms)) if norms.size else math.nan


#: Up to this many rows :func:`median_norm` works in Python floats.
_FEW_ROWS = 8


def _json_scalar(v: Any) -> Any:
    """A numpy scalar or array in the metadata as JSON (``json.dumps``'s ``default``)."""
    if isinstance(v, (np.generic, np.ndarray)):
        return plain(v)
    raise CalibrationError(f"the model to write: metadata value {v!r} ({type(v).__name__}) is "
                           "not a number, text, list or dict: JSON cannot hold it")


class TriadModel:
    """A calibrated accelerometer triad: ``a = K^-1 (am - b)``, ``am`` the raw sensor output
    (in the raw, input units: counts, mg, g, m/s^2 as recorded; ``input_units``) and ``a``
    calibrated (in the units of ``g``, normally m/s^2; ``units``).

    K : (3, 3) raw (input) units per unit of g (per m/s^2): it maps calibrated to raw;
    bias : (3,) raw (input) units, the raw output at zero specific force (an offset ``o``
    added to the calibrated output, ``a = W am + o``, is the bias ``b = -K o``, ``K = W^-1``).
    Saved as versioned JSON (format ``accelcal.TriadModel``, version 2, validated against
    the published schema ``accelcal/schemas/triad-model.schema.json`` plus numeric checks)
    with units, both covariances of the parameter vector (labelled; ``covariance`` is the
    realistic one) and metadata (sensor id, ISO 8601 UTC date, g, temperature).
    """

    FORMAT = "accelcal.TriadModel"
    VERSION = 2

    def __init__(
        self,
        K: ArrayLike,
        bias: ArrayLike,
        *,
        model: str = "lower",
        covariance: ArrayLike | None = None,
        covariance_noise_model: ArrayLike | None = None,
        covariance_scaled: ArrayLike | None = None,
        realistic: str | None = None,
        g: float | None = None,
        units: str = "m/s^2",
        input_units: str = "",
        sensor_id: str = "",
        date: str | _dt.datetime | _dt.date | None = None,
        temperature: float | None = None,
        metadata: dict[str, Any] | None = None,
    ) -> None:
        p = n_params(model)
        k = _finite_array(K, "K", (3, 3))
        b = _finite_array(np.reshape(np.asarray(bias), -1), "bias", (3,))
        cond = float(np.linalg.cond(k))
        if not cond <= MAX_CONDITION:
            raise CalibrationError(
                f"K is singular or ill-conditioned (condition number {cond:.3g}; a triad's K is "
                f"close to a multiple of the identity, at most {MAX_CONDITION:g})"
            )
        bad = _core.static_model_violation(k.tolist(), cast(Any, model))
        if bad is not None:
            i, j = bad
            raise CalibrationError(
                f"K[{i}][{j}] = {k[i, j]:.6g} is outside the {model!r} model's pattern "
                f"({_pattern(model)}); wrong triangle or wrong model" + _full_k_route(k)
            )
        # Read-only: an edit in place (K /= 9.80665 as a unit change) would change what apply
        # does and what save writes without any check; make a new model instead.
        k.setflags(write=False)
        b.setflags(write=False)
        self.K = k
        self.bias = b
        self.model = model
        if covariance is not None and covariance_noise_model is None:
            covariance_noise_model = covariance
        self.covariance_noise_model = _covariance(
            covariance_noise_model, "covariance_noise_model", p
        )
        self.covariance_scaled = _covariance(covariance_scaled, "covariance_scaled", p)
        for c in (self.covariance_noise_model, self.covariance_scaled):
            if c is not None:
                c.setflags(write=False)
        if realistic is None:
            realistic = "noise_model" if self.covariance_noise_model is not None else None
        if realistic not in ("noise_model", "scaled", None):
            raise CalibrationError(
                f"realistic must be 'noise_model' or 'scaled'; got {realistic!r}"
            )
        if realistic == "scaled" and self.covariance_scaled is None:
            raise CalibrationError("realistic='scaled' needs covariance_scaled")
        if realistic == "noise_model" and self.covariance_noise_model is None:
            raise CalibrationError("realistic='noise_model' needs covariance_noise_model")
        self.realistic = realistic
        if g is not None:
            if isinstance(g, bool) or not isinstance(g, (int, float, np.floating, np.integer)):
                raise CalibrationError(f"g must be a number (reference gravity); got {g!r}")
            if not (math.isfinite(float(g)) and float(g) > 0):
                raise CalibrationError(f"g must be positive and finite; got {g!r}")
        self.g = None if g is None else float(g)
        for name, v in (("units", units), ("input_units", input_units), ("sensor_id", sensor_id)):
            if not isinstance(v, str):
                raise CalibrationError(f"{name} must be a string; got {type(v).__name__}")
        _check_units_g(units, self.g, "units", "g")
        self.units = units
        self.input_units = input_units
        self.sensor_id = sensor_id
        self.date = iso_utc(date)
        if temperature is not None and (
            isinstance(temperature, bool) or not math.isfinite(float(temperature))
        ):
            raise CalibrationError(f"temperature must be a finite number; got {temperature!r}")
        self.temperature = None if temperature is None else float(temperature)
        if metadata is not None and not isinstance(metadata, dict):
            raise CalibrationError(f"metadata must be a dict; got {type(metadata).__name__}")
        self.metadata = dict(metadata or {})

    # -- parameters and uncertainty ------------------------------------------------------
    @property
    def vector(self) -> NDArray[np.float64]:
        return vector_from_k(self.K, self.bias, self.model)

    @property
    def names(self) -> tuple[str, ...]:
        return PARAM_NAMES[: n_params(self.model)]

    @property
    def covariance(self) -> NDArray[np.float64] | None:
        """The realistic covariance of ``vector`` (see ``realistic``), or None."""
        if self.realistic == "scaled":
            return self.covariance_scaled
        return self.covariance_noise_model

    @property
    def std(self) -> NDArray[np.float64] | None:
        c = self.covariance
        return None if c is None else np.sqrt(np.diag(c))

    @property
    def datetime(self) -> _dt.datetime:
        """The calibration date as an aware UTC datetime."""
        return _to_datetime(self.date)

    @classmethod
    def from_vector(cls, vector: ArrayLike, model: str = "lower", **kw: Any) -> TriadModel:
        v = np.asarray(vector, dtype=np.float64).reshape(-1)
        if v.size != n_params(model):
            raise CalibrationError(f"model {model!r} needs {n_params(model)} values; got {v.size}")
        return cls(k_matrix(v, model), v[3:6], model=model, **kw)

    def own_dwells(self, means: ArrayLike) -> int:
        """How many of the dwell means ``means`` (k, 3) are ones this calibration was fitted
        to (``metadata["fit_dwells"]``, written by :meth:`StaticFit.to_model`; 0 when the
        model does not record them). A check against its own dwells is not independent."""
        own = set(self.metadata.get("fit_dwells") or ())
        return sum(f in own for f in dwell_fingerprints(means)) if own else 0

    # -- use -----------------------------------------------------------------------------
    def apply(self, raw: ArrayLike, *, check_units: bool = True) -> NDArray[np.float64]:
        """Calibrated specific force (N, 3) float64 of raw output (N, 3) (float64, float32,
        int16, int32 read in place; other integer types widened). Stateless per sample, so
        chunks of a stream can be applied one at a time: an empty chunk (0, 3) gives an
        empty (0, 3) float64 array.

        A DataFrame's x, y, z columns are taken by name, as :func:`accelcal.io.read_stream`
        takes them. uint16 words are read as signed 16-bit values stored as unsigned (65404
        for -132, with a warning when some are above 32767) when the model's bias lies near
        0 (within +-16384), as a signed output's does; with a bias near mid-scale 32768 (an
        unsigned 16-bit output) they are read as given.

        ``check_units``: warn when the calibrated norms of the chunk (median of at most 1000
        rows) are under 0.2 or over 5 times the model's g: raw data in other units than the
        model was fitted in (a model in m/s^2 applied to data in g gives |a| near 0.1 g)."""
        a = numeric_array(raw, "raw")  # a DataFrame's x, y, z by name, as read_stream takes them
        if a.ndim == 1 and a.size == 3:
            return self.apply(a.reshape(1, 3), check_units=check_units)[0]  # type: ignore[no-any-return]
        if a.ndim == 2 and a.shape == (0, 3):  # an empty read of a stream
            return np.empty((0, 3), dtype=np.float64)
        if a.dtype == np.uint16 and np.all(np.abs(self.bias) < 16384.0):
            # The model's zero point lies near 0, as a signed output's does (an unsigned
            # 16-bit output's sits near mid-scale 32768): the words are signed 16-bit values
            # stored as unsigned, as read_stream reads such a file. Judged by the model, not
            # by the chunk, so that every chunk of a stream is read alike.
            if np.any(a >= 32768):
                _quiet.warn(
                    "raw: uint16 words applied to a model whose bias "
                    f"{np.array2string(self.bias, precision=4)} lies near 0, as a signed "
                    "output's does (an unsigned 16-bit output's lies near 32768): read as "
                    "signed 16-bit values stored as unsigned, as accelcal.io.read_stream "
                    "reads them (give raw.view(np.int16) to say so and silence this, or "
                    "raw.astype(np.int32) if they are unsigned outputs)",
                    UserWarning, stacklevel=2)
            a = a.view(np.int16)
        s = samples_array(a, "raw")
        out: NDArray[np.float64] = _core.apply_triad_raw(s, self.K.tolist(), self.bias.tolist())
        if check_units:
            self._check_norm(out)
        return out

    def _check_norm(self, out: NDArray[np.float64]) -> None:
        """Warn when the calibrated norms of a chunk (at most 1000 rows looked at) are far
        from the model's g: raw data in other units than the model's (a model fitted in m/s^2
        applied to data in g gave |a| = 0.67)."""
        if self.g is None or out.ndim != 2 or out.shape[0] == 0:
            return
        ratio = median_norm(out[:: max(1, out.shape[0] // 1000)]) / self.g
        if 0.2 <= ratio <= 5.0 or not math.isfinite(ratio):
            return
        _quiet.warn(
            f"raw: the calibrated norms are {ratio:.3g} times the model's g = {self.g:g} "
            f"{self.units} (median of the chunk): are the raw values in the units the model "
            f"was fitted in ({self.input_units or 'the input units of its fit'})? A sensor "
            "mostly at rest or moving gently reads about 1 g; ignore this on a centrifuge",
            UserWarning, stacklevel=3)

    # -- files ---------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        def cov(c: NDArray[np.float64] | None) -> Any:
            return None if c is None else c.tolist()

        return {
            "format": self.FORMAT,
            "version": self.VERSION,
            "model": self.model,
            "parameter_names": list(self.names),
            "vector": self.vector.tolist(),
            "K": self.K.tolist(),
            "bias": self.bias.tolist(),
            "units": {
                "output": self.units,
                "input": self.input_units,
                "K": f"input units per {self.units}",
                "bias": "input units",
            },
            "covariance": cov(self.covariance),
            "covariance_noise_model": cov(self.covariance_noise_model),
            "covariance_scaled": cov(self.covariance_scaled),
            "covariance_realistic": self.realistic,
            "g": self.g,
            "sensor_id": self.sensor_id,
            "date": self.date,
            "temperature": self.temperature,
            "metadata": self.metadata,
        }

    def default_filename(self) -> str:
        """``<sensor_id>_<YYYYmmddTHHMMSSZ>.json``: a name under which :meth:`find` and a
        person both see the sensor and the date."""
        sid = "".join(c if c.isalnum() or c in "-_." else "_" for c in self.sensor_id) or "triad"
        return f"{sid}_{self.datetime.strftime('%Y%m%dT%H%M%SZ')}.json"

    def to_json(self) -> str:
        """The model as the JSON text :meth:`save` writes, checked as :meth:`load` checks a
        file first: a model changed after it was made (an entry of ``K`` off its model's
        triangle, a covariance edited in place, ``g`` NaN) is refused here, not written as a
        file that ``load`` then refuses. Numpy scalars in the metadata are written as
        numbers."""
        text = json.dumps(self.to_dict(), indent=2, default=_json_scalar) + "\n"
        self.from_dict(json.loads(text), "the model to write")
        return text

    def save(self, path: str | os.PathLike[str], *, overwrite: bool = True) -> None:
        """Write the model as JSON, atomically, after the checks of :meth:`to_json`.

        ``overwrite=False`` never replaces a file: the complete file is linked to its name,
        which fails when the name exists, even when another process creates it at the same
        moment (FileExistsError naming the path; nothing written)."""
        if overwrite:
            atomic_write(path, self.to_json())
            return
        if not atomic_create(path, self.to_json()):
            raise FileExistsError(errno.EEXIST, "the file exists (a calibration is not "
                                  "replaced unless overwrite=True)", os.fspath(path))

    @classmethod
    def from_dict(cls, d: Any, source: str = "model") -> TriadModel:
        """A model from the dict of a file, validated: the published JSON schema, then what
        the schema cannot express (finite numbers, K's conditioning and triangle, vector
        against K and bias, covariance shapes). Each problem is one CalibrationError naming
        the field."""
        import jsonschema

        if not isinstance(d, dict) or d.get("format") != cls.FORMAT:
            raise CalibrationError(f"{source} is not an accelcal TriadModel file (format field)")
        ver = d.get("version")
        if isinstance(ver, int) and not isinstance(ver, bool) and ver > cls.VERSION:
            raise CalibrationError(
                f"{source}: TriadModel file version {ver} is newer than this accelcal reads "
                f"(1-{cls.VERSION}); upgrade accelcal"
            )
        validator = jsonschema.Draft202012Validator(_schema())
        err = jsonschema.exceptions.best_match(validator.iter_errors(d))
        if err is not None:
            where = _field(err.absolute_path)
            if err.validator == "required":
                missing = str(err.message).split("'")[1] if "'" in err.message else err.message
                raise CalibrationError(f"{source}: missing field {missing!r}")
            raise CalibrationError(f"{source}: field {where!r}: {_short(err)}")
        units_d = d.get("units") or {}
        unit_g = _check_units_g(str(units_d.get("output", "m/s^2")),
                                _file_g(d.get("g")),
                                f"{source}: field 'units.output'", "field 'g'")
        try:
            m = cls(
                d["K"],
                d["bias"],
                model=d["model"],
                covariance_noise_model=d.get("covariance_noise_model", d.get("covariance")),
                covariance_scaled=d.get("covariance_scaled"),
                realistic=d.get("covariance_realistic"),
                g=d.get("g"),
                units=(d.get("units") or {}).get("output", "m/s^2"),
                input_units=(d.get("units") or {}).get("input", ""),
                sensor_id=d.get("sensor_id", ""),
                date=d.get("date"),
                temperature=d.get("temperature"),
                metadata=d.get("metadata"),
            )
        except CalibrationError as e:
            raise CalibrationError(f"{source}: {e}") from None
        _check_unit_labels(d, m.model, source)
        if (m.g is not None and unit_g is not None and m.metadata.get("check_g") is not False
                and _core.gravity_problem(m.g * 9.80665 / unit_g) is not None):
            # A fit refuses such a g unless told (check_g=False, recorded in the metadata): a
            # file that has one was most likely edited by hand.
            _quiet.warn(
                f"{source}: field 'g' = {m.g!r} {m.units} is not a plausible local gravity "
                "(9.74-9.85 m/s^2), which fit_static refuses unless told (check_g=False, "
                "recorded as metadata.check_g): edited by hand? Every calibrated value is "
                "scaled by it", UserWarning, stacklevel=3)
        if "vector" in d:
            v = _finite_array(d["vector"], f"{source}: vector")
            want = m.vector
            if v.shape != want.shape or not np.allclose(v, want, rtol=1e-9, atol=1e-12):
                raise CalibrationError(
                    f"{source}: field 'vector' disagrees with K and bias ({v.tolist()} against "
                    f"{want.tolist()})"
                )
        _check_covariances(m, source)
        _check_session(m, source)
        if d.get("version") == 2 and d.get("covariance") is not None:
            c = _finite_array(d["covariance"], f"{source}: covariance")
            if m.covariance is None or c.shape != m.covariance.shape or not np.allclose(
                c, m.covariance, rtol=1e-9, atol=0
            ):
                raise CalibrationError(
                    f"{source}: field 'covariance' is not the covariance that "
                    "'covariance_realistic' names"
                )
        return m

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> TriadModel:
        """Read and validate a model written by :meth:`save` (versions 1 and 2)."""
        src = repr(str(path))
        try:
            # A BOM dropped, as Notepad saves it; a device (/dev/zero) or a file of more than
            # 64 MB refused, not read without end.
            d = json.loads(read_small_text(path, "calibration file"))
        except OSError as e:
            raise CalibrationError(f"cannot read model {src}: {e.strerror}") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise CalibrationError(f"{src} is not JSON: {e}") from None
        return cls.from_dict(d, src)

    @classmethod
    def find(
        cls,
        folder: str | os.PathLike[str],
        sensor_id: str,
        at: str | _dt.datetime | _dt.date | None = None,
        *,
        recursive: bool = True,
    ) -> TriadModel:
        """The calibration of ``sensor_id`` valid at time ``at`` (default now): the newest
        TriadModel file in ``folder`` for that sensor whose date is not after ``at``.

        JSON files that are not TriadModel files are skipped; a TriadModel file of this
        sensor that fails validation raises (a corrupt calibration is never passed over
        silently), and so does a ``*.json`` file that cannot be read (permissions: it may
        be this sensor's newest calibration). Only regular files are read (a link is
        followed): a FIFO, a device or a broken link named ``*.json`` is skipped, and named
        when no file qualifies. A CalibrationError says what was found when no file
        qualifies.
        """
        root = Path(folder)
        if not root.is_dir():
            raise CalibrationError(f"calibration folder {str(folder)!r} does not exist")
        when = _to_datetime(at)
        files = sorted(root.rglob("*.json") if recursive else root.glob("*.json"))
        best: tuple[_dt.datetime, Path] | None = None
        later: list[_dt.datetime] = []
        skipped: list[str] = []  # not regular files, or too large to be a calibration
        for f in files:
            text = cls._find_text(f, sensor_id, skipped)
            if text is None:
                continue
            try:
                d = json.loads(text)
            except ValueError as e:
                # Not JSON: another file, or a calibration cut short (a copy interrupted) that
                # may be this sensor's newest: never passed over silently.
                if cls.FORMAT in text and (json.dumps(sensor_id) in text
                                           or '"sensor_id"' not in text):
                    raise CalibrationError(
                        f"{str(f)!r} is a calibration file (format {cls.FORMAT}) that is not "
                        f"valid JSON ({e}; cut short?), perhaps of sensor {sensor_id!r}: "
                        "restore or remove it") from None
                continue
            if not isinstance(d, dict) or d.get("format") != cls.FORMAT:
                continue
            if d.get("sensor_id") != sensor_id:
                continue
            try:
                t = _to_datetime(d.get("date"))
            except CalibrationError as e:
                raise CalibrationError(f"{str(f)!r}: {e}") from None
            if t > when:
                later.append(t)
                continue
            if best is None or t > best[0]:
                best = (t, f)
        if best is None:
            extra = (
                f"; the earliest is dated {iso_utc(min(later))}" if later else ""
            )
            more = f" and {len(skipped) - 3} more" if len(skipped) > 3 else ""
            left = (f"; skipped, not read: {', '.join(skipped[:3])}{more}" if skipped
                    else "")
            raise CalibrationError(
                f"no calibration of sensor {sensor_id!r} dated at or before {iso_utc(when)} in "
                f"{str(folder)!r} ({len(later)} later{extra}{left})"
            )
        return cls.load(best[1])

    @staticmethod
    def _unreadable(f: Path, e: OSError, sensor_id: str) -> CalibrationError:
        """For :meth:`find`: a ``*.json`` file it cannot read, which may be the sensor's
        newest calibration."""
        return CalibrationError(
            f"cannot read {str(f)!r} ({e.strerror or e}), which may be a calibration of "
            f"sensor {sensor_id!r}: make it readable, or move it out of the folder")

    @staticmethod
    def _find_text(f: Path, sensor_id: str, skipped: list[str]) -> str | None:
        """The text of ``f`` for :meth:`find`: None for a file that cannot be a calibration
        (a folder; not text; a FIFO, a device, a broken link or a file of more than 64 MB,
        which are also listed in ``skipped``); a file that cannot be read raises, naming
        it."""
        try:
            st = f.stat()  # the link's target
        except FileNotFoundError:
            skipped.append(f"{str(f)!r} (a broken link)")
            return None
        except OSError as e:
            raise TriadModel._unreadable(f, e, sensor_id) from None
        if stat.S_ISDIR(st.st_mode):
            return None
        if not stat.S_ISREG(st.st_mode):
            skipped.append(f"{str(f)!r} ({file_kind(st.st_mode)})")
            return None
        try:
            return read_small_text(f, "calibration file")  # a BOM, as load reads it
        except CalibrationError:  # grew past the limit: not a calibration
            skipped.append(f"{str(f)!r} (more than 64 MB)")
            return None
        except UnicodeDecodeError:
            return None
        except OSError as e:
            raise TriadModel._unreadable(f, e, sensor_id) from None

    # -- comparison over time ------------------------------------------------------------
    def compare(
        self,
        other: TriadModel,
        *,
        shared_g: bool = True,
        check_sensor: bool = True,
        covariance: str = "noise_model",
    ) -> CalibrationComparison:
        """Test whether the calibration ``other`` (a later one of the same sensor, say)
        differs from this one beyond their uncertainty: a Wald test of ``other - self``.

        The covariance of the difference is ``C_self + C_other`` (independent sessions),
        except for the reference gravity's term. A file made with ``sigma_g`` carries
        ``sigma_g^2 j j^T`` (``j = dp/dg = -p / g`` for the entries of K, 0 for the biases) in
        its covariances. When both files used the same value of g (the same site value, equal
        ``g``) its error is one error shared by both, which moves both parameter vectors
        alike: with ``shared_g`` (default) the cross term is taken out, so the difference
        keeps only ``sigma_g^2 (j_self - j_other)(j_self - j_other)^T`` of it, not twice
        ``sigma_g^2 j j^T`` (counted twice, a real 3e-4 drift of sz under a 1e-3 m/s^2 formula
        g was found in 31 % of 2000 simulated pairs instead of 77 %). Files with different g
        values (different sites or gravimeter readings) are taken as independent.

        ``covariance``: "noise_model" (default) uses each file's ``covariance_noise_model``:
        under a correct noise model the test then has its nominal size (5 % of pairs of
        simulated sessions of one sensor rejected at alpha 0.05; 4.2 % of 2000). "realistic"
        uses the stored realistic covariance: it is inflated by the Birge ratio whenever
        chi2/dof exceeds 1, by chance in half the sessions, so the test is conservative (2.7 %
        of the same 2000 pairs rejected) and loses power; use it when a file's chi2/dof
        shows the noise model too small (the summary then says so), where the noise-model
        test would reject too often.

        ``check_sensor``: refuse to compare calibrations of different models, units or sensor
        ids (False compares them anyway, on the parameters both models have).
        """
        return _compare(self, other, shared_g=shared_g, check_sensor=check_sensor,
                        covariance=covariance)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, TriadModel):
            return NotImplemented
        return json.dumps(self.to_dict(), sort_keys=True) == json.dumps(
            other.to_dict(), sort_keys=True
        )

    __hash__ = None  # type: ignore[assignment]

    def __setstate__(self, state: dict[str, Any]) -> None:
        """Unpickled or copied: the arrays read-only again, as :meth:`__init__` makes them
        (pickle and deepcopy hand them back writable, and an edit in place would then change
        what apply does and contradict the model's own record)."""
        self.__dict__.update(state)
        for name in ("K", "bias", "covariance_noise_model", "covariance_scaled"):
            a = self.__dict__.get(name)
            if isinstance(a, np.ndarray):
                a.setflags(write=False)

    def __repr__(self) -> str:
        v = np.array2string(self.vector, precision=6)
        sid = f", sensor_id={self.sensor_id!r}" if self.sensor_id else ""
        return f"TriadModel(model={self.model!r}, vector={v}{sid}, date={self.date!r})"


#: The z-score beyond which :class:`CalibrationComparison` names a parameter as moved.
MOVED_Z = 3.0


@dataclass(frozen=True, eq=False)
class CalibrationComparison:
    """Two calibrations of one sensor compared (:meth:`TriadModel.compare`).

    ``names``: the parameters compared; ``difference``: ``new - old`` (the argument minus the
    model ``compare`` was called on), in the files' units; ``std``: the std of each
    difference; ``z``: ``difference / std``; ``chi2``: the Wald statistic
    ``d^T C^-1 d`` with ``dof`` degrees of freedom (the number of parameters) and its
    upper-tail ``p_value``; ``covariance``: ``C``, the covariance of the difference;
    ``covariance_source``: which covariances of the files were used; ``shared_g``: whether a
    reference-gravity error shared by both was taken out of it; ``notes``: what the test
    assumed that the files question (chi2/dof above the noise model, different g).
    """

    names: tuple[str, ...]
    difference: NDArray[np.float64]
    std: NDArray[np.float64]
    z: NDArray[np.float64]
    chi2: float
    dof: int
    p_value: float
    covariance: NDArray[np.float64]
    covariance_source: str
    shared_g: bool
    old: str
    new: str
    notes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for a in (self.difference, self.std, self.z, self.covariance):
            a.setflags(write=False)

    def moved(self, k: float = MOVED_Z) -> tuple[str, ...]:
        """The parameters whose difference exceeds ``k`` std (3 by default)."""
        return tuple(n for n, z in zip(self.names, self.z, strict=True) if abs(z) > k)

    def changed(self, alpha: float = 0.05) -> bool:
        """Whether the Wald test rejects "the same calibration" at level ``alpha``."""
        return bool(self.p_value < alpha)

    def to_dict(self) -> dict[str, Any]:
        """Plain data (the command line's ``--json``)."""
        return {
            "old": self.old, "new": self.new, "names": list(self.names),
            "difference": plain(self.difference), "std": plain(self.std), "z": plain(self.z),
            "chi2": self.chi2, "dof": self.dof, "p_value": self.p_value,
            "moved": list(self.moved()), "covariance_source": self.covariance_source,
            "shared_g": self.shared_g, "notes": list(self.notes),
        }

    def summary(self) -> str:
        moved = self.moved()
        lines = [
            f"calibrations compared: {self.old} -> {self.new}",
            f"  Wald test of new - old: chi2 = {self.chi2:.3g} on {self.dof} dof, "
            f"p = {self.p_value:.2g} ({'differ' if self.changed() else 'no change shown'} "
            "at alpha 0.05)",
            f"  covariance: {self.covariance_source}"
            + ("; the error of the g both used (the same value, sigma_g) moves both alike: "
               "counted once, it drops out of the difference" if self.shared_g else ""),
            f"  {'param':6s} {'new - old':>12s} {'std':>10s} {'z':>7s}",
        ]
        for n, d, s, z in zip(self.names, self.difference, self.std, self.z, strict=True):
            flag = "  moved" if abs(z) > MOVED_Z else ""
            lines.append(f"  {n:6s} {d:12.4g} {s:10.3g} {z:7.2f}{flag}")
        lines.append(f"  moved beyond {MOVED_Z:g} std: " + (", ".join(moved) if moved else "none"))
        lines += [f"  note: {n}" for n in self.notes]
        return "\n".join(lines)


def _label(m: TriadModel) -> str:
    sid = f"{m.sensor_id} " if m.sensor_id else ""
    return f"{sid}{m.date}"


def _sigma_g(m: TriadModel) -> float:
    sg = m.metadata.get("sigma_g")
    if not isinstance(sg, (int, float)) or isinstance(sg, bool) or not math.isfinite(sg):
        return 0.0
    return float(sg) if sg > 0 else 0.0


def _g_jacobian(m: TriadModel) -> NDArray[np.float64]:
    """``j = dp/dg``: ``-p / g`` for the entries of K, 0 for the biases."""
    j = -m.vector / (m.g or 1.0)
    j[3:6] = 0.0
    return j


def _noise_excess(m: TriadModel) -> str | None:
    """A note when the file's chi2/dof says its noise model is too small (p < 0.05)."""
    md = m.metadata
    chi2, dof = md.get("chi2_dof"), md.get("dof")
    if (not isinstance(chi2, (int, float)) or isinstance(chi2, bool) or not isinstance(dof, int)
            or dof <= 0 or not math.isfinite(chi2)):
        return None
    sess = md.get("fit_session")
    if isinstance(sess, dict) and sess.get("noise_known") is False:
        return None  # the noise was estimated: its covariance is the scaled one already
    p = float(_core.chi2_sf(float(chi2) * dof, float(dof)))
    if p >= 0.05:
        return None
    return (f"{_label(m)}: chi2/dof = {chi2:.3g} on {dof} dof (p = {p:.2g}): the residuals "
            "exceed its noise model, so the noise-model covariance understates its std and "
            "the test rejects too often; compare with covariance='realistic' "
            "(--covariance realistic)")


def _compare(a: TriadModel, b: TriadModel, *, shared_g: bool, check_sensor: bool,
             covariance: str) -> CalibrationComparison:
    if not isinstance(b, TriadModel):
        raise CalibrationError(f"compare needs a TriadModel; got {type(b).__name__}")
    if covariance not in ("noise_model", "realistic"):
        raise CalibrationError(
            f"covariance must be 'noise_model' or 'realistic'; got {covariance!r}")
    if check_sensor:
        for what, va, vb in (("models", a.model, b.model), ("sensor ids", a.sensor_id, b.sensor_id),
                             ("output units", a.units, b.units),
                             ("input units", a.input_units, b.input_units)):
            if va != vb:
                raise CalibrationError(
                    f"the calibrations have different {what} ({va!r} and {vb!r}): their "
                    "parameters are not the same quantities; compare them anyway with "
                    "check_sensor=False")
    p = min(a.vector.size, b.vector.size)
    covs = []
    for m in (a, b):
        c = m.covariance_noise_model if covariance == "noise_model" else m.covariance
        if c is None:
            raise CalibrationError(f"{_label(m)}: the calibration has no covariance to "
                                   f"compare with ({covariance.replace('_', ' ')})")
        covs.append(np.asarray(c, dtype=np.float64)[:p, :p])
    cov = covs[0] + covs[1]
    sa, sb = _sigma_g(a), _sigma_g(b)
    notes: list[str] = []
    same_g = a.g is not None and b.g is not None and a.g == b.g
    shared = bool(shared_g and same_g and sa > 0 and sb > 0)
    if shared:
        # One error dg in the one g both used: Cov(p_a, p_b) = sa sb j_a j_b^T (the errors
        # fully correlated), taken out of Var(p_b - p_a) = C_a + C_b - 2 Cov.
        ja, jb = _g_jacobian(a)[:p], _g_jacobian(b)[:p]
        cross = sa * sb * np.outer(ja, jb)
        cov = cov - cross - cross.T
    elif shared_g and (sa > 0 or sb > 0) and not same_g:
        notes.append(f"the files used different g ({a.g!r} and {b.g!r}): their gravity "
                     "errors taken as independent")
    if covariance == "noise_model":
        notes += [n for n in (_noise_excess(a), _noise_excess(b)) if n]
    cov = 0.5 * (cov + cov.T)
    d = b.vector[:p] - a.vector[:p]
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    if not np.all(std > 0):
        raise CalibrationError("the covariance of the difference has a zero variance: the "
                               "files carry no uncertainty for some parameter")
    # Solve in correlation form (scale factors in the hundreds and biases in the tens of
    # thousands of counts make the raw matrix badly scaled).
    corr = cov / np.outer(std, std)
    zs = d / std
    try:
        w = float(zs @ np.linalg.solve(corr, zs))
    except np.linalg.LinAlgError:
        raise CalibrationError("the covariance of the difference is singular") from None
    src = ("each file's noise-model covariance (covariance_noise_model)"
           if covariance == "noise_model" else "each file's realistic covariance (covariance)")
    return CalibrationComparison(
        names=PARAM_NAMES[:p], difference=d, std=std, z=zs, chi2=w, dof=int(p),
        p_value=float(_core.chi2_sf(w, float(p))), covariance=cov, covariance_source=src,
        shared_g=shared, old=_label(a), new=_label(b), notes=tuple(notes))


def _full_k_route(k: NDArray[np.float64]) -> str:
    """For a full K (entries above and below the diagonal): how to import it. The norm cannot
    see a rotation of the calibrated frame, so a full K (the inverse of a six-position or
    turntable calibration's W) is a triangular K times a rotation; its triangular factor
    gives the same norms for every input, in the triangular model's frame."""
    if (_core.static_model_violation(k.tolist(), "lower") is None
            or _core.static_model_violation(k.tolist(), "upper") is None):
        return ""
    return (". A full K (the inverse of a six-position or turntable calibration's W, "
            "a = W (am - b)) is a triangular K times a rotation, which the norm cannot see: "
            "import its triangular factor, which drops the rotation (the calibrated frame is "
            "then the triangular model's, as accelcal's fits give; the bias is unchanged): "
            "q, r = numpy.linalg.qr(K.T); r *= numpy.sign(numpy.diag(r))[:, None]; "
            "K_lower = r.T (model='lower'; see docs/guide-field.md, section 1)")


def _pattern(model: str) -> str:
    return {
        "lower": "diagonal and below",
        "upper": "diagonal and above",
        "diag": "diagonal only",
    }[model]


def _short(err: Any) -> str:
    """A schema error in a line: the offending value and what was expected."""
    v = err.instance
    txt = json.dumps(v) if not isinstance(v, (dict, list)) or len(json.dumps(v)) < 60 else "..."
    kind = err.validator
    desc = err.schema.get("description") if isinstance(err.schema, dict) else None
    if desc and kind in ("oneOf", "anyOf", "pattern"):
        return f"{txt} is not {desc}"
    if kind == "type":
        return f"{txt} is not of type {err.validator_value!r}"
    if kind in ("minimum", "exclusiveMinimum"):
        return f"{txt} must be {'>' if kind == 'exclusiveMinimum' else '>='} {err.validator_value}"
    if kind in ("minItems", "maxItems"):
        return f"has the wrong number of entries ({err.message})"
    return str(err.message)
