# Type stub of the compiled module (checked by `python -m mypy.stubtest accelcal._core`).
from collections.abc import Callable
from typing import Any, Literal, final

import numpy as np
from numpy.typing import NDArray
from typing_extensions import Self, disjoint_base

class CalibrationError(ValueError): ...
class DegenerateDataError(CalibrationError): ...

@final
class DwellTableRaw:
    """A finished dwell table (see ``accelcal.DwellSet`` for each field)."""

    @property
    def start(self) -> NDArray[np.int64]: ...
    @property
    def stop(self) -> NDArray[np.int64]: ...
    @property
    def count(self) -> NDArray[np.int64]: ...
    @property
    def mean(self) -> NDArray[np.float64]: ...
    @property
    def var(self) -> NDArray[np.float64]: ...
    @property
    def half_mean(self) -> NDArray[np.float64]: ...
    @property
    def inflation(self) -> NDArray[np.float64]: ...
    @property
    def lsb(self) -> NDArray[np.float64] | None: ...
    @property
    def dropped(self) -> int: ...
    @property
    def t(self) -> NDArray[np.float64] | None: ...
    @property
    def temperature(self) -> NDArray[np.float64] | None: ...
    @property
    def noise_var(self) -> NDArray[np.float64] | None: ...
    @property
    def threshold(self) -> NDArray[np.float64] | None: ...

def dwell_stats_raw(
    samples: NDArray[Any],
    bounds: NDArray[np.int64],
    t: NDArray[np.float64] | None = None,
    temperature: NDArray[np.float64] | None = None,
) -> DwellTableRaw:
    """Per-dwell statistics over explicit ``[start, stop)`` bounds."""

def detect_dwells_raw(
    samples: NDArray[Any],
    fs: float,
    window_s: float,
    k: float,
    min_dwell_s: float,
    trim_s: float,
    noise_quantile: float,
    block_s: float,
    noise_var: list[float] | None = None,
    t: NDArray[np.float64] | None = None,
    temperature: NDArray[np.float64] | None = None,
) -> DwellTableRaw:
    """Automatic static-interval detection plus per-dwell statistics."""

@final
class RawDwellAccumulator:
    """Streaming accumulator (bounds or detector mode); safe to share between threads."""

    def __new__(
        cls,
        bounds: NDArray[np.int64] | None = None,
        fs: float | None = None,
        window_s: float = 1.0,
        k: float = 6.0,
        min_dwell_s: float = 1.0,
        trim_s: float = 0.1,
        noise_quantile: float = 0.2,
        block_s: float = 0.02,
        noise_var: list[float] | None = None,
    ) -> RawDwellAccumulator: ...
    def push(
        self,
        chunk: NDArray[Any],
        t: NDArray[np.float64] | None = None,
        temperature: NDArray[np.float64] | None = None,
    ) -> None:
        """Push a chunk; on error nothing of it is kept."""

    @property
    def position(self) -> int:
        """Samples pushed so far."""

    def finish(self) -> DwellTableRaw:
        """The dwell table of everything pushed so far."""

    def to_state(self) -> bytes:
        """The state as versioned bytes."""

    @staticmethod
    def from_state(state: bytes) -> RawDwellAccumulator:
        """Rebuild an accumulator from ``to_state`` bytes."""

    def __reduce__(self) -> tuple[Any, ...]: ...

# --- gradiometer start-up bias and demodulation (rust/src/py/gradiometer.rs) ---
@disjoint_base
class StartupBiasCore:
    """Start-up bias, gradient (and drift) with covariance; `accelcal.StartupBias` subclasses
    it. Arrays are read-only; pickles."""

    def __new__(
        cls,
        bias: NDArray[np.float64],
        gradient: NDArray[np.float64],
        drift: NDArray[np.float64] | None,
        covariance: NDArray[np.float64],
        std: NDArray[np.float64],
        residuals: NDArray[np.float64],
        unit_covariance: NDArray[np.float64],
        sigma: NDArray[np.float64] | None,
        sigma_estimated: bool,
        dof: int,
        condition: float,
        azimuth_deg: NDArray[np.float64],
        t: NDArray[np.float64] | None,
        t_ref: float | None,
        names: list[str],
    ) -> Self: ...
    def __reduce__(self) -> tuple[type[Self], tuple[Any, ...]]: ...
    @property
    def bias(self) -> NDArray[np.float64]:
        """Per-startup bias of the inline and cross channels, E."""
    @property
    def gradient(self) -> NDArray[np.float64]:
        """Navigation-frame gradient (I, C), E."""
    @property
    def drift(self) -> NDArray[np.float64] | None:
        """Linear bias drift, E/s (drift model only)."""
    @property
    def covariance(self) -> NDArray[np.float64]: ...
    @property
    def std(self) -> NDArray[np.float64]: ...
    @property
    def residuals(self) -> NDArray[np.float64]: ...
    @property
    def unit_covariance(self) -> NDArray[np.float64]: ...
    @property
    def sigma(self) -> NDArray[np.float64] | None: ...
    @property
    def sigma_estimated(self) -> bool: ...
    @property
    def dof(self) -> int: ...
    @property
    def condition(self) -> float: ...
    @property
    def azimuth_deg(self) -> NDArray[np.float64]: ...
    @property
    def t(self) -> NDArray[np.float64] | None: ...
    @property
    def t_ref(self) -> float | None: ...
    @property
    def names(self) -> list[str]: ...

def startup_bias_raw(
    azimuth_deg: NDArray[np.float64],
    outputs: NDArray[np.float64],
    sigma: NDArray[np.float64] | None = None,
    t: NDArray[np.float64] | None = None,
    t_ref: float | None = None,
) -> StartupBiasCore:
    """Start-up least squares from azimuths in degrees; sigma None: estimated."""

@disjoint_base
class StartupPredictionCore:
    """Predicted accuracy of a start-up sequence; `accelcal.StartupPrediction` subclasses it."""

    def __new__(
        cls,
        covariance: NDArray[np.float64],
        azimuth_covariance: NDArray[np.float64],
        total_covariance: NDArray[np.float64],
        std: NDArray[np.float64],
        closed_form_variance: float,
        condition: float,
        names: list[str],
    ) -> Self: ...
    def __reduce__(self) -> tuple[type[Self], tuple[Any, ...]]: ...
    @property
    def covariance(self) -> NDArray[np.float64]: ...
    @property
    def azimuth_covariance(self) -> NDArray[np.float64]: ...
    @property
    def total_covariance(self) -> NDArray[np.float64]: ...
    @property
    def std(self) -> NDArray[np.float64]: ...
    @property
    def closed_form_variance(self) -> float: ...
    @property
    def condition(self) -> float: ...
    @property
    def names(self) -> list[str]: ...

def startup_predict_raw(
    azimuth_deg: NDArray[np.float64],
    dwell_std: NDArray[np.float64],
    t: NDArray[np.float64] | None = None,
    t_ref: float | None = None,
    gradient: list[float] | None = None,
    gradient_magnitude: float = 0.0,
    sigma_theta_deg: float = 0.0,
) -> StartupPredictionCore:
    """Predicted covariances of an azimuth design (degrees)."""

@disjoint_base
class DemodulatedCore:
    """Per-dwell inline and cross channels; `accelcal.Demodulated` subclasses it."""

    def __new__(
        cls,
        inline_E: NDArray[np.float64],
        cross_E: NDArray[np.float64],
        std_inline_E: NDArray[np.float64],
        std_cross_E: NDArray[np.float64],
        start: NDArray[np.int64],
        stop: NDArray[np.int64],
        revolutions: NDArray[np.int64],
        resid_rms: NDArray[np.float64],
        nuisance: NDArray[np.float64],
        t: NDArray[np.float64] | None,
    ) -> Self: ...
    def __reduce__(self) -> tuple[type[Self], tuple[Any, ...]]: ...
    @property
    def inline_E(self) -> NDArray[np.float64]: ...
    @property
    def cross_E(self) -> NDArray[np.float64]: ...
    @property
    def std_inline_E(self) -> NDArray[np.float64]: ...
    @property
    def std_cross_E(self) -> NDArray[np.float64]: ...
    @property
    def start(self) -> NDArray[np.int64]: ...
    @property
    def stop(self) -> NDArray[np.int64]: ...
    @property
    def revolutions(self) -> NDArray[np.int64]: ...
    @property
    def resid_rms(self) -> NDArray[np.float64]: ...
    @property
    def nuisance(self) -> NDArray[np.float64]: ...
    @property
    def t(self) -> NDArray[np.float64] | None: ...

def demodulate_raw(
    accel: NDArray[Any],
    phase: NDArray[np.float64],
    bounds: NDArray[np.int64],
    radius_m: float,
    t: NDArray[np.float64] | None = None,
) -> DemodulatedCore:
    """2-omega demodulation of (N, 4) streams per dwell."""

def gap_diagnose_raw(
    mean: NDArray[np.float64],
    sigma_mean: NDArray[np.float64] | None,
    t: NDArray[np.float64] | None,
    temperature: NDArray[np.float64] | None,
    g: float,
    effects: list[str],
    alpha: float = 0.05,
    max_effects: int = 3,
    loo: bool = True,
    start: list[float] | None = None,
    sine_tol: float = 0.05,
    ambiguity_cos: float = 0.9,
    min_temp_range: float = 0.05,
    test: str = "auto",
    trust_level: float = 0.1,
    gate: str = "auto",
    correction: str = "minp",
    n_draws: int = 4000,
    gate_margin: float = 0.0,
) -> dict[str, Any]: ...
def gap_chi2_sf(x: float, k: float) -> float: ...
def gap_f_sf(f: float, d1: float, d2: float) -> float: ...
def gap_model_residuals_raw(
    mean: NDArray[np.float64],
    t: NDArray[np.float64] | None,
    temperature: NDArray[np.float64] | None,
    g: float,
    params: list[float],
    effects: list[str],
) -> NDArray[np.float64]: ...

# --- centrifuge (rust/src/py/centrifuge.rs) ---
@disjoint_base
class CentrifugeFitCore:
    """Result of one centrifuge fit; `accelcal.CentrifugeFit` subclasses it. Arrays are
    read-only; pickles."""

    def __new__(cls, *args: Any) -> Self:
        """``(fit)``: the same result, arrays shared; ``(*fields)``: rebuilt (pickling)."""
    def __reduce__(self) -> tuple[type[Self], tuple[Any, ...]]: ...
    @property
    def params(self) -> NDArray[np.float64]: ...
    @property
    def names(self) -> list[str]: ...
    @property
    def covariance(self) -> NDArray[np.float64]: ...
    @property
    def std(self) -> NDArray[np.float64]: ...
    @property
    def residuals(self) -> NDArray[np.float64]: ...
    @property
    def outliers(self) -> NDArray[np.int64]: ...
    @property
    def residual_rms(self) -> float: ...
    @property
    def screen_sigma(self) -> float: ...
    @property
    def studentized(self) -> NDArray[np.float64]: ...
    @property
    def threshold(self) -> float: ...
    @property
    def residual_std(self) -> NDArray[np.float64]: ...
    @property
    def draws(self) -> int: ...
    @property
    def singular_values(self) -> NDArray[np.float64]: ...
    @property
    def condition_number(self) -> float: ...
    @property
    def iterations(self) -> int: ...
    @property
    def converged(self) -> bool: ...
    @property
    def taylor_coefficients(self) -> NDArray[np.float64] | None: ...
    @property
    def method(self) -> str: ...
    @property
    def radius(self) -> float: ...
    @property
    def g(self) -> float: ...
    @property
    def fit_k3(self) -> bool: ...
    @property
    def fit_misalignment(self) -> bool: ...
    @property
    def lever_model(self) -> str | None: ...
    @property
    def noise_known(self) -> bool: ...
    @property
    def labels(self) -> list[str]: ...

def centrifuge_fit_raw(
    outputs: NDArray[np.float64],
    omega: NDArray[np.float64],
    radius: float,
    g: float,
    method: Literal["nls", "taylor-paper"] = "nls",
    k3: bool = False,
    misalignment: bool = False,
    lever_arm: Literal["along", "full"] | None = None,
    spin_axis: NDArray[np.float64] | None = None,
    sigma: NDArray[np.float64] | None = None,
    robust: bool = True,
    outlier_k: float = 5.0,
    sigma_floor: float = 1e-9,
    max_draws: int = 20000,
    seed: int = 0,
    check_units: bool = True,
    labels: list[str] | None = None,
) -> CentrifugeFitCore:
    """Centrifuge calibration; sigma: per-axis output noise (k, 3), g."""

def centrifuge_unit_check_raw(
    outputs: NDArray[np.float64],
    omega: NDArray[np.float64],
    radius: float,
    g: float,
    robust: bool = True,
    max_draws: int = 20000,
    seed: int = 0,
) -> tuple[float, list[tuple[str, str, str, str, float, float]]] | None:
    """None when the units look right; else the scale needed and the likely conversions."""

def centrifuge_correct_raw(
    params: NDArray[np.float64],
    outputs: NDArray[np.float64],
    k3: bool = False,
    misalignment: bool = False,
    lever_arm: Literal["along", "full"] | None = None,
) -> NDArray[np.float64]:
    """Specific force (k, 3), g, by exact inversion of fitted parameters."""

# --- static field calibration (rust/src/py/static_fit.rs) ---
@final
class StaticFitRaw:
    @property
    def model(self) -> str: ...
    @property
    def params(self) -> NDArray[np.float64]: ...
    @property
    def start(self) -> NDArray[np.float64]: ...
    @property
    def covariance(self) -> NDArray[np.float64]: ...
    @property
    def residuals(self) -> NDArray[np.float64]: ...
    @property
    def sigma_r(self) -> NDArray[np.float64]: ...
    @property
    def cost(self) -> float: ...
    @property
    def dof(self) -> int: ...
    @property
    def chi2_dof(self) -> float: ...
    @property
    def iterations(self) -> int: ...
    @property
    def converged(self) -> bool: ...
    @property
    def noise_known(self) -> bool: ...
    @property
    def note(self) -> str: ...
    @property
    def weak(self) -> bool: ...
    @property
    def degenerate(self) -> bool: ...
    @property
    def std_comparable(self) -> NDArray[np.float64]: ...
    @property
    def weakest_std(self) -> float: ...
    def observability(self) -> dict[str, Any]: ...
    def weak_text(self, weak_std: float) -> str: ...

def static_fit_raw(
    means: NDArray[np.float64],
    g: float,
    model: str = "lower",
    method: str = "lm",
    var: NDArray[np.float64] | None = None,
    start: list[float] | None = None,
    max_iter: int = 200,
    raise_degenerate: bool = True,
    degenerate_std: float = 0.1,
    weak_std: float = 1e-3,
) -> StaticFitRaw: ...
def static_fit_batch_raw(
    means: NDArray[np.float64],
    g: NDArray[np.float64],
    model: str = "lower",
    method: str = "lm",
    sigma: float | None = None,
    start: list[float] | None = None,
    max_iter: int = 200,
    degenerate_std: float = 0.1,
) -> dict[str, Any]: ...
def apply_triad_raw(
    samples: NDArray[Any], k: list[list[float]], b: list[float]
) -> NDArray[np.float64]: ...


# ---- text reader ----------------------------------------------------------------------------
#: One output group: (column index, scale, is ISO-8601 time) per column.
_Groups = list[list[tuple[int, float, bool]]]

@final
class TextBlocks:
    """Blocks of a text recording, read and parsed ahead on a background thread.

    Iterating yields ``(arrays, rows, bytes, repeats)`` per block in file order, ``arrays``
    holding one float64 array per column group ((m, k), or (m,) for one column).
    """

    def __new__(
        cls,
        path: str | None,
        offset: int,
        ncols: int,
        groups: _Groups,
        *,
        delimiter: str | None = None,
        decimal_comma: bool = False,
        comment: str = "#",
        names: list[str] | None = None,
        first_line: int = 1,
        t0: tuple[int, int] | None = None,
        prefix: bytes | None = None,
        stdin: bool = False,
        block_bytes: int = 4194304,
    ) -> TextBlocks: ...
    def __iter__(self) -> TextBlocks: ...
    def __next__(self) -> tuple[list[NDArray[np.float64]], int, int, int]: ...

def text_read_all(
    path: str | None,
    offset: int,
    ncols: int,
    groups: _Groups,
    *,
    delimiter: str | None = None,
    decimal_comma: bool = False,
    comment: str = "#",
    names: list[str] | None = None,
    first_line: int = 1,
    t0: tuple[int, int] | None = None,
    prefix: bytes | None = None,
    stdin: bool = False,
    block_bytes: int = 4194304,
    rows_hint: int = 0,
    progress: Callable[[int, int], object] | None = None,
) -> tuple[list[NDArray[np.float64]], int, int, int]:
    """Read a whole text recording into one array per column group: (arrays, rows, bytes,
    repeats)."""

def text_parse_head(
    data: bytes,
    ncols: int,
    groups: _Groups,
    *,
    delimiter: str | None = None,
    decimal_comma: bool = False,
    comment: str = "#",
    names: list[str] | None = None,
    first_line: int = 1,
    t0: tuple[int, int] | None = None,
    max_rows: int | None = None,
) -> tuple[list[NDArray[np.float64]], int, int, int]:
    """Parse at most ``max_rows`` data rows of ``data``: (arrays, rows, bytes, lines)."""

def parse_iso8601(text: str) -> tuple[int, int] | None:
    """(seconds, nanoseconds) since 1970-01-01T00:00:00Z of an ISO-8601 date and time."""

def format_rows(
    values: NDArray[np.float64],
    lead: NDArray[np.float64] | None = None,
    delimiter: str = ",",
) -> bytes:
    """Rows as delimited text, shortest round-trip float formatting."""

__all__ = [
    "CentrifugeFitCore",
    "centrifuge_correct_raw",
    "centrifuge_fit_raw",
    "centrifuge_unit_check_raw",
    "DwellTableRaw",
    "detect_dwells_raw",
    "dwell_stats_raw",
    "RawDwellAccumulator",
    "gap_chi2_sf",
    "gap_diagnose_raw",
    "gap_f_sf",
    "gap_model_residuals_raw",
    "DemodulatedCore",
    "StartupBiasCore",
    "StartupPredictionCore",
    "demodulate_raw",
    "startup_bias_raw",
    "startup_predict_raw",
    "apply_triad_raw",
    "static_fit_batch_raw",
    "static_fit_raw",
    "StaticFitRaw",
    "TextBlocks",
    "format_rows",
    "parse_iso8601",
    "text_parse_head",
    "text_read_all",
    "CalibrationError",
    "DegenerateDataError",
]
