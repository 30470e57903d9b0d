"""Readers: the three real recordings as they are, generic text layouts, .npy/.npz, chunked
reading and streaming into the dwell accumulator."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from accelcal import CalibrationError, detect_dwells, dwell_stats
from accelcal.io import Stream, iter_stream, read_stream, stream_dwells
from conftest import shared_data

XSENS = partial(shared_data, 'xsens-mti', 'xsens_acc.txt')
MPU = partial(shared_data, 'mpu6050-10poses', 'example_data_calibration.csv')
IMUCAL = partial(shared_data, 'imucal', 'example_ferraris_session.csv')




def line_count(p: Path) -> int:
    return sum(1 for ln in p.read_text().splitlines() if ln.strip())


def test_xsens_whitespace_no_header() -> None:
    s = read_stream(XSENS())
    assert isinstance(s, Stream)
    assert s.samples.shape == (51175, 3) and s.samples.dtype == np.float64
    np.testing.assert_array_equal(s.samples[0], [33108.0, 33329.0, 36429.0])
    np.testing.assert_array_equal(s.samples[-1], np.loadtxt(XSENS())[-1, 1:])
    assert s.t is not None
    assert s.t[0] == pytest.approx(0.02984) and s.t[1] == pytest.approx(0.039857)
    assert s.fs == pytest.approx(100.0, rel=1e-3)  # from the time column
    assert s.temperature is None and len(s) == 51175


def test_mpu6050_metadata_then_header() -> None:
    s = read_stream(MPU())
    assert s.fs == 100.0  # from the `Fs,100` metadata line
    assert s.metadata["Logging Type"] == "0"
    assert s.metadata["Initialization time"] == "36.5"
    assert s.metadata["Waiting time"] == "3"
    assert s.names == ("ax", "ay", "az")
    assert s.samples.shape == (line_count(MPU()) - 5, 3)
    np.testing.assert_array_equal(s.samples[:2], [[-12, -812, 15032], [-208, -828, 14796]])
    assert s.t is not None
    np.testing.assert_allclose(s.t[:3], [0.0, 0.01, 0.02])


def test_imucal_picks_accelerometer_columns() -> None:
    s = read_stream(IMUCAL())
    assert s.names == ("acc_x", "acc_y", "acc_z")
    assert s.samples.shape == (line_count(IMUCAL()) - 1, 3)
    np.testing.assert_allclose(s.samples[0], [10.332114257812501, -0.5795947265625, 0.51732421875])
    assert s.fs is None and s.t is None  # 102.4 Hz is not in the file
    s2 = read_stream(IMUCAL(), fs=102.4)
    assert s2.fs == 102.4 and s2.t is not None and s2.t[1] == pytest.approx(1 / 102.4)
    g = read_stream(IMUCAL(), columns="gyr_x,gyr_y,gyr_z")
    np.testing.assert_allclose(g.samples[0], [-0.6103515625, -0.30517578125, 0.06103515625])
    np.testing.assert_array_equal(read_stream(IMUCAL(), columns=[4, 5, 6]).samples, s.samples)


@pytest.mark.parametrize(("data", "fs"), [(XSENS, None), (MPU, None), (IMUCAL, 102.4)])
def test_stream_dwells_equals_detect_dwells(data: Callable[[], Path], fs: float | None) -> None:
    path = data()
    s = read_stream(path, fs=fs)
    assert s.fs is not None
    one = detect_dwells(s.samples, s.fs, t=s.t, temperature=s.temperature)
    streamed = stream_dwells(path, fs=fs, chunk_rows=1234)
    assert len(streamed) == len(one) >= 6
    for name in ("mean", "var", "count", "start", "stop", "t", "threshold"):
        assert np.array_equal(getattr(streamed, name), getattr(one, name)), name
    assert streamed.fs == s.fs
    # Known bounds through the same streaming path.
    b = np.column_stack([one.start, one.stop])
    sb = stream_dwells(path, fs=fs, bounds=b, chunk_rows=999)
    ob = dwell_stats(s.samples, b, t=s.t, fs=s.fs)
    for name in ("mean", "var", "count", "t"):
        assert np.array_equal(getattr(sb, name), getattr(ob, name)), name


def test_iter_stream_chunks_concatenate_to_read_stream() -> None:
    s = read_stream(MPU())
    chunks = list(iter_stream(MPU(), chunk_rows=1000))
    assert all(c.shape[0] <= 1000 for c, _ in chunks) and len(chunks) == 11
    np.testing.assert_array_equal(np.concatenate([c for c, _ in chunks]), s.samples)
    np.testing.assert_array_equal(np.concatenate([t for _, t in chunks]), s.t)


# ---- generic text layouts ---------------------------------------------------------------------
def write(tmp_path: Path, text: str, name: str = "rec.csv") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_units_in_header_time_in_ms_and_temperature(tmp_path: Path) -> None:
    rows = "\n".join(f"{10 * i},{i},{2 * i},{3 * i},{20 + i / 10}" for i in range(50))
    p = write(
        tmp_path,
        "# device: test\n# sample_rate = 100 Hz\n"
        "time_ms,acc_x [m/s^2],acc_y [m/s^2],acc_z [m/s^2],temp_C\n" + rows + "\n",
    )
    s = read_stream(p)
    assert s.metadata["device"] == "test"
    assert s.fs == 100.0  # metadata wins over the time column
    np.testing.assert_allclose(s.t, np.arange(50) * 0.01)  # ms -> s
    np.testing.assert_array_equal(s.samples[:, 2], 3 * np.arange(50))
    assert s.temperature is not None
    np.testing.assert_allclose(s.temperature, 20 + np.arange(50) / 10)
    assert read_stream(p, fs=50.0).fs == 50.0  # explicit wins


def test_plain_xyz_and_time_by_name(tmp_path: Path) -> None:
    rows = "\n".join(f"{i / 200}\t{i}\t{-i}\t{i % 7}" for i in range(30))
    s = read_stream(write(tmp_path, "t[s]\tx\ty\tz\n" + rows + "\n", "rec.tsv"))
    assert s.names == ("x", "y", "z") and s.fs == pytest.approx(200.0)
    np.testing.assert_array_equal(s.samples[:, 1], -np.arange(30))


def test_three_columns_no_header_is_xyz(tmp_path: Path) -> None:
    s = read_stream(write(tmp_path, "1 2 3\n4 5 6\n7 8 9\n", "rec.txt"))
    np.testing.assert_array_equal(s.samples, [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    assert s.t is None and s.fs is None


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("", ["empty"]),
        ("\n\n", ["no numeric data"]),
        ("a,b,c\n", ["no numeric data"]),
        ("ax,ay,az\n1,2,3\n4,x,6\n", ["non-numeric"]),
        ("ax,ay,az\n1,2,3\n4,5\n", ["ragged"]),
        ("3,1,2,3,4\n4,5,6,7,8\n", ["columns="]),
        ("5,1,2,3\n4,5,6,7\n", ["columns="]),  # 4 columns, first not increasing
        ("gx,gy,gz\n1,2,3\n", ["no accelerometer columns"]),
        ("acc_x,acc_x,acc_y,acc_z\n1,2,3,4\n", ["columns="]),
    ],
)
def test_bad_text_files(tmp_path: Path, text: str, words: list[str]) -> None:
    p = write(tmp_path, text)
    with pytest.raises(CalibrationError) as ei:
        read_stream(p)
    msg = str(ei.value)
    assert str(p) in msg
    for w in words:
        assert w in msg


@pytest.mark.parametrize(
    ("kw", "words"),
    [
        ({"columns": ["ax", "ay"]}, ["exactly 3"]),
        ({"columns": ["ax", "ay", "nope"]}, ["no column named"]),
        ({"columns": [0, 1, 9]}, ["out of range"]),
        ({"fs": 0.0}, ["fs"]),
        ({"fs": float("nan")}, ["fs"]),
    ],
)
def test_bad_arguments(kw: dict[str, Any], words: list[str]) -> None:
    with pytest.raises(CalibrationError) as ei:
        read_stream(MPU(), **kw)
    for w in words:
        assert w in str(ei.value)


def test_missing_file_and_unknown_rate(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="not found"):
        read_stream(tmp_path / "nope.txt")
    with pytest.raises(CalibrationError, match="not found"):
        read_stream(tmp_path / "nope.npy")
    with pytest.raises(CalibrationError, match="fs="):
        stream_dwells(IMUCAL())
    with pytest.raises(CalibrationError, match="chunk_rows"):
        list(iter_stream(MPU(), chunk_rows=0))


# ---- numpy files ------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int16, np.int32])
def test_npy_round_trip_keeps_dtype(tmp_path: Path, dtype: Any) -> None:
    x = (np.random.default_rng(0).normal(size=(500, 3)) * 100).astype(dtype)
    p = tmp_path / "rec.npy"
    np.save(p, x)
    s = read_stream(p, fs=50.0)
    assert s.samples.dtype == dtype
    np.testing.assert_array_equal(s.samples, x)
    np.testing.assert_allclose(s.t, np.arange(500) / 50.0)
    chunks = [c for c, _ in iter_stream(p, chunk_rows=123)]
    np.testing.assert_array_equal(np.concatenate(chunks), x)


def test_npy_wide_needs_columns(tmp_path: Path) -> None:
    x = np.random.default_rng(1).normal(size=(100, 6))
    p = tmp_path / "wide.npy"
    np.save(p, x)
    with pytest.raises(CalibrationError, match="columns="):
        read_stream(p)
    np.testing.assert_array_equal(read_stream(p, columns=[3, 4, 5]).samples, x[:, 3:])
    # Four columns with an increasing first column: t, x, y, z.
    tx = np.column_stack([np.arange(100) / 10.0, x[:, :3]])
    np.save(p, tx)
    s = read_stream(p)
    np.testing.assert_array_equal(s.samples, x[:, :3])
    assert s.fs == pytest.approx(10.0)


def test_npz_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    x = rng.integers(-3000, 3000, size=(400, 3)).astype(np.int16)
    t = np.arange(400) / 200.0 + 3.0
    temp = np.linspace(20, 25, 400)
    p = tmp_path / "rec.npz"
    np.savez(p, acc=x, t=t, fs=200.0, temperature=temp, serial=np.array("ABC123"))
    s = read_stream(p)
    assert s.samples.dtype == np.int16
    np.testing.assert_array_equal(s.samples, x)
    np.testing.assert_array_equal(s.t, t)
    np.testing.assert_array_equal(s.temperature, temp)
    assert s.fs == 200.0 and s.metadata["serial"] == "ABC123"
    d = stream_dwells(p, bounds=[[0, 100], [150, 400]], chunk_rows=77)
    one = dwell_stats(x, [[0, 100], [150, 400]], t=t, temperature=temp)
    assert np.array_equal(d.var, one.var) and np.array_equal(d.temperature, one.temperature)
    np.savez(p, foo=x, bar=x)
    with pytest.raises(CalibrationError, match="samples"):
        read_stream(p)


def test_corrupt_numpy_files(tmp_path: Path) -> None:
    p = tmp_path / "bad.npy"
    p.write_bytes(b"not a numpy file at all")
    with pytest.raises(CalibrationError, match="bad.npy"):
        read_stream(p)
    np.save(p, np.zeros((0, 3)))
    with pytest.raises(CalibrationError, match="empty"):
        read_stream(p)
    np.save(p, np.zeros(5))
    with pytest.raises(CalibrationError, match="shape"):
        read_stream(p)
    q = tmp_path / "bad.npz"
    q.write_bytes(b"PK\x03\x04garbage")
    with pytest.raises(CalibrationError, match="bad.npz"):
        read_stream(q)


def test_hdf5_reader_finds_samples_time_and_temperature(tmp_path: Path) -> None:
    import h5py  # the optional 'hdf5' extra; `make test` installs it
    rng = np.random.default_rng(4)
    x = rng.normal(size=(900, 3))
    temp = np.linspace(20.0, 21.0, 900)
    path = tmp_path / "session.h5"
    with h5py.File(path, "w") as f:
        g = f.create_group("imu")
        g["acc"] = x
        g["temperature"] = temp
        f.attrs["fs"] = 300.0
    s = read_stream(path)
    assert np.array_equal(s.samples, x)
    assert s.fs == 300.0
    np.testing.assert_allclose(s.t, np.arange(900) / 300.0)
    np.testing.assert_array_equal(s.temperature, temp)
    d = stream_dwells(path, bounds=[[0, 450], [450, 900]], chunk_rows=100)
    np.testing.assert_allclose(d.mean, [x[:450].mean(0), x[450:].mean(0)], rtol=1e-12)
    np.testing.assert_allclose(d.temperature, [temp[:450].mean(), temp[450:].mean()])
    bad = tmp_path / "bad.h5"
    bad.write_text("not hdf5")
    with pytest.raises(CalibrationError, match="HDF5"):
        read_stream(bad)
