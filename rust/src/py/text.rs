//! Bindings of the text reader: a block iterator, a whole-file read, the head parser, the
//! ISO-8601 parser and the row formatter.

use numpy::{IntoPyArray, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyList, PyTuple};
use std::io::{Read, Seek, SeekFrom};
use std::sync::Mutex;
use std::time::Duration;

use super::dwell::guarded;
use super::CalibrationError;
use crate::text::{
    read_all_with, BadRows, Block, Collected, Column, ColumnKind, Delimiter, MappedText, Next,
    Progress, Source, StreamOptions, TextLayout, TextStream,
};

/// How often a waiting call looks for Ctrl-C.
const POLL: Duration = Duration::from_millis(100);

#[allow(clippy::too_many_arguments)]
fn layout_from(
    delimiter: Option<&str>,
    ncols: usize,
    groups: Vec<Vec<(usize, f64, bool)>>,
    decimal_comma: bool,
    comment: &str,
    names: Option<Vec<String>>,
    first_line: u64,
    t0: Option<(i64, i64)>,
    sparse_groups: Vec<usize>,
    skip_empty_rows: bool,
) -> PyResult<TextLayout> {
    let one_byte = |s: &str, what: &str| -> PyResult<u8> {
        match s.as_bytes() {
            [b] if b.is_ascii() => Ok(*b),
            _ => Err(CalibrationError::new_err(format!(
                "{what} must be a single ASCII character; got {s:?}"
            ))),
        }
    };
    let delimiter = match delimiter {
        None => Delimiter::Whitespace,
        Some(d) => Delimiter::Byte(one_byte(d, "delimiter")?),
    };
    // An empty string: no comment lines.
    let comment = if comment.is_empty() {
        None
    } else {
        Some(one_byte(comment, "comment")?)
    };
    let groups = groups
        .into_iter()
        .map(|g| {
            g.into_iter()
                .map(|(index, scale, iso)| {
                    let kind = if iso {
                        let (t0_s, t0_ns) = t0.ok_or_else(|| {
                            CalibrationError::new_err("an ISO-8601 time column needs t0")
                        })?;
                        ColumnKind::Iso8601 { t0_s, t0_ns }
                    } else {
                        ColumnKind::Number { scale }
                    };
                    Ok(Column { index, kind })
                })
                .collect::<PyResult<Vec<Column>>>()
        })
        .collect::<PyResult<Vec<Vec<Column>>>>()?;
    let layout = TextLayout {
        delimiter,
        ncols,
        groups,
        decimal_comma,
        comment,
        names,
        first_line,
        sparse_groups,
        skip_empty_rows,
    };
    layout.validate()?;
    Ok(layout)
}

fn open_source(
    path: Option<&str>,
    offset: u64,
    prefix: Option<Vec<u8>>,
    stdin: bool,
) -> PyResult<Source> {
    let head = prefix.unwrap_or_default();
    match path {
        Some(p) => {
            let mut f = std::fs::File::open(p)
                .map_err(|e| CalibrationError::new_err(format!("{p}: cannot open ({e})")))?;
            // A regular file is mapped (no copy); ACCELCAL_MMAP=0 reads it instead, e.g. for
            // a file that another program may truncate while it is read (see MappedText).
            if std::env::var_os("ACCELCAL_MMAP").is_none_or(|v| v != "0") {
                if let Ok(Some(m)) = MappedText::open(&f, offset) {
                    return Ok(Source::Map(m));
                }
            }
            f.seek(SeekFrom::Start(offset))
                .map_err(|e| CalibrationError::new_err(format!("{p}: cannot seek ({e})")))?;
            Ok(Source::Reader(Box::new(f)))
        }
        None => {
            let start = usize::try_from(offset)
                .unwrap_or(usize::MAX)
                .min(head.len());
            let cur = std::io::Cursor::new(head[start..].to_vec());
            if stdin {
                Ok(Source::Reader(Box::new(cur.chain(std::io::stdin()))))
            } else {
                Ok(Source::Reader(Box::new(cur)))
            }
        }
    }
}

/// A block's groups as NumPy arrays: (m, k) for groups of k > 1 columns, (m,) for one.
fn groups_to_py<'py>(
    py: Python<'py>,
    values: Vec<Vec<f64>>,
    rows: usize,
    widths: &[usize],
) -> PyResult<Bound<'py, PyList>> {
    let out = PyList::empty(py);
    for (v, &k) in values.into_iter().zip(widths) {
        if k == 1 {
            out.append(v.into_pyarray(py))?;
        } else {
            let a = ndarray::Array2::from_shape_vec((rows, k), v)
                .map_err(|e| CalibrationError::new_err(e.to_string()))?;
            out.append(a.into_pyarray(py))?;
        }
    }
    Ok(out)
}

fn widths(layout: &TextLayout) -> Vec<usize> {
    layout.groups.iter().map(Vec::len).collect()
}

fn block_to_py<'py>(py: Python<'py>, b: Block, widths: &[usize]) -> PyResult<Bound<'py, PyTuple>> {
    let arrays = groups_to_py(py, b.values, b.rows, widths)?;
    PyTuple::new(
        py,
        [
            arrays.into_any(),
            b.rows.into_pyobject(py)?.into_any(),
            b.bytes.into_pyobject(py)?.into_any(),
            b.repeats.into_pyobject(py)?.into_any(),
            b.skipped.into_pyobject(py)?.into_any(),
            bad_to_py(py, &b.bad)?,
        ],
    )
}

/// Rows left out because they did not parse: ``(count, line, message)`` of the first, or
/// None.
fn bad_to_py<'py>(py: Python<'py>, bad: &BadRows) -> PyResult<Bound<'py, PyAny>> {
    match &bad.first {
        Some((line, msg)) if bad.count > 0 => Ok((bad.count, *line, msg.as_str())
            .into_pyobject(py)?
            .into_any()),
        _ => Ok(py.None().into_bound(py)),
    }
}

/// Blocks of a text recording, read and parsed ahead on a background thread.
///
/// Iterating yields ``(arrays, rows, bytes, repeats, skipped, bad)`` per block in file order,
/// ``arrays`` holding one float64 array per column group, ``bad`` the rows that did not parse
/// and were left out (``(count, line, message)`` of the first) or None.
#[pyclass(name = "TextBlocks", module = "accelcal._core", frozen)]
pub struct TextBlocks {
    inner: Mutex<TextStream>,
    widths: Vec<usize>,
}

#[pymethods]
impl TextBlocks {
    #[new]
    #[pyo3(signature = (path, offset, ncols, groups, *, delimiter=None, decimal_comma=false, comment="#", names=None, first_line=1, t0=None, prefix=None, stdin=false, block_bytes=4194304, sparse_groups=Vec::new(), skip_empty_rows=false))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        path: Option<&str>,
        offset: u64,
        ncols: usize,
        groups: Vec<Vec<(usize, f64, bool)>>,
        delimiter: Option<&str>,
        decimal_comma: bool,
        comment: &str,
        names: Option<Vec<String>>,
        first_line: u64,
        t0: Option<(i64, i64)>,
        prefix: Option<Vec<u8>>,
        stdin: bool,
        block_bytes: usize,
        sparse_groups: Vec<usize>,
        skip_empty_rows: bool,
    ) -> PyResult<Self> {
        let layout = layout_from(
            delimiter,
            ncols,
            groups,
            decimal_comma,
            comment,
            names,
            first_line,
            t0,
            sparse_groups,
            skip_empty_rows,
        )?;
        let src = open_source(path, offset, prefix, stdin)?;
        let opts = StreamOptions {
            block_bytes,
            parallel: 0,
        };
        let widths = widths(&layout);
        Ok(TextBlocks {
            inner: Mutex::new(TextStream::new(src, layout, opts)?),
            widths,
        })
    }

    fn __iter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }

    fn __next__<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyTuple>>> {
        loop {
            // The lock is taken only with the interpreter released (no GIL/lock inversion).
            let next = py.detach(|| -> PyResult<crate::Result<Next>> {
                let mut g = self.inner.lock().map_err(|_| {
                    CalibrationError::new_err("text reader poisoned by an earlier error")
                })?;
                Ok(g.next_block(POLL))
            })??;
            match next {
                Next::Block(b) => return Ok(Some(block_to_py(py, b, &self.widths)?)),
                Next::Done => return Ok(None),
                Next::Pending => py.check_signals()?,
            }
        }
    }
}

/// Read a whole text recording (blocks parsed in parallel) into one array per column group.
///
/// ``progress(rows, bytes)`` is called about every 0.1 s while reading (it may raise to
/// stop); Ctrl-C stops the read. Returns ``(arrays, rows, bytes, repeats, skipped, bad)``.
#[pyfunction]
#[pyo3(signature = (path, offset, ncols, groups, *, delimiter=None, decimal_comma=false, comment="#", names=None, first_line=1, t0=None, prefix=None, stdin=false, block_bytes=4194304, rows_hint=0, progress=None, sparse_groups=Vec::new(), skip_empty_rows=false))]
#[allow(clippy::too_many_arguments)]
pub fn text_read_all<'py>(
    py: Python<'py>,
    path: Option<&str>,
    offset: u64,
    ncols: usize,
    groups: Vec<Vec<(usize, f64, bool)>>,
    delimiter: Option<&str>,
    decimal_comma: bool,
    comment: &str,
    names: Option<Vec<String>>,
    first_line: u64,
    t0: Option<(i64, i64)>,
    prefix: Option<Vec<u8>>,
    stdin: bool,
    block_bytes: usize,
    rows_hint: usize,
    progress: Option<Bound<'py, PyAny>>,
    sparse_groups: Vec<usize>,
    skip_empty_rows: bool,
) -> PyResult<Bound<'py, PyTuple>> {
    let layout = layout_from(
        delimiter,
        ncols,
        groups,
        decimal_comma,
        comment,
        names,
        first_line,
        t0,
        sparse_groups,
        skip_empty_rows,
    )?;
    let src = open_source(path, offset, prefix, stdin)?;
    let opts = StreamOptions {
        block_bytes,
        parallel: 0,
    };
    let w = widths(&layout);
    let cb = progress.map(Bound::unbind);
    let shared = Progress::default();
    // The read runs on its own thread (and the rayon pool); this one reports progress and
    // watches for Ctrl-C, with the interpreter released in between.
    let collected = py.detach(|| -> PyResult<Collected> {
        std::thread::scope(|s| {
            let (tx, rx) = std::sync::mpsc::channel();
            let p = &shared;
            s.spawn(move || {
                let r = guarded("text_read_all", || {
                    read_all_with(src, layout, opts, rows_hint, p)
                });
                let _ = tx.send(r);
            });
            loop {
                match rx.recv_timeout(POLL) {
                    Ok(r) => return r,
                    Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
                    Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
                        return Err(CalibrationError::new_err(
                            "the text reader stopped unexpectedly",
                        ))
                    }
                }
                let polled = Python::attach(|py| -> PyResult<()> {
                    py.check_signals()?;
                    if let Some(f) = &cb {
                        let rows = shared.rows.load(std::sync::atomic::Ordering::Relaxed);
                        let bytes = shared.bytes.load(std::sync::atomic::Ordering::Relaxed);
                        f.call1(py, (rows, bytes))?;
                    }
                    Ok(())
                });
                if let Err(e) = polled {
                    // Stop the reader and wait for it (it checks between chunks).
                    shared
                        .stop
                        .store(true, std::sync::atomic::Ordering::Relaxed);
                    let _ = rx.recv();
                    return Err(e);
                }
            }
        })
    })?;
    if let Some(f) = &cb {
        f.call1(py, (collected.rows, collected.bytes))?;
    }
    let arrays = groups_to_py(py, collected.values, collected.rows, &w)?;
    PyTuple::new(
        py,
        [
            arrays.into_any(),
            collected.rows.into_pyobject(py)?.into_any(),
            collected.bytes.into_pyobject(py)?.into_any(),
            collected.repeats.into_pyobject(py)?.into_any(),
            collected.skipped.into_pyobject(py)?.into_any(),
            bad_to_py(py, &collected.bad)?,
        ],
    )
}

/// Parse at most ``max_rows`` data rows of ``data`` (the first lines of a file).
///
/// Returns ``(arrays, rows, bytes, lines)``.
#[pyfunction]
#[pyo3(signature = (data, ncols, groups, *, delimiter=None, decimal_comma=false, comment="#", names=None, first_line=1, t0=None, max_rows=None, sparse_groups=Vec::new(), skip_empty_rows=false))]
#[allow(clippy::too_many_arguments)]
pub fn text_parse_head<'py>(
    py: Python<'py>,
    data: &[u8],
    ncols: usize,
    groups: Vec<Vec<(usize, f64, bool)>>,
    delimiter: Option<&str>,
    decimal_comma: bool,
    comment: &str,
    names: Option<Vec<String>>,
    first_line: u64,
    t0: Option<(i64, i64)>,
    max_rows: Option<usize>,
    sparse_groups: Vec<usize>,
    skip_empty_rows: bool,
) -> PyResult<Bound<'py, PyTuple>> {
    let layout = layout_from(
        delimiter,
        ncols,
        groups,
        decimal_comma,
        comment,
        names,
        first_line,
        t0,
        sparse_groups,
        skip_empty_rows,
    )?;
    let w = widths(&layout);
    let b = py.detach(|| crate::text::parse_block(data, &layout, max_rows))?;
    let lines = b.lines;
    let (rows, bytes) = (b.rows, b.bytes);
    let arrays = groups_to_py(py, b.values, rows, &w)?;
    PyTuple::new(
        py,
        [
            arrays.into_any(),
            rows.into_pyobject(py)?.into_any(),
            bytes.into_pyobject(py)?.into_any(),
            lines.into_pyobject(py)?.into_any(),
        ],
    )
}

/// ``(seconds, nanoseconds)`` since 1970-01-01T00:00:00Z of an ISO-8601 date and time
/// (no offset: UTC), or None when the text is not one.
#[pyfunction]
pub fn parse_iso8601(text: &str) -> Option<(i64, i64)> {
    crate::text::parse_iso8601(text.as_bytes())
}

/// Rows as delimited text (bytes): ``lead`` (m,) first when given, then the (m, k) ``values``;
/// shortest round-trip float formatting.
#[pyfunction]
#[pyo3(signature = (values, lead=None, delimiter=","))]
pub fn format_rows<'py>(
    py: Python<'py>,
    values: PyReadonlyArray2<'py, f64>,
    lead: Option<PyReadonlyArray1<'py, f64>>,
    delimiter: &str,
) -> PyResult<Bound<'py, PyBytes>> {
    let d = match delimiter.as_bytes() {
        [b] if b.is_ascii() => *b,
        _ => {
            return Err(CalibrationError::new_err(format!(
                "delimiter must be a single ASCII character; got {delimiter:?}"
            )))
        }
    };
    let k = values.shape()[1];
    let owned;
    let flat: &[f64] = if values.is_c_contiguous() {
        values.as_slice()?
    } else {
        owned = values.as_array().iter().copied().collect::<Vec<f64>>();
        &owned
    };
    let lead_owned;
    let lead_slice: Option<&[f64]> = match &lead {
        None => None,
        Some(l) => match l.as_slice() {
            Ok(s) => Some(s),
            Err(_) => {
                lead_owned = l.as_array().to_vec();
                Some(&lead_owned)
            }
        },
    };
    let bytes = py.detach(|| crate::text::format_rows(lead_slice, flat, k, d))?;
    Ok(PyBytes::new(py, &bytes))
}
