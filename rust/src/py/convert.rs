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
            "{what} must have shape (k, 3); got ({}, {})",
            a.shape()[0],
            a.shape()[1]
        )));
    }
    let b: &Bound<'_, numpy::PyArray2<f64>> = a;
    if !aligned(b) {
        // A view into a byte buffer at an odd offset: read each value unaligned (no slice or
        // ndarray view of misaligned memory may be formed).
        let st = b.strides();
        let base = numpy::PyArrayMethods::data(b) as *const u8;
        return Ok((0..a.shape()[0] as isize)
            .map(|i| {
                std::array::from_fn(|j| {
                    // SAFETY: (i, j) is inside the array, so the byte offset is inside its
                    // buffer; the read makes no alignment assumption.
                    unsafe {
                        std::ptr::read_unaligned(
                            base.offset(i * st[0] + j as isize * st[1]) as *const f64
                        )
                    }
                })
            })
            .collect());
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

/// A read-only 1-D array holding `v`.
pub fn frozen1<T: numpy::Element>(py: Python<'_>, v: Vec<T>) -> Py<numpy::PyArray1<T>> {
    use numpy::IntoPyArray;
    let a = v.into_pyarray(py);
    clear_writeable(&a);
    a.unbind()
}

/// Clear the WRITEABLE flag of an array this module has just made (what numpy's
/// `PyReadwriteArray::make_nonwriteable` does, without its borrow bookkeeping: nothing else
/// can hold a borrow of a fresh array).
fn clear_writeable<T: numpy::Element, D: ndarray::Dimension>(a: &Bound<'_, numpy::PyArray<T, D>>) {
    use numpy::PyUntypedArrayMethods;
    // SAFETY: `a` is a live array created by the caller and not yet shared with anyone.
    unsafe {
        (*numpy::npyffi::_PyArray_GET_ITEM_DATA(a.as_array_ptr())).flags &=
            !numpy::npyffi::NPY_ARRAY_WRITEABLE;
    }
}

/// A read-only `(rows, cols)` array from row-major values (`v.len()` must be `rows * cols`;
/// otherwise an empty `(0, cols)` array, which callers never produce).
pub fn frozen2<T: numpy::Element>(
    py: Python<'_>,
    v: Vec<T>,
    rows: usize,
    cols: usize,
) -> Py<numpy::PyArray2<T>> {
    use numpy::IntoPyArray;
    let arr = ndarray::Array2::from_shape_vec((rows, cols), v).unwrap_or_else(|_| {
        ndarray::Array2::from_shape_vec((0, cols), Vec::new()).expect("an empty array")
    });
    let a = arr.into_pyarray(py);
    clear_writeable(&a);
    a.unbind()
}

/// The array's data are aligned for `T` (numpy's ALIGNED flag).
fn aligned<T: numpy::Element, D: ndarray::Dimension>(a: &Bound<'_, numpy::PyArray<T, D>>) -> bool {
    // SAFETY: reads the flags word of a live array object (no write, no borrow).
    let flags = unsafe { (*numpy::npyffi::_PyArray_GET_ITEM_DATA(a.as_array_ptr())).flags };
    flags & numpy::npyffi::NPY_ARRAY_ALIGNED != 0
}

fn writeable<T: numpy::Element, D: ndarray::Dimension>(
    a: &Bound<'_, numpy::PyArray<T, D>>,
) -> bool {
    use numpy::PyUntypedArrayMethods;
    // SAFETY: reads the flags word of a live array object (no write, no borrow).
    let flags = unsafe { (*numpy::npyffi::_PyArray_GET_ITEM_DATA(a.as_array_ptr())).flags };
    flags & numpy::npyffi::NPY_ARRAY_WRITEABLE != 0
}

/// A 1-D array argument of a result's constructor: shared when already read-only (another
/// result's field: no copy), else a read-only copy (unpickling).
pub fn frozen_copy1<T: numpy::Element + Copy>(
    a: &PyReadonlyArray1<'_, T>,
) -> Py<numpy::PyArray1<T>> {
    let b: &Bound<'_, numpy::PyArray1<T>> = a;
    if !writeable(b) {
        return b.clone().unbind();
    }
    frozen1(a.py(), a.as_array().to_vec())
}

/// [`frozen_copy1`] for a 2-D float64 argument.
pub fn frozen_copy2(a: &PyReadonlyArray2<'_, f64>) -> Py<numpy::PyArray2<f64>> {
    let b: &Bound<'_, numpy::PyArray2<f64>> = a;
    if !writeable(b) {
        return b.clone().unbind();
    }
    let (r, c) = (a.shape()[0], a.shape()[1]);
    frozen2(a.py(), a.as_array().iter().copied().collect(), r, c)
}

/// A contiguous copy of a 1-D float64 argument in logical order (any strides or layout).
pub fn vec1(a: &PyReadonlyArray1<'_, f64>) -> Vec<f64> {
    match a.as_slice() {
        Ok(s) => s.to_vec(),
        Err(_) => a.as_array().to_vec(),
    }
}

/// A 1-D float64 argument as a slice: borrowed when contiguous (zero copy), else a copy in
/// logical order.
pub fn cow1<'a>(a: &'a PyReadonlyArray1<'_, f64>) -> std::borrow::Cow<'a, [f64]> {
    match a.as_slice() {
        Ok(s) => std::borrow::Cow::Borrowed(s),
        Err(_) => std::borrow::Cow::Owned(a.as_array().to_vec()),
    }
}
