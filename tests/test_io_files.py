"""File-reading fixes: rate metadata with units, rates that disagree, a time array in ms
in .npz, non-finite times, ``ts_ns``, ``fs`` as a 1-element array, a cut-off numeric last
line. Every test compares with the values written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from accelcal import CalibrationError
from accelcal.io import read_stream


def _acc(n: int = 400) -> np.ndarray:
    rng = np.random.default_rng(1)
    return rng.normal(0, 0.01, (n, 3)) + [0.1, -0.2, 9.8]


def _csv(path: Path, pre: str, a: np.ndarray, t: np.ndarray | None = None,
         tname: str = "t", end: str = "\n") -> Path:
    head = (f"{tname}," if t is not None else "") + "ax,ay,az"
    rows = [(f"{t[i]:.6f}," if t is not None else "") + ",".join(f"{v:.6f}" for v in r)
            for i, r in enumerate(a)]
    path.write_text(pre + head + "\n" + "\n".join(rows) + end)
    return path


@pytest.mark.parametrize(("meta", "fs"), [
    ("# Sample rate: 1 kHz\n", 1000.0),
    ("# fs = 0.1 kHz\n", 100.0),
    ("# Sample rate (Hz): 250\n", 250.0),
    ("ODR,100 Hz\n", 100.0),
    ("Sampling interval (s),0.01\n", 100.0),
    ("# period = 10 ms\n", 100.0),
    ("Abtastrate [Hz];100,0\n", 100.0),
    ("# Sample rate: 2 MHz\n", 2e6),
])
def test_rate_metadata_unit(tmp_path: Path, meta: str, fs: float) -> None:
    a = _acc()
    p = _csv(tmp_path / "m.csv", meta, a)
    s = read_stream(p)
    assert s.fs == pytest.approx(fs) and s.fs_source == "metadata"
    np.testing.assert_allclose(s.samples, a, atol=1e-6)


def test_rate_metadata_unit_not_understood(tmp_path: Path) -> None:
    p = _csv(tmp_path / "m.csv", "x\n# fs = 3 furlongs\n", _acc())
    with pytest.raises(CalibrationError, match=r"line 2 \('# fs = 3 furlongs'\).*'furlongs'"):
        read_stream(p)


def test_khz_metadata_agrees_with_time_column(tmp_path: Path) -> None:
    # "1 kHz" was read as 1 Hz and overrode the time column's 1000 Hz.
    a = _acc()
    t = np.arange(len(a)) / 1000.0
    s = read_stream(_csv(tmp_path / "k.csv", "# Sample rate: 1 kHz\n", a, t))
    assert s.fs == pytest.approx(1000.0) and s.fs_source == "metadata"
    assert not any("metadata says" in n for n in s.notes)
    np.testing.assert_allclose(s.t, t, atol=1e-9)


def test_metadata_and_time_column_disagree(tmp_path: Path) -> None:
    a = _acc()
    t = np.arange(len(a)) / 100.0
    p = _csv(tmp_path / "c.csv", "# Sample rate: 200 Hz\n", a, t)
    with pytest.raises(CalibrationError, match=r"line 1 .*200 Hz.*time column 't' read in s "
                       r"gives 100 Hz.*fs="):
        read_stream(p)
    assert read_stream(p, fs=100.0).fs == 100.0  # the rate given settles it
    # Within 5 %: the metadata, with a note, as before.
    p2 = _csv(tmp_path / "c2.csv", "# Sample rate: 103 Hz\n", a, t)
    s = read_stream(p2)
    assert s.fs == 103.0 and any("metadata says 103 Hz" in n for n in s.notes)


def test_npz_time_in_ms_hint_and_unit(tmp_path: Path) -> None:
    from accelcal.io import _Recording

    a = _acc(3000)
    t = np.arange(len(a)) * 10.0  # ms
    p = tmp_path / "ms.npz"
    np.savez(p, samples=a, t=t)
    rec = _Recording(str(p), None, None, None)
    assert rec.fs == pytest.approx(0.1)
    hint = rec.rate_hint()
    assert "time column 't' read in s" in hint and "ms (100 Hz)" in hint
    with pytest.raises(CalibrationError) as e:
        rec.dwell_accumulator()
    assert "ms (100 Hz)" in str(e.value) and "or more" not in str(e.value)
    # The hint's fix works: the container's time array named with its unit.
    s = read_stream(p, time_column="t [ms]")
    assert s.fs == pytest.approx(100.0)
    np.testing.assert_allclose(s.t, t / 1000.0)


def test_npz_fs_one_element_array(tmp_path: Path) -> None:
    a = _acc()
    for fs in (np.array([100.0]), np.array(100.0)):
        p = tmp_path / "fs.npz"
        np.savez(p, samples=a, fs=fs)
        s = read_stream(p)
        assert s.fs == 100.0 and s.fs_source == "metadata"
        np.testing.assert_array_equal(s.samples, a)


def test_nan_time_row_left_out(tmp_path: Path) -> None:
    from accelcal.io import iter_stream

    a = _acc()
    t = np.arange(len(a)) / 100.0
    p = _csv(tmp_path / "n.csv", "", a, t)
    lines = p.read_text().split("\n")
    lines[51] = "NaN," + lines[51].split(",", 1)[1]  # data row 50
    p.write_text("\n".join(lines))
    keep = np.ones(len(a), bool)
    keep[50] = False
    s = read_stream(p)
    np.testing.assert_allclose(s.samples, a[keep], atol=1e-6)
    np.testing.assert_allclose(s.t, t[keep], atol=1e-9)
    assert any("line 52: column 't' is 'NaN'" in n for n in s.notes)
    got = np.concatenate([c for c, _ in iter_stream(p, chunk_rows=64)])
    np.testing.assert_allclose(got, a[keep], atol=1e-6)


def test_ts_ns_is_the_time(tmp_path: Path) -> None:
    a = _acc()
    t = np.arange(len(a)) * 10_000_000  # ns, 100 Hz
    lines = ["ts_ns,ax,ay,az"] + [f"{t[i]}," + ",".join(f"{v:.6f}" for v in r)
                                  for i, r in enumerate(a)]
    p = tmp_path / "ts.csv"
    p.write_text("\n".join(lines) + "\n")
    s = read_stream(p)
    assert s.fs == pytest.approx(100.0) and s.fs_source == "time column"
    np.testing.assert_allclose(s.t, t * 1e-9)


def test_cut_off_numeric_last_line(tmp_path: Path) -> None:
    a = _acc()
    t = np.arange(len(a)) / 100.0
    p = _csv(tmp_path / "p.csv", "", a, t)
    text = p.read_text()
    p.write_text(text + "4.000000,0.100000,-0.200000,9.8")  # still being written
    s = read_stream(p)
    np.testing.assert_allclose(s.samples, a, atol=1e-6)
    assert any("line 402, the last" in n and "cut off" in n for n in s.notes)
    # A complete last line without its line end is kept.
    p.write_text(text + "4.000000,0.100000,-0.200000,9.800000")
    s = read_stream(p)
    assert s.samples.shape[0] == len(a) + 1 and not any("cut off" in n for n in s.notes)


# ---- time stamps other than ISO 8601 (a time of day, day-first and US dates) -----------------
def _stamped(path: Path, head: str, stamps: list[str], a: np.ndarray, sep: str = ",",
             dc: bool = False) -> Path:
    def num(v: float) -> str:
        return f"{v:.6f}".replace(".", ",") if dc else f"{v:.6f}"

    rows = [sep.join([s, *(num(v) for v in r)]) for s, r in zip(stamps, a, strict=True)]
    path.write_text(head + "\n" + "\n".join(rows) + "\n")
    return path


def _clock(n: int, fmt: str) -> tuple[list[str], np.ndarray]:
    """n stamps 10 ms apart from 1 March 2024 23:59:58 (across midnight), in ``fmt``."""
    import datetime as dt

    t0 = dt.datetime(2024, 3, 1, 23, 59, 58)
    when = [t0 + dt.timedelta(milliseconds=10 * i) for i in range(n)]
    out = []
    for w in when:
        ms = f"{w.microsecond // 1000:03d}"
        out.append(w.strftime(fmt).replace("MS", ms))
    return out, np.arange(n) * 0.01


@pytest.mark.parametrize(("head", "fmt", "sep", "dc", "said"), [
    ("time,ax,ay,az", "%H:%M:%S.MS", ",", False, "past midnight 1 time(s)"),
    ("Datum/Zeit;ax;ay;az", "%d.%m.%Y %H:%M:%S,MS", ";", True, "dates (day-first)"),
    ("Time,ax,ay,az", "%m/%d/%Y %I:%M:%S.MS %p", ",", False, "dates (month-first"),
    ("Time,ax,ay,az", "%d/%m/%Y %H:%M:%S.MS", ",", False, "dates (day-first"),
])
def test_clock_stamps_are_read_as_the_time(tmp_path: Path, head: str, fmt: str, sep: str,
                                           dc: bool, said: str) -> None:
    a = _acc()
    stamps, t = _clock(len(a), fmt)
    p = _stamped(tmp_path / "c.csv", head, stamps, a, sep, dc)
    s = read_stream(p)
    np.testing.assert_allclose(s.samples, a, atol=1e-6)
    np.testing.assert_allclose(s.t, t, atol=1e-9)
    assert s.fs == pytest.approx(100.0) and s.fs_source == "time column"
    assert s.t0 == stamps[0]
    assert any(said in n for n in s.notes), s.notes


def test_clock_stamps_ignored_with_time_column_none(tmp_path: Path) -> None:
    a = _acc()
    stamps, _ = _clock(len(a), "%d-%b-%Y %H:%M:%S.MS")  # 01-Mar-2024: not understood
    p = _stamped(tmp_path / "c.csv", "time,ax,ay,az", stamps, a)
    with pytest.raises(CalibrationError, match=r"column 'time' holds time stamps in a format "
                       r"not understood \('01-Mar-2024 23:59:58.000', data row 1\); give "
                       r"time_column='none', fs=RATE"):
        read_stream(p)
    s = read_stream(p, time_column="none", fs=100)
    np.testing.assert_allclose(s.samples, a, atol=1e-6)
    assert s.fs == 100.0 and s.fs_source == "given"


def test_ambiguous_dates_are_refused(tmp_path: Path) -> None:
    a = _acc(3)
    stamps = ["03/01/2024 10:00:00", "03/01/2024 10:00:01", "03/02/2024 10:00:01"]
    p = _stamped(tmp_path / "c.csv", "time,ax,ay,az", stamps, a)
    with pytest.raises(CalibrationError, match="read both day-first and month-first"):
        read_stream(p)
    s = read_stream(p, time_column="none", fs=1)
    np.testing.assert_allclose(s.samples, a, atol=1e-6)


def test_a_first_line_longer_than_the_head_is_said_so(tmp_path: Path) -> None:
    """One line longer than the 2 MB first block (or a CR-only file) was reported as
    'no numeric data rows (only blank lines)'."""
    one = tmp_path / "oneline.csv"
    one.write_text(",".join(["1.0"] * 800_000))  # 3.2 MB, no line end
    with pytest.raises(CalibrationError, match=r"no line end found in the first \d+ bytes"):
        read_stream(one, fs=100)
    cr = tmp_path / "cr.txt"
    cr.write_bytes(b"ax,ay,az\r" + b"0.1,0.2,9.8\r" * 250_000)  # 3 MB of CR-ended lines
    with pytest.raises(CalibrationError, match="carriage return alone") as e:
        read_stream(cr, fs=100)
    assert "blank lines" not in str(e.value)


def test_a_full_temporary_folder_is_named_when_expanding_gzip(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A full temporary folder while expanding a .gz blamed the input ('cannot decompress
    it')."""
    import errno
    import gzip
    import shutil
    import tempfile

    gz = tmp_path / "rec.csv.gz"
    with gzip.open(gz, "wt") as fh:
        fh.write("ax,ay,az\n" + "0.1,0.2,9.8\n" * 1000)

    def full(src: object, dst: object, length: int = 0) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(shutil, "copyfileobj", full)
    with pytest.raises(CalibrationError, match="temporary folder .* is full") as e:
        read_stream(gz, fs=100)
    assert tempfile.gettempdir() in str(e.value) and "TMPDIR" in str(e.value)


def test_hdf5_declaring_more_samples_than_it_holds_is_refused(tmp_path: Path) -> None:
    """A 1.5 KB HDF5 file declaring 2e9 samples (no chunk written: all fill value) was read
    through, the dwell statistics growing until the process aborted."""
    h5py = pytest.importorskip("h5py")
    chunked = tmp_path / "chunked.h5"
    with h5py.File(chunked, "w") as f:
        f.create_dataset("samples", shape=(200_000, 3), dtype="f8", chunks=(65536, 3),
                         fillvalue=9.81 / 3 ** 0.5)
    contiguous = tmp_path / "contiguous.h5"
    with h5py.File(contiguous, "w") as f:
        f.create_dataset("samples", shape=(200_000, 3), dtype="f8")
    for p in (chunked, contiguous):
        with pytest.raises(CalibrationError, match="declares .* but the file holds"):
            read_stream(p, fs=100)
    good = tmp_path / "good.h5"
    with h5py.File(good, "w") as f:
        f.create_dataset("samples", data=np.tile([0.0, 0.0, 9.81], (1000, 1)),
                         chunks=(256, 3))
    assert read_stream(good, fs=100).samples.shape == (1000, 3)
