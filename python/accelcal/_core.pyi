# Type stub of the compiled module (checked by `python -m mypy.stubtest accelcal._core`).
from collections.abc import Callable
from typing import Any, Final, Literal, final

import numpy as np
from numpy.typing import NDArray
from typing_extensions import Self, disjoint_base

class CalibrationError(ValueError): ...
class DegenerateDataError(CalibrationError): ...

#: The fewest samples the dwell detector's window may hold.
MIN_WINDOW_SAMPLES: Final[float]
#: The fewest samples a dwell needs for its variance to count in the output-fault checks.
FAULT_MIN_SAMPLES: Final[int]
#: Unit gravity directions closer than this (about 3 deg) are one pose.
SAME_POSE: Final[float]

@final
class StepLog:
    """A recording that holds only the rests (a block of samples per pose, nothing recorded
    while the sensor was turned): its runs between jumps."""

    @property
    def runs(self) -> NDArray[np.int64]:
        """``[start, stop)`` sample bounds of each run, (k, 2)."""
    @property
    def jumps(self) -> int:
        """Jumps found."""
    @property
    def period(self) -> int | None:
        """The run length shared by at least half of the runs, or None."""
    @property
    def motion_fraction(self) -> float:
        """Share of the samples in recorded motion."""

def dwell_step_log(samples: Any) -> StepLog | None:
    """The stream read as a log of rests, or None when it does not read as one (its moves
    are recorded, or it has too few jumps)."""

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
    @property
    def vibrating_bounds(self) -> NDArray[np.int64]: ...
    @property
    def vibrating_std(self) -> NDArray[np.float64]: ...
    @property
    def shorter(self) -> tuple[float, float, float, int] | None: ...

@final
class OutputFault:
    """One dwell whose output did not follow the sensor (``accelcal.DwellSet.faults``)."""

    @property
    def dwell(self) -> int:
        """Index of the dwell."""
    @property
    def axis(self) -> int | None:
        """The constant axis (0, 1, 2), or None when every axis is constant (frozen)."""
    @property
    def kind(
        self,
    ) -> Literal[
        "saturated_high",
        "saturated_low",
        "partly_saturated_high",
        "partly_saturated_low",
        "stuck",
        "frozen",
    ]:
        """What the fault is."""
    @property
    def value(self) -> float:
        """The dwell mean on that axis, input units (the constant value; x when frozen)."""
    @property
    def rail(self) -> float:
        """The value at which the axis saturates (NaN for stuck and frozen dwells)."""
    @property
    def typical_var(self) -> float:
        """The axis's typical dwell variance, squared input units."""

def dwell_output_faults(
    mean: NDArray[np.float64],
    var: NDArray[np.float64],
    count: NDArray[np.int64],
    lsb: tuple[float, float, float] | list[float] | None = None,
) -> list[OutputFault]:
    """Dwells with a saturated, stuck or frozen output (exactly constant axes), and those
    within reach of a rail that a saturated dwell has shown."""

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
        sigma_theta: float = 0.0,
        azimuth_covariance: NDArray[np.float64] | None = None,
        chi2_scale: float = 1.0,
        chi2_dof: float | None = None,
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
    @property
    def sigma_theta(self) -> float:
        """Std of the independent azimuth errors allowed for, deg."""
    @property
    def azimuth_covariance(self) -> NDArray[np.float64]:
        """The part of `covariance` from the azimuth errors."""
    @property
    def chi2_scale(self) -> float: ...
    @property
    def chi2_dof(self) -> float: ...

def startup_bias_raw(
    azimuth_deg: NDArray[np.float64],
    outputs: NDArray[np.float64],
    sigma: NDArray[np.float64] | None = None,
    t: NDArray[np.float64] | None = None,
    t_ref: float | None = None,
    sigma_theta_deg: float = 0.0,
) -> StartupBiasCore:
    """Start-up least squares from azimuths in degrees; sigma None: estimated;
    sigma_theta_deg the azimuth error std added to the covariance."""

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
        random_offset: bool | None = None,
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
    @property
    def random_offset(self) -> bool: ...

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
    def ambiguous(self) -> list[tuple[str, str, float, float]]: ...
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

def gap_distinct_poses(mean: NDArray[np.float64], tol: float) -> int:
    """Number of distinct poses among dwell means (k, 3): means closer than ``tol`` (raw
    units) count once."""

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
    resid_corr: NDArray[np.float64] | None = None,
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
    t: NDArray[np.float64] | None = None,
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
_StaticModel = Literal["lower", "diag", "upper"]
_StaticMethod = Literal["lm", "gauss-newton", "gn", "quadric", "linear-paper"]

@final
class Observability:
    """What the dwells can determine: SVD of the whitened Jacobian in comparable units
    (scale factors and misalignments relative, biases in units of g)."""

    def __new__(
        cls,
        singular_values: NDArray[np.float64],
        condition: float,
        std_comparable: NDArray[np.float64],
        weakest: NDArray[np.float64],
        weakest_std: float,
        degenerate: bool,
        weak: bool,
        combination: str,
    ) -> Observability: ...
    @property
    def singular_values(self) -> NDArray[np.float64]:
        """Singular values, descending."""
    @property
    def condition(self) -> float:
        """s_max / s_min."""
    @property
    def std_comparable(self) -> NDArray[np.float64]:
        """Predicted std of each parameter (comparable units)."""
    @property
    def weakest(self) -> NDArray[np.float64]:
        """Least determined combination (unit vector, comparable units)."""
    @property
    def weakest_std(self) -> float:
        """Predicted std of that combination (comparable units)."""
    @property
    def degenerate(self) -> bool:
        """Exactly or numerically undetermined."""
    @property
    def weak(self) -> bool:
        """Some parameter is weakly determined."""
    @property
    def combination(self) -> str:
        """The weakest combination in parameter names, e.g. "m2 + 0.94 m1"."""
    def __getnewargs__(self) -> tuple[Any, ...]: ...

@disjoint_base
class StaticFit:
    """One static fit; constructing it fits the (k, 3) dwell means to the reference gravity
    (the Python ``accelcal.StaticFit`` subclasses it; pickles as its inputs)."""

    def __new__(
        cls,
        means: NDArray[np.float64],
        g: float,
        model: _StaticModel = "lower",
        method: _StaticMethod = "lm",
        var: NDArray[np.float64] | float | None = None,
        start: list[float] | None = None,
        max_iter: int = ...,
        raise_degenerate: bool = True,
        degenerate_std: float = ...,
        weak_std: float = ...,
        check_g: bool = True,
        noise_model: str | None = None,
        input_units: str | None = None,
        nominal: Any = None,
        sigma_g: float | None = None,
    ) -> Self: ...
    @property
    def model(self) -> _StaticModel:
        """Sensor model."""
    @property
    def method(self) -> _StaticMethod:
        """Estimation method."""
    @property
    def g(self) -> float:
        """Reference gravity (units of the calibrated output)."""
    @property
    def means(self) -> NDArray[np.float64]:
        """Dwell means (k, 3), output units."""
    @property
    def var(self) -> NDArray[np.float64] | float | None:
        """Variance of each dwell mean per axis: one number, (k, 3), or None (estimated)."""
    @property
    def vector(self) -> NDArray[np.float64]:
        """Parameters [sx, sy, sz, bx, by, bz, m1, m2, m3] (p = 6 for diag)."""
    @property
    def start(self) -> NDArray[np.float64]:
        """Start of GN/LM (or the linear method's own solution)."""
    @property
    def start_source(self) -> Literal["quadric", "linear-paper", "user", "fallback"]:
        """Where the start came from."""
    @property
    def start_error(self) -> str | None:
        """Why the linear solution failed (when the start is the fallback)."""
    @property
    def _attention(self) -> int:
        """Bit 0: neither converged nor degenerate (an error); bit 1: weak or degenerate."""
    @property
    def user_start(self) -> list[float] | None:
        """The start given by the caller."""
    @property
    def covariance_unscaled(self) -> NDArray[np.float64]:
        """(J^T W J)^-1 (p, p); per unit output variance when the noise is estimated."""
    @property
    def sigma_g(self) -> float | None:
        """Std of the reference gravity (units of g), or None."""
    @property
    def covariance_gravity(self) -> NDArray[np.float64]:
        """sigma_g^2 (dp/dg) (dp/dg)^T (p, p), dp/dg = -p / g for the entries of K (zero
        without sigma_g)."""
    @property
    def residuals(self) -> NDArray[np.float64]:
        """|a_k| - g per dwell (units of g)."""
    @property
    def sigma_residual(self) -> NDArray[np.float64]:
        """Predicted std of each residual (units of g)."""
    @property
    def cost(self) -> float:
        """Minimised cost sum e_k^2."""
    @property
    def dof(self) -> int:
        """Degrees of freedom k - p."""
    @property
    def chi2_dof(self) -> float:
        """chi2/dof (known noise) or the estimated variance of a dwell mean per axis."""
    @property
    def chi2_p(self) -> float:
        """P(chi2(dof) >= chi2_dof * dof) under the noise model; NaN when it is estimated."""
    @property
    def iterations(self) -> int:
        """GN/LM iterations."""
    @property
    def converged(self) -> bool:
        """The minimum was reached (within 1e-3 parameter std)."""
    @property
    def decrement(self) -> float:
        """Squared distance in parameter std to the minimum of the local quadratic model."""
    @property
    def noise_known(self) -> bool:
        """The noise model was known (not estimated)."""
    @property
    def weak(self) -> bool:
        """Some parameter is weakly determined."""
    @property
    def degenerate(self) -> bool:
        """Some combination is undetermined."""
    @property
    def predicted_std_relative(self) -> NDArray[np.float64]:
        """Predicted std of each parameter in comparable units."""
    @property
    def weakest_std(self) -> float:
        """Predicted std of the least determined combination (comparable units)."""
    @property
    def max_iter(self) -> int:
        """Iteration limit used."""
    @property
    def raise_degenerate(self) -> bool:
        """A degenerate design raised."""
    @property
    def degenerate_std(self) -> float:
        """Threshold of degenerate (comparable units)."""
    @property
    def weak_std(self) -> float:
        """Threshold of weak (comparable units)."""
    @property
    def check_g(self) -> bool:
        """g was checked for plausibility."""
    @property
    def noise_model(self) -> str:
        """How the dwell weights were obtained."""
    @property
    def input_units(self) -> str:
        """Units of the raw output."""
    @property
    def nominal(self) -> Any:
        """Nominal model for the "before" norm statistics."""
    def observability(self) -> Observability:
        """Full observability report (SVD)."""
    def __getnewargs_ex__(self) -> tuple[tuple[Any, ...], dict[str, Any]]: ...

@final
class BatchFit:
    """Result of a batch of static fits, one row per session."""

    def __new__(
        cls,
        model: _StaticModel,
        params: NDArray[np.float64],
        std: NDArray[np.float64],
        chi2_dof: NDArray[np.float64],
        rms: NDArray[np.float64],
        iterations: NDArray[np.int64],
        n_dwells: NDArray[np.int64],
        status: NDArray[np.uint8],
        weak: NDArray[np.bool_],
        messages: list[str],
    ) -> BatchFit: ...
    @property
    def model(self) -> _StaticModel:
        """Sensor model."""
    @property
    def params(self) -> NDArray[np.float64]:
        """Parameters (B, p); NaN where the fit failed."""
    @property
    def std(self) -> NDArray[np.float64]:
        """Std of each parameter (B, p)."""
    @property
    def chi2_dof(self) -> NDArray[np.float64]:
        """chi2/dof, or the estimated variance of a dwell mean (B,)."""
    @property
    def rms(self) -> NDArray[np.float64]:
        """RMS of |a| - g (B,), units of g."""
    @property
    def iterations(self) -> NDArray[np.int64]:
        """GN/LM iterations (B,)."""
    @property
    def n_dwells(self) -> NDArray[np.int64]:
        """Dwells per session (B,)."""
    @property
    def status(self) -> NDArray[np.uint8]:
        """0 ok (weak included), 1 degenerate, 2 not converged, 3 invalid input (B,)."""
    @property
    def weak(self) -> NDArray[np.bool_]:
        """Some parameter weakly determined (B,)."""
    @property
    def messages(self) -> list[str]:
        """What went wrong per session ("" for ok and weak)."""
    @property
    def ok(self) -> NDArray[np.bool_]:
        """Sessions fitted (status 0)."""
    @property
    def state(self) -> list[Literal["ok", "weak", "degenerate", "error"]]:
        """Outcome per session."""
    @property
    def names(self) -> list[str]:
        """Parameter names of the columns."""
    def __len__(self) -> int: ...
    def __getnewargs__(self) -> tuple[Any, ...]: ...

@disjoint_base
class Prediction:
    """Cramer-Rao bound of a pose design (the Python ``accelcal.Prediction`` subclasses it)."""

    def __new__(
        cls,
        force: NDArray[np.float64],
        sigma: float,
        model: _StaticModel = "lower",
        *,
        g: float | None = None,
        truth: list[float] | None = None,
        sigma_g: float | None = None,
    ) -> Self: ...
    @property
    def model(self) -> _StaticModel:
        """Sensor model."""
    @property
    def force(self) -> NDArray[np.float64]:
        """Specific force at each pose (n, 3)."""
    @property
    def sigma(self) -> float:
        """Dwell-mean noise per axis (output units)."""
    @property
    def g(self) -> float:
        """Reference gravity."""
    @property
    def sigma_g(self) -> float | None:
        """Std of the reference gravity (units of g), or None; its term is in covariance."""
    @property
    def truth(self) -> NDArray[np.float64]:
        """Parameters at which the bound is evaluated."""
    @property
    def std(self) -> NDArray[np.float64]:
        """Std of each parameter (p,), output units."""
    @property
    def covariance(self) -> NDArray[np.float64]:
        """Covariance (p, p), output units."""
    @property
    def singular(self) -> bool:
        """Some combination is undetermined."""
    @property
    def condition(self) -> float:
        """Condition number of the comparable Jacobian."""
    @property
    def weakest(self) -> NDArray[np.float64]:
        """Least determined combination (comparable units)."""
    @property
    def combination(self) -> str:
        """That combination in parameter names."""
    def __getnewargs_ex__(self) -> tuple[tuple[Any, ...], dict[str, Any]]: ...

def static_fit_batch(
    means: NDArray[np.float64] | list[NDArray[np.float64]],
    g: float | list[float],
    *,
    model: _StaticModel = "lower",
    method: _StaticMethod = "lm",
    sigma: float | None = None,
    start: list[float] | None = None,
    max_iter: int = ...,
    degenerate_std: float = ...,
    weak_std: float = ...,
    mask: NDArray[np.bool_] | None = None,
    sigma_g: float | None = None,
) -> BatchFit:
    """Fit many sessions in parallel ((B, n, 3) with an optional mask, or a list)."""

def static_design_rows(
    force: NDArray[np.float64], truth: list[float], model: _StaticModel, sigma: float
) -> NDArray[np.float64]:
    """Fisher-information rows (n, p) of poses."""

def static_model_violation(k: list[list[float]], model: _StaticModel) -> tuple[int, int] | None:
    """K entries outside the model's pattern that are not zero."""

def chi2_sf(x: float, k: float) -> float:
    """Upper tail of the chi-square distribution with ``k`` degrees of freedom at ``x``."""

def f_sf(f: float, d1: float, d2: float) -> float:
    """Upper tail of the F distribution with ``d1``, ``d2`` degrees of freedom at ``f``."""

def gravity_problem(g: float) -> str | None:
    """Why ``g`` cannot be a local gravity in m/s^2, units of g or cm/s^2 (None if it can)."""

def apply_triad_raw(
    samples: NDArray[Any], k: list[list[float]], b: list[float]
) -> NDArray[np.float64]:
    """Calibrated specific force K^-1 (am - b) of an (N, 3) array."""


# ---- text reader ----------------------------------------------------------------------------
#: One output group: (column index, scale, is ISO-8601 time) per column.
_Groups = list[list[tuple[int, float, bool]]]
#: Rows left out because they did not parse: (count, line of the first, its fault), or None.
_BadRows = tuple[int, int, str] | None

@final
class TextBlocks:
    """Blocks of a text recording, read and parsed ahead on a background thread.

    Iterating yields ``(arrays, rows, bytes, repeats, skipped, bad)`` per block in file order,
    ``arrays`` holding one float64 array per column group ((m, k), or (m,) for one column);
    ``skipped`` counts rows left out by ``skip_empty_rows`` (their first group all empty);
    ``bad`` is ``(count, line, message)`` of the rows left out because they did not parse
    (the first one's line and fault), or None. More than 10 of those that are also more than
    1 % of the rows make the read fail at the end.
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
        sparse_groups: list[int] = ...,
        skip_empty_rows: bool = False,
    ) -> TextBlocks: ...
    def __iter__(self) -> TextBlocks: ...
    def __next__(
        self,
    ) -> tuple[list[NDArray[np.float64]], int, int, int, int, _BadRows]: ...

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
    sparse_groups: list[int] = ...,
    skip_empty_rows: bool = False,
) -> tuple[list[NDArray[np.float64]], int, int, int, int, _BadRows]:
    """Read a whole text recording into one array per column group: (arrays, rows, bytes,
    repeats, skipped, bad) (``bad`` as for :class:`TextBlocks`). A regular file is
    memory-mapped and parsed in parallel chunks straight into the arrays; any other source is
    read in blocks into arrays presized for ``rows_hint`` rows (an estimate: they grow past
    it). ``progress(rows, bytes)`` is called about every
    0.1 s and may raise to stop."""

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
    sparse_groups: list[int] = ...,
    skip_empty_rows: bool = False,
) -> tuple[list[NDArray[np.float64]], int, int, int]:
    """Parse at most ``max_rows`` data rows of ``data``: (arrays, rows, bytes, lines).

    In the groups listed in ``sparse_groups`` (of every text reader here) an empty field reads
    as NaN instead of being an error: a slow channel written on some rows only. With
    ``skip_empty_rows`` a row whose first-group fields are all empty is left out (a row of
    another sensor in a merged log); some of them empty is still an error."""

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
    "dwell_output_faults",
    "dwell_stats_raw",
    "dwell_step_log",
    "gravity_problem",
    "chi2_sf",
    "f_sf",
    "StepLog",
    "OutputFault",
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
    "gap_distinct_poses",
    "DemodulatedCore",
    "StartupBiasCore",
    "StartupPredictionCore",
    "demodulate_raw",
    "startup_bias_raw",
    "startup_predict_raw",
    "apply_triad_raw",
    "static_design_rows",
    "static_fit_batch",
    "static_model_violation",
    "BatchFit",
    "Observability",
    "Prediction",
    "StaticFit",
    "TextBlocks",
    "format_rows",
    "parse_iso8601",
    "text_parse_head",
    "text_read_all",
    "CalibrationError",
    "DegenerateDataError",
    "MIN_WINDOW_SAMPLES",
    "FAULT_MIN_SAMPLES",
    "SAME_POSE",
]
