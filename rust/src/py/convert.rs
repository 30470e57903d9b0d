//! Conversions between NumPy arrays and core types.

use numpy::{PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;

use super::CalibrationError;

/// A `(N, 3)` sample array of one of the dtypes the kernels accept (zero copy, any strides).
pub enum SampleArray<'py> {
    F64(PyReadonlyArray2<'py, f64>),
    F32(PyReadonlyArray2<'py, f32>),
    I16(PyReadonlyArray2<'py, i16>),
    I32(PyReadonlyArray2<'py, i32>),
}

impl<'py> SampleArray<'py> {
    pub fn extract(obj: &Bound<'py, PyAny>) -> PyResult<Self> {
        if let Ok(a) = obj.extract::<PyReadonlyArray2<'py, f64>>() {
            return Ok(SampleArray::F64(a));
        }
        if let Ok(a) = obj.extract::<PyReadonlyArray2<'py, f32>>() {
            return Ok(SampleArray::F32(a));
        }
        if let Ok(a) = obj.extract::<PyReadonlyArray2<'py, i16>>() {
            return Ok(SampleArray::I16(a));
        }
        if let Ok(a) = obj.extract::<PyReadonlyArray2<'py, i32>>() {
            return Ok(SampleArray::I32(a));
        }
        Err(CalibrationError::new_err(
            "samples must be a 2-D NumPy array of float64, float32, int16 or int32",
        ))
    }
}

/// Run `$body` with `$v` bound to the `ArrayView2` of whichever dtype `$arr` holds.
macro_rules! with_view {
    ($arr:expr, $v:ident => $body:expr) => {
        match $arr {
            $crate::py::convert::SampleArray::F64(a) => {
                let $v = a.as_array();
                $body
            }
            $crate::py::convert::SampleArray::F32(a) => {
                let $v = a.as_array();
                $body
            }
            $crate::py::convert::SampleArray::I16(a) => {
                let $v = a.as_array();
                $body
            }
            $crate::py::convert::SampleArray::I32(a) => {
                let $v = a.as_array();
                $body
            }
        }
    };
}
pub(crate) use with_view;

/// `(k, 2)` int64 bounds to `[start, stop)` pairs.
pub fn bounds_from(b: &PyReadonlyArray2<'_, i64>) -> PyResult<Vec<[usize; 2]>> {
    if b.shape()[1] != 2 {
        return Err(CalibrationError::new_err(format!(
            "bounds must have shape (k, 2) [start, stop); got {:?}",
            b.shape()
        )));
    }
    let v = b.as_array();
    v.rows()
        .into_iter()
        .enumerate()
        .map(|(k, r)| {
            if r[0] < 0 || r[1] < 0 {
                Err(CalibrationError::new_err(format!(
                    "dwell {k}: negative bound [{}, {})",
                    r[0], r[1]
                )))
            } else {
                Ok([r[0] as usize, r[1] as usize])
            }
        })
        .collect()
}

/// An optional contiguous 1-D float64 channel as a slice (zero copy).
pub fn opt_slice<'a>(
    x: &'a Option<PyReadonlyArray1<'_, f64>>,
    what: &str,
) -> PyResult<Option<&'a [f64]>> {
    match x {
        None => Ok(None),
        Some(a) => a.as_slice().map(Some).map_err(|_| {
            CalibrationError::new_err(format!("{what} must be a contiguous 1-D float64 array"))
        }),
    }
}

/// `(k, 3)` float64 rows as fixed-size triples (one pass; no per-row views when contiguous).
pub fn rows3(a: &PyReadonlyArray2<'_, f64>, what: &str) -> PyResult<Vec<[f64; 3]>> {
    if a.shape()[1] != 3 {
        return Err(CalibrationError::new_err(format!(
            "{what} must have shape (k, 3); got {:?}",
            a.shape()
        )));
    }
    // `as_slice` also succeeds on Fortran-ordered arrays (any contiguous memory): only a
    // C-contiguous array may be read as consecutive rows.
    if a.is_c_contiguous() {
        if let Ok(flat) = a.as_slice() {
            return Ok(flat.chunks_exact(3).map(|r| [r[0], r[1], r[2]]).collect());
        }
    }
    Ok(a.as_array()
        .rows()
        .into_iter()
        .map(|r| [r[0], r[1], r[2]])
        .collect())
}
