# Type stub of the compiled module (checked by `python -m mypy.stubtest accelcal._core`).
from typing import Any, Literal, final

import numpy as np
from numpy.typing import NDArray

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

# --- gap diagnosis (rust/src/py/gap.rs) ---
@final
class GapSettings:
    """Engine settings; every value not given is the engine's default."""

    def __new__(
        cls,
        *,
        alpha: float | None = None,
        max_effects: int | None = None,
        loo: bool | None = None,
        sine_tol: float | None = None,
        ambiguity_cos: float | None = None,
        ambiguity_weight: float | None = None,
        min_temp_range: float | None = None,
        test: Literal["auto", "chi2", "f"] | None = None,
        trust_level: float | None = None,
        gate: Literal["auto", "strict", "off"] | None = None,
        gate_sd: float | None = None,
        gate_margin: float | None = None,
        correction: Literal["minp", "bonferroni"] | None = None,
        n_draws: int | None = None,
    ) -> GapSettings: ...
    @property
    def alpha(self) -> float: ...
    @property
    def max_effects(self) -> int: ...
    @property
    def loo(self) -> bool: ...
    @property
    def sine_tol(self) -> float: ...
    @property
    def ambiguity_cos(self) -> float: ...
    @property
    def ambiguity_weight(self) -> float: ...
    @property
    def min_temp_range(self) -> float: ...
    @property
    def test(self) -> str: ...
    @property
    def trust_level(self) -> float: ...
    @property
    def gate(self) -> str: ...
    @property
    def gate_sd(self) -> float: ...
    @property
    def gate_margin(self) -> float: ...
    @property
    def correction(self) -> str: ...
    @property
    def n_draws(self) -> int: ...

@final
class GapCandidate:
    """One candidate effect's screening and estimate."""

    @property
    def name(self) -> str: ...
    @property
    def unit(self) -> str: ...
    @property
    def status(self) -> str: ...
    @property
    def sines(self) -> list[float]: ...
    @property
    def d(self) -> int: ...
    @property
    def score(self) -> float: ...
    @property
    def f(self) -> float: ...
    @property
    def p_f(self) -> float: ...
    @property
    def p_chi2(self) -> float: ...
    @property
    def p(self) -> float: ...
    @property
    def chi2_used(self) -> bool: ...
    @property
    def bic(self) -> float: ...
    @property
    def weight(self) -> float: ...
    @property
    def estimate(self) -> list[float]: ...
    @property
    def std(self) -> list[float]: ...

@final
class GapHeldOut:
    """Leave-one-group-out held-out gap."""

    @property
    def g_before(self) -> float: ...
    @property
    def g_after(self) -> float: ...
    @property
    def rms_before(self) -> float: ...
    @property
    def rms_after(self) -> float: ...
    @property
    def z_before(self) -> list[float]: ...
    @property
    def z_after(self) -> list[float]: ...
    @property
    def g_steps(self) -> list[float]: ...
    @property
    def fold_counts(self) -> list[int]: ...
    @property
    def n_failed(self) -> int: ...

@final
class GapGroup:
    """The gap of one group of rows."""

    @property
    def key(self) -> float: ...
    @property
    def n(self) -> int: ...
    @property
    def mean_e2(self) -> float: ...
    @property
    def p(self) -> float: ...

@final
class GapLocation:
    """Where the gap lies."""

    @property
    def t_stud(self) -> list[float]: ...
    @property
    def threshold(self) -> float: ...
    @property
    def flagged(self) -> list[int]: ...
    @property
    def axes(self) -> list[GapGroup]: ...
    @property
    def segments(self) -> list[GapGroup]: ...
    @property
    def serial(self) -> tuple[float, float, float] | None: ...
    @property
    def temperature(self) -> tuple[float, float, float, float] | None: ...

@final
class GapStructureTest:
    """One structure test."""

    @property
    def name(self) -> str: ...
    @property
    def status(self) -> str: ...
    @property
    def n_columns(self) -> int: ...
    @property
    def d(self) -> int: ...
    @property
    def dof2(self) -> float: ...
    @property
    def statistic(self) -> float: ...
    @property
    def p_value(self) -> float: ...
    @property
    def p_adjusted(self) -> float: ...
    @property
    def explained(self) -> float: ...

@final
class GapNoiseEmpirical:
    """Empirical dwell-mean noise from half-dwell differences."""

    @property
    def n(self) -> int: ...
    @property
    def rms(self) -> float: ...
    @property
    def rms_model(self) -> float: ...
    @property
    def rms_white(self) -> float: ...
    @property
    def rms_allan(self) -> float: ...
    @property
    def ratio_model(self) -> float: ...
    @property
    def ratio_white(self) -> float: ...
    @property
    def ratio_allan(self) -> float: ...
    @property
    def p_model(self) -> float: ...

@final
class GapStructure:
    """What the remaining gap is made of."""

    @property
    def verdict(self) -> str: ...
    @property
    def statistic(self) -> float: ...
    @property
    def p_value(self) -> float: ...
    @property
    def persistence(self) -> float: ...
    @property
    def persistence_testable(self) -> bool: ...
    @property
    def per_dwell_rms(self) -> float: ...
    @property
    def quantization_rms(self) -> float: ...
    @property
    def tests(self) -> list[GapStructureTest]: ...
    @property
    def noise_empirical(self) -> GapNoiseEmpirical | None: ...

@final
class GapRaw:
    """Everything one diagnosis measured (any system)."""

    @property
    def system(self) -> str: ...
    @property
    def n(self) -> int: ...
    @property
    def base_params(self) -> list[float]: ...
    @property
    def base_std(self) -> list[float]: ...
    @property
    def sigma(self) -> list[float]: ...
    @property
    def resid(self) -> list[float]: ...
    @property
    def e(self) -> list[float]: ...
    @property
    def leverage(self) -> list[float]: ...
    @property
    def chi2(self) -> float: ...
    @property
    def dof(self) -> int: ...
    @property
    def p_chi2(self) -> float: ...
    @property
    def noise_known(self) -> bool: ...
    @property
    def noise_scale(self) -> float: ...
    @property
    def candidates(self) -> list[GapCandidate]: ...
    @property
    def bic_none(self) -> float: ...
    @property
    def weight_none(self) -> float: ...
    @property
    def selected(self) -> list[str]: ...
    @property
    def step_p(self) -> list[float]: ...
    @property
    def step_p_adj(self) -> list[float]: ...
    @property
    def step_m(self) -> list[int]: ...
    @property
    def not_confirmed(self) -> tuple[str, float, float, float] | None: ...
    @property
    def stop_p(self) -> float: ...
    @property
    def stop_p_adj(self) -> float: ...
    @property
    def params_after(self) -> list[float]: ...
    @property
    def std_after(self) -> list[float]: ...
    @property
    def resid_after(self) -> list[float]: ...
    @property
    def e_after(self) -> list[float]: ...
    @property
    def sigma_after(self) -> list[float]: ...
    @property
    def chi2_after(self) -> float: ...
    @property
    def dof_after(self) -> int: ...
    @property
    def p_after(self) -> float: ...
    @property
    def ambiguous(self) -> list[tuple[str, str, float]]: ...
    @property
    def loo(self) -> GapHeldOut | None: ...
    @property
    def gate_skipped(self) -> bool: ...
    @property
    def location(self) -> GapLocation: ...
    @property
    def structure(self) -> GapStructure: ...
    @property
    def direction(self) -> list[list[float]]: ...
    @property
    def pose_angle_deg(self) -> list[float]: ...

def gap_dictionary(
    system: Literal["static", "centrifuge", "gradiometer"],
) -> list[tuple[str, str, int]]:
    """The effect dictionary of a system: (name, unit, number of parameters)."""

def gap_diagnose_static(
    mean: NDArray[np.float64],
    var: NDArray[np.float64] | None,
    t: NDArray[np.float64] | None,
    temperature: NDArray[np.float64] | None,
    g: float,
    effects: list[str],
    settings: GapSettings,
    calibration: tuple[list[list[float]], list[float], bool] | None = None,
    half_mean: NDArray[np.float64] | None = None,
    white_var: NDArray[np.float64] | None = None,
    allan_var: NDArray[np.float64] | None = None,
    sample_var: NDArray[np.float64] | None = None,
    lsb: list[float] | None = None,
) -> GapRaw:
    """Static gap diagnosis on raw dwell means."""

def gap_diagnose_centrifuge(
    outputs: NDArray[np.float64],
    omega: NDArray[np.float64],
    radius: float,
    g: float,
    effects: list[str],
    settings: GapSettings,
    spin_axis: NDArray[np.float64] | None = None,
    sigma_norm: NDArray[np.float64] | None = None,
    sigma_axis: NDArray[np.float64] | None = None,
) -> GapRaw:
    """Centrifuge gap diagnosis (outputs in g, omega rad/s, radius m)."""

def gap_diagnose_gradiometer(
    azimuth_deg: NDArray[np.float64],
    outputs: NDArray[np.float64],
    effects: list[str],
    settings: GapSettings,
    t: NDArray[np.float64] | None = None,
    sigma: NDArray[np.float64] | None = None,
    warmup_tau_s: float = 600.0,
) -> GapRaw:
    """Gradiometer gap diagnosis (azimuths deg, outputs (m, 2) in E)."""

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

__all__ = [
    "centrifuge_fit_raw",
    "DwellTableRaw",
    "detect_dwells_raw",
    "dwell_stats_raw",
    "RawDwellAccumulator",
    "GapCandidate",
    "GapGroup",
    "GapHeldOut",
    "GapLocation",
    "GapNoiseEmpirical",
    "GapRaw",
    "GapSettings",
    "GapStructure",
    "GapStructureTest",
    "gap_diagnose_centrifuge",
    "gap_diagnose_gradiometer",
    "gap_diagnose_static",
    "gap_dictionary",
    "demodulate_raw",
    "startup_bias_raw",
    "startup_predict_raw",
    "apply_triad_raw",
    "static_fit_batch_raw",
    "static_fit_raw",
    "StaticFitRaw",
    "CalibrationError",
    "DegenerateDataError",
]
