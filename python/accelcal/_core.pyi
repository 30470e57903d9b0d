# Type stub of the compiled module (checked by `python -m mypy.stubtest accelcal._core`).
from typing import Any

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
