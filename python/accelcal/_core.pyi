# Type stub of the compiled module (checked by `python -m mypy.stubtest accelcal._core`).
from collections.abc import Callable
from typing import Any, final

import numpy as np
from numpy.typing import NDArray

class CalibrationError(ValueError): ...
class DegenerateDataError(CalibrationError): ...

def dwell_stats_raw(
    samples: NDArray[Any],
    bounds: NDArray[np.int64],
    t: NDArray[np.float64] | None = None,
    temperature: NDArray[np.float64] | None = None,
) -> dict[str, Any]: ...
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
) -> dict[str, Any]: ...

@final
class RawDwellAccumulator:
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
    ) -> None: ...
    @property
    def position(self) -> int: ...
    def finish(self) -> dict[str, Any]: ...

def startup_bias_raw(
    theta_rad: NDArray[np.float64],
    outputs: NDArray[np.float64],
    dwell_std: NDArray[np.float64],
    t: NDArray[np.float64] | None = None,
    t_ref: float = 0.0,
) -> dict[str, Any]: ...
def startup_predict_raw(
    theta_rad: NDArray[np.float64],
    dwell_std: NDArray[np.float64],
    t: NDArray[np.float64] | None = None,
    t_ref: float = 0.0,
    gradient: list[float] | None = None,
    gradient_magnitude: float = 0.0,
    sigma_theta_rad: float = 0.0,
) -> dict[str, Any]: ...
def demodulate_raw(
    accel: NDArray[Any],
    phase: NDArray[np.float64],
    bounds: NDArray[np.int64],
    radius_m: float,
) -> dict[str, Any]: ...

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

def centrifuge_fit_raw(
    outputs: NDArray[np.float64],
    omega: NDArray[np.float64],
    radius: float,
    g: float,
    method: str = "nls",
    k3: bool = False,
    misalignment: bool = False,
    lever_arm: str | None = None,
    spin_axis: NDArray[np.float64] | None = None,
    sigma: NDArray[np.float64] | None = None,
    robust: bool = True,
    outlier_k: float = 5.0,
    sigma_floor: float = 1e-9,
    max_draws: int = 20000,
    seed: int = 0,
) -> dict[str, Any]: ...

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
    "centrifuge_fit_raw",
    "detect_dwells_raw",
    "dwell_stats_raw",
    "RawDwellAccumulator",
    "gap_chi2_sf",
    "gap_diagnose_raw",
    "gap_f_sf",
    "gap_model_residuals_raw",
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
