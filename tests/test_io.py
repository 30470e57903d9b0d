"""Readers: the three real recordings as they are, generic text layouts, .npy/.npz, chunked
reading and streaming into the dwell accumulator."""

from __future__ import annotations

import json
import re
import sys
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import accelcal as ac
import numpy as np
import pytest
from accelcal import CalibrationError, detect_dwells, dwell_stats
from accelcal.io import Stream, iter_stream, read_stream, stream_dwells
from conftest import shared_data, write_csv

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
        ("ax,ay,az\n1,2,3\n4,x,6\n", ["line 3", 'column "ay"', "not a number"]),
        ("ax,ay,az\n1,2,3\n4,5\n", ["line 3", "2 fields where the data rows have 3"]),
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


# ---- the Rust text reader against numpy.loadtxt / pandas.read_csv ------------------------------
def _table(n: int, seed: int) -> np.ndarray:
    """(n, 5) rows t, ax, ay, az, temp with values that stress float parsing."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 250.0
    a = rng.normal(0.0, 1.0, (n, 3)) * [1e-3, 3.0, 9.81] + [0.0, -1.5e-7, 1e4]
    temp = 20.0 + rng.random(n)
    return np.column_stack([t, a, temp])


def _fmt(x: np.ndarray) -> list[list[str]]:
    return [[repr(float(v)) for v in row] for row in x]


@pytest.mark.parametrize("delim", [",", ";", "\t", " ", ", "])
@pytest.mark.parametrize("eol", ["\n", "\r\n"])
@pytest.mark.parametrize("trailing_newline", [True, False])
def test_text_parity_with_loadtxt(
    tmp_path: Path, delim: str, eol: str, trailing_newline: bool
) -> None:
    x = _table(3000, 1)
    lines = ["# exported by a logger", "Fs, 250", "# a comment before the header",
             delim.join(["t", "ax", "ay", "az", "temp_C"])]
    rows = [delim.join(r) for r in _fmt(x)]
    rows.insert(1000, "# a comment among the data")
    rows.insert(2000, "")
    text = eol.join(lines + rows) + (eol if trailing_newline else "")
    p = tmp_path / "rec.csv"
    p.write_bytes(text.encode())
    s = read_stream(p)
    ref = np.loadtxt(p, delimiter=None if delim.strip() in ("", "\t") else delim.strip(),
                     skiprows=4,
                     comments="#")
    np.testing.assert_array_equal(ref, x)  # the reference itself reads what was written
    np.testing.assert_array_equal(s.samples, ref[:, 1:4])
    np.testing.assert_array_equal(s.t, ref[:, 0])
    np.testing.assert_array_equal(s.temperature, ref[:, 4])
    assert s.fs == 250.0 and s.fs_source == "metadata" and s.names == ("ax", "ay", "az")
    chunks = list(iter_stream(p, chunk_rows=701))
    assert [c.shape[0] for c, _ in chunks] == [701] * 4 + [3000 - 4 * 701]
    np.testing.assert_array_equal(np.concatenate([c for c, _ in chunks]), ref[:, 1:4])


def test_text_parity_with_pandas_on_a_file_larger_than_the_head(tmp_path: Path) -> None:
    import pandas as pd

    x = _table(120_000, 2)  # about 8 MB: read in several blocks, past the sniffed head
    p = tmp_path / "big.csv"
    pd.DataFrame(x, columns=["time_ms", "acc_x", "acc_y", "acc_z", "temperature"]).to_csv(
        p, index=False, float_format="%.17g")
    assert p.stat().st_size > 3 * (1 << 21)
    ref = pd.read_csv(p, engine="c")
    s = read_stream(p)
    np.testing.assert_array_equal(s.samples, ref[["acc_x", "acc_y", "acc_z"]].to_numpy())
    np.testing.assert_array_equal(s.t, ref["time_ms"].to_numpy() * 1e-3)
    np.testing.assert_array_equal(s.temperature, ref["temperature"].to_numpy())
    assert s.fs == pytest.approx(250_000.0)  # time in ms: 1/250 ms apart
    got = np.concatenate([c for c, _ in iter_stream(p, chunk_rows=50_000)])
    np.testing.assert_array_equal(got, s.samples)


def test_iso_timestamps_match_pandas(tmp_path: Path) -> None:
    import pandas as pd

    n = 2500
    base = pd.Timestamp("2024-02-29T23:59:58.5", tz="UTC")
    ts = base + pd.to_timedelta(np.arange(n) * 2_500_000, unit="ns")  # 400 Hz
    x = _table(n, 3)[:, 1:4]
    p = tmp_path / "iso.csv"
    with open(p, "w") as f:
        f.write("timestamp,ax,ay,az\n")
        for i in range(n):
            stamp = ts[i].strftime("%Y-%m-%dT%H:%M:%S.%f") + ("Z" if i % 2 else "+00:00")
            f.write(stamp + "," + ",".join(repr(float(v)) for v in x[i]) + "\n")
    s = read_stream(p)
    ref = pd.read_csv(p, parse_dates=["timestamp"])
    want = (ref["timestamp"] - ref["timestamp"][0]).dt.total_seconds().to_numpy()
    np.testing.assert_allclose(s.t, want, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(s.samples, ref[["ax", "ay", "az"]].to_numpy())
    assert s.t0 == "2024-02-29T23:59:58.500000+00:00"
    assert s.fs == pytest.approx(400.0)
    # With an offset, the instant is what counts.
    q = write(tmp_path, "t;x;y;z\n2024-03-01 01:00:00+01:00;1;2;3\n2024-03-01T00:00:01Z;1;2;3\n")
    np.testing.assert_array_equal(read_stream(q).t, [0.0, 1.0])


def test_a_dated_column_is_the_time_whatever_its_name(tmp_path: Path) -> None:
    rows = "".join(f"2026-03-01T12:00:{i // 100:02d}.{i % 100:02d},{i % 7},2,9.8\n"
                   for i in range(3000))
    s = read_stream(write(tmp_path, "recorded,ax,ay,az\n" + rows))
    np.testing.assert_allclose(s.t, np.arange(3000) / 100.0, rtol=0, atol=1e-9)
    assert s.fs == pytest.approx(100.0, rel=1e-12)
    assert s.t0 == "2026-03-01T12:00:00.00"
    assert any("'recorded' holds dates and times" in n for n in s.notes)


def test_rate_from_epoch_stamps_is_not_their_rounding(tmp_path: Path) -> None:
    # float64 epoch seconds are 2.4e-7 s apart: one interval's rate is off by up to 5e-5, the
    # average of the regular intervals is not (their sum telescopes).
    t = 1.764e9 + np.arange(4000) / 200.0
    rows = "".join(f"{v:.3f},1,2,9.8\n" for v in t)
    s = read_stream(write(tmp_path, "time,ax,ay,az\n" + rows))
    assert s.fs == pytest.approx(200.0, rel=1e-7)
    # A dropout (a missing second) and a repeated stamp do not move it either.
    keep = np.r_[0:1000, 1200:4000]
    rows = "".join(f"{v:.3f},1,2,9.8\n" for v in np.r_[t[keep], t[-1]])
    assert read_stream(write(tmp_path, "time,ax,ay,az\n" + rows)).fs == pytest.approx(
        200.0, rel=1e-7)


def test_unknown_rate_names_the_column_that_looks_like_time(tmp_path: Path) -> None:
    rows = "".join(f"{i / 50:.2f};{i % 7};2;9,8\n".replace(".", ",") for i in range(500))
    p = write(tmp_path, "Zeit;ax;ay;az\n" + rows)
    with pytest.raises(CalibrationError, match="column 'Zeit' .* time_column="):
        stream_dwells(p)
    assert read_stream(p, time_column="Zeit").fs == pytest.approx(50.0)


def test_time_unit_given_with_the_column_and_explained_when_missing(tmp_path: Path) -> None:
    from accelcal.sim import field_session

    s = field_session(fs=100.0, n_dwells=6, dwell_s=8.0, move_s=3.0, rng=3)
    stamp = (3.2e12 + s.t * 1e9).astype(np.int64)  # ns since boot, as Android logs them
    p = tmp_path / "ns.csv"
    np.savetxt(p, np.column_stack([stamp, s.samples]), delimiter=",", fmt=["%d"] + ["%.9g"] * 3,
               header="timestamp,ax,ay,az", comments="")
    # Read in s, the rate is 1e-7 Hz: the error says which unit gives a plausible rate.
    with pytest.raises(CalibrationError, match=r"if it is in ns \(100 Hz\).*'timestamp \[ns\]'"):
        stream_dwells(p)
    st = read_stream(p, time_column="timestamp [ns]")
    assert st.fs == pytest.approx(100.0, rel=1e-9)
    np.testing.assert_allclose(st.t - 3200.0, s.t, atol=1e-6)
    assert read_stream(p, time_column="0 [ns]").fs == pytest.approx(100.0, rel=1e-9)
    assert len(stream_dwells(p, time_column="timestamp [ns]")) == 6
    with pytest.raises(CalibrationError, match="unknown time unit 'ks'"):
        read_stream(p, time_column="timestamp [ks]")


@pytest.mark.parametrize(("unit", "factor"), [("ms", 1e3), ("us", 1e6), ("ns", 1e9)])
def test_epoch_stamps_without_a_unit_are_read_in_theirs(tmp_path: Path, unit: str,
                                                        factor: float) -> None:
    # Sensor Logger's layout: epoch ns in "time", columns z, y, x.
    t = np.arange(2000) / 100.0
    rows = "".join(f"{int(round((1.764e9 + v) * factor))},{v:.6f},9.8,{i % 3},{i % 5}\n"
                   for i, v in enumerate(t))
    s = read_stream(write(tmp_path, "time,seconds_elapsed,z,y,x\n" + rows))
    assert s.fs == pytest.approx(100.0, rel=1e-6)
    np.testing.assert_allclose(s.t - s.t[0], t, atol=1e-6)
    np.testing.assert_array_equal(s.samples[:5], [[0, 0, 9.8], [1, 1, 9.8], [2, 2, 9.8],
                                                  [3, 0, 9.8], [4, 1, 9.8]])
    assert any(f"Unix epoch times in {unit}" in n for n in s.notes)
    # Nanoseconds since boot (3.2e12 looks like epoch ms, but would give 1e-4 Hz): not read
    # as epoch; the rate error then names the unit that fits.
    rows = "".join(f"{int(3.2e12 + v * 1e9)},9.8,{i % 3},{i % 5}\n" for i, v in enumerate(t))
    p = write(tmp_path, "time,z,y,x\n" + rows)
    assert read_stream(p).fs == pytest.approx(1e-7)
    with pytest.raises(CalibrationError, match=r"if it is in ns \(100 Hz\)"):
        stream_dwells(p)


@pytest.mark.parametrize(
    ("names", "time_scale"),
    [
        ("millis,Ax_g,Ay_g,Az_g", 1e-3),
        ("time_usec,imu.acc.x,imu.acc.y,imu.acc.z", 1e-6),
        ("seconds,acc_x_mps2,acc_y_mps2,acc_z_mps2", 1.0),
        ("micros,accel_x_raw,accel_y_raw,accel_z_raw", 1e-6),
        ("time,gFx,gFy,gFz", 1.0),  # Physics Toolbox (g-force)
        ("Time since start in ms ,ACCELEROMETER X (m/s²),ACCELEROMETER Y (m/s²),"
         "ACCELEROMETER Z (m/s²)", 1e-3),  # AndroSensor
        ("X_Value,ax,ay,az", 1.0),  # LabVIEW
        ("SampleTimeFine,Acc_X,Acc_Y,Acc_Z", 1e-4),  # Xsens MT Manager (100 us ticks)
        ("millis,AcX,AcY,AcZ", 1e-3),  # the MPU-6050 Arduino sketch
    ],
)
def test_logger_column_names(tmp_path: Path, names: str, time_scale: float) -> None:
    rows = "".join(f"{i * 5},{i % 3},{i % 5},9.8\n" for i in range(400))
    s = read_stream(write(tmp_path, names + "\n" + rows))
    np.testing.assert_array_equal(s.samples[:, 0], np.arange(400) % 3)
    assert s.fs == pytest.approx(1.0 / (5 * time_scale))


def test_mpu6050_sketch_log_with_gyro_and_temperature_registers(tmp_path: Path) -> None:
    rows = "".join(f"{i * 10};{i % 3};{i % 5};16384;{-1200 + i};3;-2;1\n" for i in range(400))
    s = read_stream(write(tmp_path, "millis;AcX;AcY;AcZ;Tmp;GyX;GyY;GyZ\n" + rows))
    assert s.names == ("AcX", "AcY", "AcZ") and s.fs == pytest.approx(100.0)
    assert s.temperature is not None
    np.testing.assert_array_equal(s.temperature, -1200.0 + np.arange(400))


def test_phyphox_workbook_reads_the_raw_data_sheet(tmp_path: Path) -> None:
    import pandas as pd

    x = np.random.default_rng(4).normal(size=(500, 3)) + [0.0, 0.0, 9.8]
    t = np.arange(500) / 200.0
    raw = pd.DataFrame({"Time (s)": t, "Acceleration x (m/s^2)": x[:, 0],
                        "Acceleration y (m/s^2)": x[:, 1], "Acceleration z (m/s^2)": x[:, 2],
                        "Absolute acceleration (m/s^2)": np.linalg.norm(x, axis=1)})
    p = tmp_path / "phyphox.xlsx"
    with pd.ExcelWriter(p) as w:  # a metadata sheet first: the reader must look further
        pd.DataFrame({"event": ["START", "PAUSE"], "experiment time": [0.0, 2.5]}).to_excel(
            w, sheet_name="Metadata Time", index=False)
        raw.to_excel(w, sheet_name="Raw Data", index=False)
    s = read_stream(p)
    ref = pd.read_excel(p, sheet_name="Raw Data").to_numpy()
    np.testing.assert_array_equal(s.samples, ref[:, 1:4])
    np.testing.assert_array_equal(s.t, ref[:, 0])
    np.testing.assert_allclose(s.samples, x, rtol=1e-15)  # the workbook's own rounding
    assert s.fs == pytest.approx(200.0) and s.names[0] == "Acceleration x (m/s^2)"
    assert any("sheet 'Raw Data'" in n for n in s.notes)
    # columns= picks the sheet that holds them.
    s2 = read_stream(p, columns=["Acceleration z (m/s^2)", "Acceleration y (m/s^2)",
                                 "Acceleration x (m/s^2)"])
    np.testing.assert_array_equal(s2.samples, ref[:, 3:0:-1])
    # Not a workbook, or no reader for it: clear errors.
    bad = tmp_path / "bad.xlsx"
    bad.write_text("ax,ay,az\n1,2,3\n")
    with pytest.raises(CalibrationError, match="bad.xlsx: cannot read the spreadsheet"):
        read_stream(bad)


def test_spreadsheet_without_its_reader_says_what_to_install(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import pandas as pd

    def missing(*a: Any, **k: Any) -> Any:
        raise ImportError("Missing optional dependency 'odfpy'.  Use pip or conda to install "
                          "odfpy.")

    monkeypatch.setattr(pd, "read_excel", missing)
    p = tmp_path / "log.ods"
    p.write_bytes(b"PK")
    with pytest.raises(CalibrationError, match=r"log\.ods: Missing optional dependency 'odfpy'.*"
                       r"or export the sheet as CSV"):
        read_stream(p)


def _rows(n: int, fmt: Any) -> str:
    return "".join(fmt(i) for i in range(n))


def test_linear_acceleration_columns_get_a_note(tmp_path: Path) -> None:
    rows = "".join(f"{i / 100},0.0{i % 3},0.0{i % 5},0.01\n" for i in range(300))
    s = read_stream(write(tmp_path, '"Time (s)","Linear Acceleration x (m/s^2)","Linear '
                          'Acceleration y (m/s^2)","Linear Acceleration z (m/s^2)"\n' + rows))
    assert any("look like a linear (user) acceleration" in n for n in s.notes)
    raw = read_stream(write(tmp_path, "t,ax,ay,az\n" + rows, "raw.csv"))
    assert not any("linear" in n for n in raw.notes)


def test_witmotion_log_with_a_device_column_and_unpadded_dates(tmp_path: Path) -> None:
    # WitMotion's export: tab-separated, the device name in every row, dates without zero
    # padding (which the text reader's ISO-8601 parser refuses), a second time column.
    head = ("Time\tDevice name\tChip Time()\tAcceleration X(g)\tAcceleration Y(g)\t"
            "Acceleration Z(g)\tAngular velocity X(°/s)\tTemperature(°C)\n")
    body = _rows(300, lambda i: (
        f"2023-10-9 16:14:{27 + i // 100:02d}.{(i % 100) * 10:03d}\tWT5300001234(e1:2f)\t"
        f"2023-10-09 16:14:{27 + i // 100:02d}.{(i % 100) * 10:03d}\t0.{i % 7}\t-0.{i % 3}\t"
        f"0.98\t0.061\t24.5{i % 2}\n"))
    s = read_stream(write(tmp_path, head + body, "wit.txt"))
    assert s.names == ("Acceleration X(g)", "Acceleration Y(g)", "Acceleration Z(g)")
    np.testing.assert_allclose(s.samples[:, 0], (np.arange(300) % 7) / 10)
    np.testing.assert_allclose(s.t, np.arange(300) / 100.0, atol=1e-9)
    assert s.fs == pytest.approx(100.0) and s.t0 == "2023-10-09T16:14:27.000000"
    assert s.temperature is not None and s.temperature[1] == pytest.approx(24.51)
    assert any("'Device name' holds 'WT5300001234(e1:2f)' in every row" in n for n in s.notes)
    # A text column that varies and names no sensor is still refused, with the advice.
    mixed = head + body.replace("WT5300001234(e1:2f)", "WT5300005678(aa:bb)", 5)
    with pytest.raises(CalibrationError, match="no label that names an accelerometer"):
        read_stream(write(tmp_path, mixed, "mixed.txt"))


def test_shimmer_export_kind_and_units_rows_two_ranges(tmp_path: Path) -> None:
    names = ["Shimmer_9A2F_Timestamp_Unix_CAL"] + [
        f"Shimmer_9A2F_Accel_{r}_{a}_CAL" for r in ("LN", "WR") for a in "XYZ"]

    def header(names: list[str]) -> str:
        return ('"sep=,"\n' + ",".join(names) + ",\n" + "CAL," * 7 + "\n"
                + "ms," + "m/(s^2)," * 6 + "\n")

    head = header(names)
    body = _rows(400, lambda i: f"{1.7e12 + 5 * i:.3f},0.{i % 7},0.{i % 3},9.8,1.{i % 7},2,3,\n")
    p = write(tmp_path, head + body, "shimmer.csv")
    with pytest.raises(CalibrationError, match=r"2 accelerometer triads \(Shimmer_9A2F_Accel_LN_X"
                       r"_CAL,.*; Shimmer_9A2F_Accel_WR_X_CAL.*several sensors or ranges"):
        read_stream(p)
    s = read_stream(p, columns=names[4:7])  # the wide-range triad, named without its unit
    np.testing.assert_allclose(s.samples[:, 0], 1 + (np.arange(400) % 7) / 10)
    assert s.names[0] == "Shimmer_9A2F_Accel_WR_X_CAL [m/s^2]"
    assert s.fs == pytest.approx(200.0) and s.t is not None  # the ms time stamp
    gyro = header(names[:4] + [f"Shimmer_9A2F_Gyro_{a}_CAL" for a in "XYZ"])
    s = read_stream(write(tmp_path, gyro + body, "ln.csv"))  # one triad: found by itself
    assert s.names[0] == "Shimmer_9A2F_Accel_LN_X_CAL [m/s^2]"


def test_dataframe_with_zoned_date_times(tmp_path: Path) -> None:
    import pandas as pd

    df = pd.DataFrame({"time": pd.date_range("2024-01-01", periods=50, freq="10ms",
                                             tz="Europe/Berlin"),
                       "ax": np.arange(50.0), "ay": 1.0, "az": 9.8})
    s = read_stream(df)
    np.testing.assert_allclose(s.t, np.arange(50) / 100.0, atol=1e-12)
    assert s.fs == pytest.approx(100.0) and s.t0 == "2023-12-31T23:00:00.000000"  # UTC


def _write_tdms(p: Path, x: np.ndarray, names: tuple[str, ...] = ("Acc X", "Acc Y", "Acc Z"),
                group: str = "Accelerometer") -> None:
    from nptdms import ChannelObject, TdmsWriter

    props = {"wf_increment": 0.004, "wf_start_time": np.datetime64("2026-11-20T10:00:00"),
             "unit_string": "m/s^2"}
    with TdmsWriter(str(p)) as w:
        w.write_segment(
            [ChannelObject("Settings", "Gain", np.array([1.0, 2.0]))]
            + [ChannelObject(group, n, x[:, i], props) for i, n in enumerate(names)]
            + [ChannelObject(group, "Temperature", np.full(len(x), 22.5),
                             {"unit_string": "degC"}),
               ChannelObject(group, "Slow channel", np.arange(3.0))])


def test_labview_tdms_file(tmp_path: Path) -> None:
    x = np.random.default_rng(5).normal(size=(1000, 3)) + [0.0, 0.0, 9.8]
    p = tmp_path / "run.tdms"
    _write_tdms(p, x)
    s = read_stream(p)
    np.testing.assert_array_equal(s.samples, x)
    assert s.names == ("Acc X [m/s^2]", "Acc Y [m/s^2]", "Acc Z [m/s^2]")
    assert s.fs == pytest.approx(250.0) and s.fs_source == "metadata"
    assert s.t0 == "2026-11-20T10:00:00.000000"
    np.testing.assert_allclose(s.t, np.arange(1000) / 250.0)
    assert s.temperature is not None and s.temperature[0] == 22.5
    assert any("TDMS group 'Accelerometer'" in n for n in s.notes)
    # Channels named otherwise: columns= names them (without their unit), or the error lists
    # every group's channels.
    q = tmp_path / "daq.tdms"
    _write_tdms(q, x, names=("AI0", "AI1", "AI2"), group="DAQ")
    with pytest.raises(CalibrationError, match=r"no TDMS group holds an accelerometer triad.*"
                       r"'DAQ': 'AI0 \[m/s\^2\]', 'AI1"):
        read_stream(q)
    np.testing.assert_array_equal(read_stream(q, columns="AI2,AI1,AI0").samples, x[:, ::-1])
    bad = tmp_path / "bad.tdms"
    bad.write_bytes(b"not a TDMS file at all")
    with pytest.raises(CalibrationError, match="bad.tdms: cannot read the TDMS file"):
        read_stream(bad)


def test_tdms_without_nptdms_says_what_to_install(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "nptdms", None)  # import nptdms now fails
    p = tmp_path / "run.tdms"
    p.write_bytes(b"TDSm")
    with pytest.raises(CalibrationError, match=r"reading it needs npTDMS: pip install "
                       r"'accelcal\[tdms\]'"):
        read_stream(p)


def _mseed(path: Path, counts: np.ndarray, *, locs: tuple[str, ...] = ("00",),
           inst: str = "N", seismometer: bool = True, gap: bool = False) -> None:
    from obspy import Stream, Trace, UTCDateTime

    t0 = UTCDateTime("2026-11-20T10:00:00")
    st = Stream()
    for loc in locs:
        for j, ch in enumerate("ENZ"):
            st.append(Trace(counts[:, j].copy(), header={
                "network": "XX", "station": "GRAV", "location": loc, "channel": f"H{inst}{ch}",
                "sampling_rate": 200.0, "starttime": t0}))
    if seismometer:  # a velocity seismometer beside it
        for ch in "ENZ":
            st.append(Trace(np.zeros(500, np.int32), header={
                "network": "XX", "station": "GRAV", "location": "10", "channel": f"HH{ch}",
                "sampling_rate": 200.0, "starttime": t0}))
    if gap:  # 0.5 s missing from the Z trace
        z = st.select(location=locs[0], channel=f"H{inst}Z")[0]
        st.remove(z)
        st += Stream([z.slice(t0, t0 + 2.0), z.slice(t0 + 2.5, z.stats.endtime)])
    st.write(str(path), format="MSEED")


def test_miniseed_accelerometer_channels(tmp_path: Path) -> None:
    c = (np.random.default_rng(6).normal(size=(2000, 3)) * 50 + [0, 0, 2**20]).astype(np.int32)
    p = tmp_path / "station.mseed"
    _mseed(p, c)
    s = read_stream(p)
    assert s.names == ("XX.GRAV.00.HNE", "XX.GRAV.00.HNN", "XX.GRAV.00.HNZ")
    np.testing.assert_array_equal(s.samples, c)
    assert s.fs == 200.0 and s.fs_source == "metadata" and s.t0 == "2026-11-20T10:00:00"
    np.testing.assert_allclose(s.t, np.arange(2000) / 200.0)
    # Traces by channel code, in any order; a file named otherwise is told by its header.
    q = tmp_path / "logger.dat"
    _mseed(q, c, gap=True)
    s = read_stream(q, columns="HNZ,HNN,HNE")
    np.testing.assert_array_equal(s.samples[:, 1:], c[:, 1::-1])
    gone = np.isnan(s.samples[:, 0])
    assert gone.sum() == 99 and not gone[:400].any()  # the 0.5 s gap: dropouts
    assert any("99 samples in gaps read as NaN (dropouts)" in n for n in s.notes)
    d = ac.detect_dwells(s.samples, s.fs)
    assert d.dropped == 99


def test_miniseed_without_one_accelerometer_triad(tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    c = np.zeros((500, 3), np.int32)
    p = tmp_path / "vel.mseed"
    _mseed(p, c, inst="H", seismometer=False)
    with pytest.raises(CalibrationError, match=r"no accelerometer triad among the traces.*"
                       r"not accelerometer channels - SEED instrument code N - and a "
                       r"seismometer's velocity output does not see gravity"):
        read_stream(p)
    q = tmp_path / "two.mseed"
    _mseed(q, c, locs=("00", "01"), seismometer=False)
    with pytest.raises(CalibrationError, match=r"2 accelerometer triads .*giving.*columns=, e.g. "
                       r"'XX.GRAV.00.HNE,XX.GRAV.00.HNN,XX.GRAV.00.HNZ'"):
        read_stream(q)
    with pytest.raises(CalibrationError, match=r"more than one trace named 'HNE'"):
        read_stream(q, columns="HNE,HNN,HNZ")
    assert read_stream(q, columns="XX.GRAV.01.HNE,XX.GRAV.01.HNN,XX.GRAV.01.HNZ").names[0] == (
        "XX.GRAV.01.HNE")
    monkeypatch.setitem(sys.modules, "obspy", None)
    with pytest.raises(CalibrationError, match=r"needs ObsPy: pip install 'accelcal\[seismic\]'"):
        read_stream(q)


def test_read_bounds_formats(tmp_path: Path) -> None:
    from accelcal.io import read_bounds

    imu = read_bounds(shared_data("imucal", "example_ferraris_session_list.json"))
    assert imu.names == ["x_p", "x_a", "y_p", "y_a", "z_p", "z_a"] and not imu.seconds
    np.testing.assert_array_equal(imu.rows(None)[0], [540, 1271])
    assert "left out as motions, not static: x_rot, y_rot, z_rot" in imu.notes[0]
    cases = {
        "pairs.json": ("[[10, 50], [80, 120]]", [[10, 50], [80, 120]], False),
        "obj.json": ('{"bounds": [{"name": "up", "start_s": 0.1, "stop_s": 0.5}]}',
                     [[0.1, 0.5]], True),
        "named.csv": ("# sequencer log\npose,start,end\nup,10,50\ndown,80,120\n",
                      [[10, 50], [80, 120]], False),
        "plain.tsv": ("10\t50\n80\t120\n", [[10, 50], [80, 120]], False),
        "secs.csv": ("start_s;stop_s;what\n0.1;0.5;tilt 1\n1.0;1.4;move 1\n",
                     [[0.1, 0.5]], True),
        # A (2, k) array saved as it is (tomisuarez2/ImuCalibration's static_intervals.csv):
        # the starts, then the stops, one dwell per column.
        "starts_stops.csv": ("1.5e+02,4.297e+03,4.934e+03\n3.613e+03,4.299e+03,4.946e+03\n",
                             [[150, 3613], [4297, 4299], [4934, 4946]], False),
    }
    for name, (text, want, seconds) in cases.items():
        b = read_bounds(write(tmp_path, text, name))
        np.testing.assert_allclose(b.values, want, err_msg=name)
        assert b.seconds == seconds, name
    # Given dwells of a few samples are said to be so (their variances tell little).
    from accelcal.sim.field import field_session

    s = field_session(fs=100.0, n_dwells=10, dwell_s=3.0, move_s=1.0, sigma=0.01, rng=1)
    rec = write(tmp_path, "t,ax,ay,az\n" + "".join(
        f"{t:.2f},{x:.5f},{y:.5f},{z:.5f}\n" for t, (x, y, z) in zip(s.t, s.samples,
                                                                    strict=True)), "rec.csv")
    tiny = write(tmp_path, "[[10, 12], [400, 412], [800, 1000]]", "tiny.json")
    from accelcal.io import _stream_dwells

    _, r = _stream_dwells(rec, bounds=tiny)
    assert any("2 of the given dwells hold fewer than 30 samples (dwell 0: 2 samples, "
               "dwell 1: 12 samples)" in x for x in r.notes())
    b = read_bounds(tmp_path / "secs.csv")
    np.testing.assert_array_equal(b.rows(100.0), [[10, 50]])
    with pytest.raises(CalibrationError, match=r"in seconds, so the sample rate is needed"):
        b.rows(None)
    bad = {
        '{"a": {"begin_s": 1}}': r"section 'a' has no start and stop",
        "[[1.5, 4]]": r"rows must be whole numbers.*start_s and stop_s",
        '{"x_rot": [1, 5]}': r"no static sections in the bounds file \(left out as motions: "
                             r"x_rot\)",
        "first,second\n1,2\n": r"names no start and stop",
        '[{"start": 1, "stop": 4}, {"start_s": 1.0, "stop_s": 2.0}]': r"some bounds are in "
                                                                    r"rows and some in seconds",
        "[[1, 2, 3]]": r"entry 0 is not a \[start, stop\] pair",
    }
    for i, (text, msg) in enumerate(bad.items()):
        with pytest.raises(CalibrationError, match=msg):
            read_bounds(write(tmp_path, text, f"bad{i}.json" if text[0] in "[{" else
                              f"bad{i}.csv"))
    with pytest.raises(CalibrationError, match="bounds file not found"):
        read_bounds(tmp_path / "none.json")


def test_stream_dwells_with_a_bounds_file_equals_dwell_stats() -> None:
    from accelcal.io import read_bounds, stream_dwells

    csv = shared_data("imucal", "example_ferraris_session.csv")
    js = shared_data("imucal", "example_ferraris_session_list.json")
    d = stream_dwells(csv, fs=102.4, bounds=js)
    st = read_stream(csv, fs=102.4)
    ref = ac.dwell_stats(st.samples, read_bounds(js).rows(st.fs), fs=st.fs)
    np.testing.assert_array_equal(d.mean, ref.mean)
    np.testing.assert_array_equal(d.count, [731, 741, 484, 412, 453, 607])


def _imu_msg(ts: Any, i: int, acc: np.ndarray, stamped: bool, ros1: bool = False) -> Any:
    t = ts.types["builtin_interfaces/msg/Time"]
    head = {"stamp": t(sec=100 + i // 200, nanosec=(i % 200) * 5_000_000) if stamped
            else t(sec=0, nanosec=0), "frame_id": "imu"}
    if ros1:
        head["seq"] = i
    v, q = ts.types["geometry_msgs/msg/Vector3"], ts.types["geometry_msgs/msg/Quaternion"]
    return ts.types["sensor_msgs/msg/Imu"](
        header=ts.types["std_msgs/msg/Header"](**head), orientation=q(x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.zeros(9), angular_velocity=v(x=0.0, y=0.0, z=0.0),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=v(x=acc[i, 0], y=acc[i, 1], z=acc[i, 2]),
        linear_acceleration_covariance=np.zeros(9))


def test_ros_bags_imu_topics(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    acc = np.random.default_rng(7).normal(size=(400, 3)) + [0.0, 0.0, 9.8]
    ts = get_typestore(Stores.ROS2_HUMBLE)
    imu, string = "sensor_msgs/msg/Imu", "std_msgs/msg/String"
    bag = tmp_path / "bag2"
    with Writer(bag, version=8) as w:
        a = w.add_connection("/imu/data", imu, typestore=ts)
        b = w.add_connection("/imu/raw", imu, typestore=ts)
        c = w.add_connection("/log", string, typestore=ts)
        for i in range(400):
            w.write(a, 10**11 + i * 5_000_000, ts.serialize_cdr(_imu_msg(ts, i, acc, True), imu))
            w.write(b, 10**11 + i * 5_000_000 + 1000,
                    ts.serialize_cdr(_imu_msg(ts, i, acc[::-1], False), imu))
        w.write(c, 10**11, ts.serialize_cdr(ts.types[string](data="start"), string))
    with pytest.raises(CalibrationError, match=r"2 IMU topics \(/imu/data \(400 messages\), "
                       r"/imu/raw \(400 messages\)\): give the one to calibrate with columns="):
        read_stream(bag)
    s = read_stream(bag, columns="/imu/data")
    np.testing.assert_array_equal(s.samples, acc)
    np.testing.assert_allclose(s.t, np.arange(400) * 0.005, atol=1e-9)
    assert s.fs == pytest.approx(200.0) and s.t0 == "1970-01-01T00:01:40.000000"
    assert "linear_acceleration (which includes gravity, REP 145)" in s.notes[0]
    raw = read_stream(next(bag.glob("*.db3")), columns="/imu/raw")  # the storage file itself
    np.testing.assert_array_equal(raw.samples, acc[::-1])
    assert any("header stamps do not increase" in n for n in raw.notes)
    assert raw.fs == pytest.approx(200.0)  # from the receive times
    with pytest.raises(CalibrationError, match=r"no sensor_msgs/Imu topic '/imu' in the bag"):
        read_stream(bag, columns="/imu")
    # ROS 1: one topic, found by itself.
    ts1 = get_typestore(Stores.ROS1_NOETIC)
    one = tmp_path / "run.bag"
    with Writer1(one) as w1:
        a = w1.add_connection("/imu", imu, typestore=ts1)
        for i in range(400):
            w1.write(a, 10**11 + i * 5_000_000,
                     ts1.serialize_ros1(_imu_msg(ts1, i, acc, True, ros1=True), imu))
    np.testing.assert_array_equal(read_stream(one).samples, acc)
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    with pytest.raises(CalibrationError, match=r"needs rosbags: pip install 'accelcal\[ros\]'"):
        read_stream(one)


def test_decimal_comma_files_match_pandas(tmp_path: Path) -> None:
    import pandas as pd

    x = _table(1500, 4)
    p = tmp_path / "dc.csv"
    body = "\n".join(";".join(v.replace(".", ",") for v in r) for r in _fmt(x))
    p.write_text("Abtastrate: 250\nt;ax;ay;az;temp\n" + body + "\n")
    ref = pd.read_csv(p, sep=";", decimal=",", skiprows=1)
    s = read_stream(p)
    np.testing.assert_array_equal(s.samples, ref[["ax", "ay", "az"]].to_numpy())
    np.testing.assert_array_equal(s.samples, x[:, 1:4])
    np.testing.assert_array_equal(s.t, x[:, 0])
    # Tab-separated, no header.
    q = tmp_path / "dc.tsv"
    q.write_text("\n".join("\t".join(v.replace(".", ",") for v in r[1:4]) for r in _fmt(x)))
    np.testing.assert_array_equal(read_stream(q, fs=250).samples, x[:, 1:4])


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("ax,ay,az\n1,2,3\n4,5,6\n7,8\n", ["line 4", "2 fields where the data rows have 3"]),
        ("t,ax,ay,az\n2024-01-01T00:00:00,1,2,3\n2024-01-01T00:00:01,1,2,3\nyesterday,1,2,3\n",
         ["line 4", '"yesterday"', "ISO-8601"]),
        ("2024-01-01 00:00:00 1 2 3\n2024-01-01 00:00:01 1 2 3\n",
         ["line 1", "date and a time separated by a space"]),
        ("t,ax,ay,az,gx\n0,1,2,3,\n0.005,,,,1\n0.01,1,,3,\n",
         ["line 4", 'column "ay": is empty (missing value)']),
        ("timestamp,sensor,x,y,z\n0.00,MAG,0.1,0.2,9.8\n0.00,GYR,0.01,0.02,0.03\n",
         ["long-format log", "'sensor': GYR, MAG", "no label that names an "
          "accelerometer", "df[df[label] == value]"]),
    ],
)
def test_bad_rows_are_named_by_line(tmp_path: Path, text: str, words: list[str]) -> None:
    p = write(tmp_path, text)
    with pytest.raises(CalibrationError) as ei:
        read_stream(p)
    msg = str(ei.value)
    assert msg.startswith(str(p))
    for w in words:
        assert w in msg, msg


@pytest.mark.parametrize(
    ("text", "rows", "words"),
    [
        ("Fs,100\nax;ay;az\n" + "1;2;3\n" * 400_000 + "4;5;6,5\n" + "1;2;3\n" * 10,
         400_010, ["1 data row(s)", "line 400003", '"6,5"', "decimal comma"]),
        ("ax,ay,az\n" + "1,2,3\n" * 5000 + "1,2,oops\n" + "1,2,3\n,-0.06\n" * 9,
         5009, ["10 data row(s)", "line 5002", '"oops"']),
        # A serial capture: lines cut short or run together.
        ("t,ax,ay,az\n" + "".join(f"{i / 100},0.01,-0.02,1.01\n" + (
            ",-0.06\n" if i % 500 == 7 else "1.03,-0.01,-0.05\n" if i % 500 == 300 else "")
            for i in range(2000)), 2000, ["8 data row(s)", "line 10: 2 fields where the "
                                          "data rows have 4"]),
    ],
)
def test_a_few_rows_that_do_not_parse_are_left_out_and_named(
        tmp_path: Path, text: str, rows: int, words: list[str]) -> None:
    p = write(tmp_path, text)
    st = read_stream(p, fs=100.0)  # the whole file in parallel chunks
    streamed = ac.io._Recording(p, None, 100.0, None)  # in blocks, as dwell detection reads
    n = sum(len(c[0]) for c in streamed.chunks(chunk_rows=1000))
    for got, notes in ((len(st), st.notes), (n, streamed.notes())):
        assert got == rows
        note = [n for n in notes if "do not parse" in n]
        assert len(note) == 1 and all(w in note[0] for w in words), notes
    np.testing.assert_array_equal(np.unique(read_stream(p).samples, axis=0).shape, (1, 3))
    # Eleven of 2000 and more than 1 %: the file's error.
    bad = write(tmp_path, "ax,ay,az\n" + "1,2,3\n" * 1000 + "1,2\n" * 11, "bad.csv")
    with pytest.raises(CalibrationError, match=r"line 1002: 2 fields .* \(11 of the 1011 data"):
        read_stream(bad)


def test_many_preamble_lines_do_not_hide_the_data(tmp_path: Path) -> None:
    # 1200 metadata lines, then 3000 ISO-time rows: found, not "no numeric data row".
    meta = "".join(f"# note {i}: value\n" for i in range(1200))
    rows = "".join(f"2024-01-01T00:00:{i // 100:02d}.{i % 100:02d},{i},2,3\n" for i in range(3000))
    s = read_stream(write(tmp_path, meta + "t,ax,ay,az\n" + rows))
    assert len(s) == 3000 and s.fs == pytest.approx(100.0)


def test_columns_by_index_keep_time_detection() -> None:
    s = read_stream(XSENS(), columns="1,2,3")
    assert s.t is not None and s.fs == pytest.approx(100.0, rel=1e-3)
    np.testing.assert_array_equal(s.t, read_stream(XSENS()).t)


def test_sample_counter_is_not_time(tmp_path: Path) -> None:
    rows = "".join(f"{i},{i % 5},{i % 3},9.8\n" for i in range(200))
    s = read_stream(write(tmp_path, rows), columns=[1, 2, 3])
    assert s.t is None and s.fs is None
    assert any("counts samples" in n for n in s.notes)
    assert any("sample rate is not in the file" in n for n in s.notes)
    # Without columns= too (a helper's real file: `index, x, y, z` rows 0..88 in m/s^2, read
    # as a clock in s at 1 Hz before): the counter is no time, the three others are the axes.
    rows = "".join(f"{i},{0.4 + i % 5 * 1e-3},-0.1,{9.3 + i % 3 * 1e-3}\r\n" for i in range(89))
    s = read_stream(write(tmp_path, rows))
    assert s.t is None and s.fs is None and s.samples.shape == (89, 3)
    assert s.samples[0, 0] == pytest.approx(0.4)
    assert any("column 0 (0-based) counts samples" in n for n in s.notes)


def test_repeated_samples_give_the_output_rate(tmp_path: Path) -> None:
    # A 100 Hz sensor polled at 400 Hz: every value 4 times.
    rng = np.random.default_rng(5)
    v = rng.normal(size=(1000, 3))
    x = np.repeat(v, 4, axis=0)
    p = tmp_path / "polled.csv"
    np.savetxt(p, x, delimiter=",", header="ax,ay,az", comments="")
    s = read_stream(p, fs=400.0)
    assert s.repeats == 3000
    assert s.output_rate_hz == pytest.approx(100.0)
    assert any("100 Hz" in n and "400 Hz" in n for n in s.notes)
    d, rec = _stream(p, fs=400.0)
    assert rec.repeats == 3000 and rec.output_rate() == pytest.approx(100.0)
    # Real recordings do not trigger it.
    for f in (XSENS, MPU):
        assert read_stream(f()).output_rate_hz is None


def _stream(p: Path, **kw: Any) -> Any:
    from accelcal.io import _stream_dwells

    return _stream_dwells(p, bounds=[[0, 100]], chunk_rows=777, **kw)


def test_time_column_disagreeing_with_fs_is_reported() -> None:
    s = read_stream(XSENS(), fs=200.0)
    assert s.fs == 200.0 and s.fs_source == "given"
    assert any("200 Hz is used" in n and "100" in n for n in s.notes)
    assert not any("Hz" in n for n in read_stream(XSENS()).notes)


def test_stdin_is_read(tmp_path: Path) -> None:
    import subprocess
    import sys

    data = MPU().read_bytes()
    code = ("import sys, numpy as np; from accelcal.io import read_stream; "
            "s = read_stream('-'); np.save(sys.argv[1], s.samples); print(s.fs)")
    out = tmp_path / "x.npy"
    r = subprocess.run([sys.executable, "-c", code, str(out)], input=data, capture_output=True,
                       check=True)
    assert r.stdout.decode().strip() == "100.0"
    np.testing.assert_array_equal(np.load(out), read_stream(MPU()).samples)
    # Larger than the sniffed head: the Rust reader continues from the same descriptor.
    x = _table(60_000, 6)
    big = ("t,ax,ay,az,temp\n" + "\n".join(",".join(r) for r in _fmt(x)) + "\n").encode()
    assert len(big) > (1 << 21)
    r = subprocess.run([sys.executable, "-c", code, str(out)], input=big, capture_output=True,
                       check=True)
    np.testing.assert_array_equal(np.load(out), x[:, 1:4])


def test_dataframes_and_arrays_are_read_like_files() -> None:
    import pandas as pd

    s = read_stream(MPU())
    df = pd.DataFrame({"time_s": s.t, "acc_x": s.samples[:, 0], "acc_y": s.samples[:, 1],
                       "acc_z": s.samples[:, 2], "label": "static"})
    r = read_stream(df)
    np.testing.assert_array_equal(r.samples, s.samples)
    np.testing.assert_array_equal(r.t, s.t)
    assert r.fs == pytest.approx(100.0) and r.names == ("acc_x", "acc_y", "acc_z")
    d1 = stream_dwells(df, chunk_rows=999)
    d2 = stream_dwells(MPU())
    assert np.array_equal(d1.mean, d2.mean) and np.array_equal(d1.count, d2.count)
    # Fortran-ordered DataFrame.to_numpy(), a plain list, and the interchange protocol.
    arr = df[["acc_x", "acc_y", "acc_z"]].to_numpy()
    assert arr.flags.f_contiguous and not arr.flags.c_contiguous
    np.testing.assert_array_equal(read_stream(arr, fs=100.0).samples, s.samples)
    np.testing.assert_array_equal(read_stream(arr[:3].tolist()).samples, s.samples[:3])
    import warnings

    class Interchange:  # only the DataFrame interchange protocol
        def __dataframe__(self, nan_as_null: bool = False, allow_copy: bool = True) -> Any:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return df.__dataframe__(nan_as_null, allow_copy)

    ic = Interchange()
    np.testing.assert_array_equal(read_stream(ic).samples, s.samples)
    with pytest.raises(CalibrationError, match="DataFrame"):
        read_stream(object())


def test_hdf5_separate_axis_datasets(tmp_path: Path) -> None:
    import h5py

    rng = np.random.default_rng(7)
    x = (rng.normal(size=(5000, 3)) * 1000).astype(np.int16)
    path = tmp_path / "axes.h5"
    with h5py.File(path, "w") as f:
        g = f.create_group("sensors/imu")
        g["ax"], g["ay"], g["az"] = x[:, 0], x[:, 1], x[:, 2]
        g["gx"] = np.zeros(5000)
        g["time_s"] = np.arange(5000) / 500.0
    s = read_stream(path)
    np.testing.assert_array_equal(s.samples, x)
    assert s.samples.dtype == np.int16 and s.fs == pytest.approx(500.0)
    got = np.concatenate([c for c, _ in iter_stream(path, chunk_rows=1234)])
    np.testing.assert_array_equal(got, x)


def test_progress_bar_has_total_percentage_and_eta(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    x = _table(200_000, 8)
    p = tmp_path / "bar.csv"
    p.write_text("t,ax,ay,az,temp\n" + "\n".join(",".join(r) for r in _fmt(x)) + "\n")
    from accelcal.io import _progress_bar, _Recording

    rec = _Recording(p, None, None, None)
    est = rec.rows_estimate()
    assert est is not None and abs(est - 200_000) < 0.05 * 200_000  # from the file size
    bar = _progress_bar(rec, "dwells", True)
    with bar as cb:
        assert cb is not None
        for _ in rec.chunks(None, cb):
            pass
    assert bar.bar.total == bar.bar.n == 200_000
    err = capsys.readouterr().err
    assert "100%" in err and "200k/200k" in err and "rows" in err and "<" in err  # ETA
    # Off a terminal with progress=None, and with progress=False: nothing.
    read_stream(p, progress=None)
    read_stream(p, progress=False)
    assert capsys.readouterr().err == ""


def test_utf16_and_cr_only_text_get_a_remedy(tmp_path: Path) -> None:
    text = "t,ax,ay,az\n" + "".join(f"{i / 100},{i % 3},2,9.8\n" for i in range(300))
    p = tmp_path / "u16.csv"
    p.write_text(text, encoding="utf-16")
    with pytest.raises(CalibrationError, match="UTF-16.*save it as UTF-8"):
        read_stream(p)
    q = tmp_path / "cr.csv"
    q.write_bytes(text.replace("\n", "\r").encode())
    with pytest.raises(CalibrationError, match="carriage return alone"):
        read_stream(q)
    # The same text as UTF-8 with a byte-order mark reads.
    r = tmp_path / "bom.csv"
    r.write_text(text, encoding="utf-8-sig")
    assert read_stream(r).fs == pytest.approx(100.0)


@pytest.mark.parametrize("first_empty", [False, True])
def test_sparse_temperature_holds_its_last_value(tmp_path: Path, first_empty: bool) -> None:
    import pandas as pd

    n = 5000
    temp = 20.0 + np.arange(n) // 700  # logged every 700th row (from row 3 when first_empty)
    logged = np.arange(n) % 700 == (3 if first_empty else 0)
    rows = "".join(f"{i / 100},{i % 3},2,9.8,{temp[i] if logged[i] else ''}\n" for i in range(n))
    p = write(tmp_path, "t,ax,ay,az,temperature\n" + rows)
    want = pd.Series(np.where(logged, temp, np.nan)).ffill().bfill().to_numpy()
    s = read_stream(p)
    np.testing.assert_array_equal(s.temperature, want)
    assert any(f"empty in {int((~logged).sum())} of {n} rows" in x for x in s.notes)
    # Streamed in small chunks: the held value crosses chunk boundaries.
    got = [temp for _, _, temp in _iter_triples(p, 333)]
    np.testing.assert_array_equal(np.concatenate(got), want)
    # The same table as a DataFrame with NaN: the same hold.
    df = pd.read_csv(p)
    np.testing.assert_array_equal(read_stream(df).temperature, want)
    # The accelerometer columns stay strict.
    q = write(tmp_path, "t,ax,ay,az,temperature\n0,1,2,3,20\n0.01,1,,3,\n", "q.csv")
    with pytest.raises(CalibrationError, match='line 3: column "ay": is empty'):
        read_stream(q)


def _iter_triples(p: Path, chunk_rows: int) -> Any:
    from accelcal.io import open_recording

    rec = open_recording(p)
    yield from rec.chunks(chunk_rows, None)


@pytest.mark.parametrize("gyro_first", [False, True])
def test_merged_log_rows_of_another_sensor_are_left_out(tmp_path: Path, gyro_first: bool) -> None:
    # Accelerometer and gyroscope rows interleaved (each leaves the other's fields empty),
    # both at 100 Hz, 5 ms apart; an event column that is empty but for one row.
    n = 3000
    lines = []
    for i in range(n):
        acc = f"{i / 100:.3f},{i % 3},{i % 5},9.8,,,,"
        gyr = f"{i / 100 + 0.005:.3f},,,,0.1,0.2,0.3," + ("tap" if i == 7 else "")
        lines += [gyr, acc] if gyro_first else [acc, gyr]
    p = write(tmp_path, "time,ax,ay,az,gx,gy,gz,event\n" + "\n".join(lines) + "\n")
    s = read_stream(p)
    assert len(s) == n and s.fs == pytest.approx(100.0)
    np.testing.assert_array_equal(s.samples[:, 0], np.arange(n) % 3)
    np.testing.assert_allclose(s.t, np.arange(n) / 100, atol=1e-12)
    assert any(f"{n} rows with every accelerometer field empty were left out" in x
               for x in s.notes)
    streamed = np.concatenate([c for c, _ in iter_stream(p, chunk_rows=700)])
    np.testing.assert_array_equal(streamed, s.samples)


def test_binary_matlab_files_are_read(tmp_path: Path) -> None:
    import h5py
    from scipy.io import savemat

    rng = np.random.default_rng(3)
    acc = rng.normal(0, 0.01, (600, 3)) + [0.1, -0.2, 9.8]
    t = np.arange(600) / 200.0
    # v5 (scipy.io.savemat writes what MATLAB's save does): the (N, 3) matrix, a time vector
    # stored as a 1 x N row and the rate as a scalar.
    p = tmp_path / "acc.mat"
    savemat(p, {"acc": acc, "t": t[None, :], "fs": 200.0})
    s = read_stream(p)
    np.testing.assert_array_equal(s.samples, acc)
    np.testing.assert_array_equal(s.t, t)
    assert s.fs == 200.0 and s.fs_source == "metadata"
    # v7.3 (HDF5 after a 512-byte header): MATLAB stores an N x 3 matrix as 3 x N.
    q = tmp_path / "acc73.mat"
    with h5py.File(q, "w", userblock_size=512) as f:
        f["acc"] = acc.T
        f["t"] = t[None, :]
    with open(q, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Thu Nov 26 2026 HDF5 "
                 b"schema 1.00 .")
    s73 = read_stream(q)
    np.testing.assert_array_equal(s73.samples, acc)
    assert s73.fs == pytest.approx(200.0)
    # A file with no numeric matrix says so.
    e = tmp_path / "empty.mat"
    savemat(e, {"name": "session 1"})
    with pytest.raises(CalibrationError, match="holds no numeric matrix or vector"):
        read_stream(e)
    # An ASCII .mat (imu_tk's test data, MATLAB's save -ascii) is text.
    r = write(tmp_path, "".join(f"{i / 100} 1 2 9.8\n" for i in range(300)), "ascii.mat")
    assert read_stream(r).fs == pytest.approx(100.0)


def test_rows_left_out_may_lack_a_time_and_kept_rows_may_not(tmp_path: Path) -> None:
    rows = "".join(f"{i / 100},{i % 3},2,9.8,,\n,,,,0.1,0.2\n" for i in range(500))
    s = read_stream(write(tmp_path, "t,ax,ay,az,gx,gy\n" + rows))
    assert len(s) == 500 and s.fs == pytest.approx(100.0)
    bad = write(tmp_path, "t,ax,ay,az,gx,gy\n" + rows + ",1,2,9.8,,\n", "bad.csv")
    st = read_stream(bad)  # a kept row without its time does not parse: left out, and said
    assert len(st) == 500 and any(
        '1 data row(s) that do not parse were left out (the first, line 1002: column "t": is '
        "empty (missing value)): the file's last line" in n for n in st.notes), st.notes


def _wrapping_log(tmp_path: Path, unit: str, width: int, at_s: float) -> tuple[Path, Any]:
    from accelcal.sim.field import field_session

    s = field_session(fs=100.0, n_dwells=16, dwell_s=20.0, move_s=4.0, max_tilt_deg=80,
                      sigma=3e-3, rng=5)
    per_s = {"us": 1e6, "ms": 1e3}[unit]
    m = 2**width
    stamp = (np.round(s.t * per_s).astype(np.int64) + m - int(at_s * per_s)) % m
    p = tmp_path / f"wrap_{unit}.csv"
    np.savetxt(p, np.column_stack([stamp, s.samples]), delimiter=",",
               header=f"time_{unit},ax,ay,az", comments="", fmt=["%d", "%.6f", "%.6f", "%.6f"])
    return p, s


@pytest.mark.parametrize(("unit", "width", "at_s"), [("us", 32, 200.0), ("ms", 16, 30.0)])
def test_a_wrapping_time_counter_is_unwrapped(tmp_path: Path, unit: str, width: int,
                                              at_s: float) -> None:
    p, s = _wrapping_log(tmp_path, unit, width, at_s)
    st = read_stream(p)
    assert st.t is not None and np.all(np.diff(st.t) > 0)
    np.testing.assert_allclose(np.diff(st.t), np.diff(s.t), atol=1e-9)
    wraps = int((s.t[-1] - s.t[0] + (2**width / {"us": 1e6, "ms": 1e3}[unit] - at_s))
                // (2**width / {"us": 1e6, "ms": 1e3}[unit]))
    assert any(f"wraps around {wraps} time(s) (a {width}-bit counter of 1 {unit}" in n
               for n in st.notes), st.notes
    # Streaming in blocks (a wrap may fall on a block's first row) gives the same times ...
    chunks = [t for _, t in iter_stream(p, chunk_rows=997)]
    np.testing.assert_array_equal(np.concatenate(chunks), st.t)
    # ... and so do the dwells' times, which now follow the pose order.
    d, _rec = ac.io._stream_dwells(p)
    assert d.t is not None and np.all(np.diff(d.t) > 0)


def test_a_clock_reset_is_kept_and_said(tmp_path: Path) -> None:
    t = np.r_[np.arange(0, 50, 0.01), np.arange(0, 50, 0.01)] + 1000.0
    t[5000:] -= 600.0  # the logger's clock was set back 10 min
    x = np.random.default_rng(1).normal(0, 0.01, (t.size, 3)) + [0, 0, 9.81]
    p = tmp_path / "reset.csv"
    np.savetxt(p, np.column_stack([t, x]), delimiter=",", header="t,ax,ay,az", comments="")
    st = read_stream(p)
    assert st.t is not None and np.array_equal(st.t, np.loadtxt(p, delimiter=",",
                                                                skiprows=1)[:, 0])
    assert any("steps back 1 time(s) (the first at data row 5001, by 649.99 s)" in n
               for n in st.notes), st.notes


def test_unwrap_is_the_same_whatever_the_chunking() -> None:
    from accelcal.io import _TimeUnwrap

    raw = (np.arange(0, 300_000) * 1000 + 2**32 - 5_000_000) % 2**32 * 1e-6  # 1 kHz, us
    whole = _TimeUnwrap(1e-6, 1000.0)(raw.copy(), 0)
    assert np.allclose(np.diff(whole), 1e-3)
    for cuts in ([5000], [4999, 5001], [1, 5000, 5001, 250_000], list(range(0, 300_000, 777))):
        u = _TimeUnwrap(1e-6, 1000.0)
        parts = [u(c.copy(), int(a)) for a, c in zip([0, *cuts], np.split(raw, cuts),
                                                     strict=True)]
        np.testing.assert_array_equal(np.concatenate(parts), whole)
        assert u.wraps == [(5000, 32)] and u.back == []
    # A whole read of more rows than one slice gives the same times too.
    big = (np.arange(0, 3_000_000) * 1000 + 2**32 - 2_000_000_000) % 2**32 * 1e-6
    u = _TimeUnwrap(1e-6, 1000.0)
    out = u(big, 0)
    assert np.allclose(np.diff(out), 1e-3) and u.wraps == [(2_000_000, 32)]


def test_time_stamps_coarser_than_the_sample_interval_give_the_rate_from_their_span(
        tmp_path: Path) -> None:
    from accelcal.sim.field import field_session

    s = field_session(fs=5000.0, n_dwells=6, dwell_s=4.0, move_s=2.0, max_tilt_deg=80,
                      sigma=3e-3, rng=5)
    p = tmp_path / "ms_stamps.csv"  # a 5 kHz stream stamped in whole ms: 4 of 5 intervals 0
    np.savetxt(p, np.column_stack([np.round(s.t * 1e3), s.samples]), delimiter=",",
               header="time_ms,ax,ay,az", comments="", fmt=["%d", "%.6f", "%.6f", "%.6f"])
    st = read_stream(p)
    assert st.fs == pytest.approx(5000.0, rel=1e-3) and st.fs_source == "time column"
    assert any("resolution (0.001 s) is coarser than the sample interval" in n
               for n in st.notes), st.notes
    d, _rec = ac.io._stream_dwells(p)
    assert len(d) == len(s.bounds)


def _daq_text(kind: str) -> str:
    """A recording as a DAQ export of ``kind`` would write it."""
    from accelcal.sim.field import field_session

    s = field_session(fs=100.0, n_dwells=6, dwell_s=5.0, move_s=2.0, max_tilt_deg=80,
                      sigma=3e-3, rng=5)
    if kind == "units_row_ms_g":  # names, then units; time in ms, outputs in g
        rows = np.column_stack([s.t * 1e3, s.samples / 9.80665])
        return "time,ax,ay,az\nms,g,g,g\n" + "\n".join(
            ",".join(f"{v:.6f}" for v in r) for r in rows) + "\n"
    rows = np.column_stack([s.t, s.samples])
    body = "\n".join("\t".join(f"{v:.6f}" for v in r) + "\t" for r in rows) + "\n"
    if kind == "trailing_tab":  # every line ends in a tab (an empty last field)
        return "time\tax\tay\taz\t\n" + body
    # LabVIEW .lvm: a header block, then X_Value (the time) and a Comment column
    return ("LabVIEW Measurement\t\nWriter_Version\t2\nSeparator\tTab\n***End_of_Header***\t\n"
            "\nX_Value\tax\tay\taz\tComment\n" + body)


@pytest.mark.parametrize(("kind", "skip"), [("units_row_ms_g", 2), ("trailing_tab", 1),
                                            ("labview", 6)])
def test_daq_exports(tmp_path: Path, kind: str, skip: int) -> None:
    text = _daq_text(kind)
    p = tmp_path / f"{kind}.txt"
    p.write_text(text)
    st = read_stream(p)
    want = np.loadtxt(p, delimiter="\t" if "\t" in text else ",", skiprows=skip,
                      usecols=(0, 1, 2, 3))
    np.testing.assert_array_equal(st.samples, want[:, 1:])
    assert st.fs == pytest.approx(100.0, rel=1e-9) and st.t is not None
    np.testing.assert_allclose(st.t, want[:, 0] * (1e-3 if kind == "units_row_ms_g" else 1.0))
    if kind == "units_row_ms_g":
        assert st.names == ("ax [g]", "ay [g]", "az [g]")


@pytest.mark.parametrize("style", ["ax{}", "acc{}_x", "imu{}.acc.x"])
def test_numbered_triads(tmp_path: Path, style: str) -> None:
    def names(k: int) -> list[str]:
        return [style.format(k).replace("x", a) if "acc" in style else
                style.format(k).replace("ax", "a" + a) for a in "xyz"]

    rows = "".join(f"{i / 100},{i % 3},{i % 5},9.8,{i % 7},{i % 2},9.7\n" for i in range(300))
    two = write(tmp_path, ",".join(["t", *names(1), *names(2)]) + "\n" + rows)
    listed = re.escape(",".join(names(1)) + "; " + ",".join(names(2)))
    with pytest.raises(CalibrationError,
                       match=rf"2 accelerometer triads \({listed}\): a recording of several"):
        read_stream(two)
    s = read_stream(two, columns=",".join(names(2)))
    np.testing.assert_array_equal(s.samples[:, 0], np.arange(300) % 7)
    # One numbered triad is simply the accelerometer.
    rows1 = "".join(f"{i / 100},{i % 3},{i % 5},9.8\n" for i in range(300))
    s1 = read_stream(write(tmp_path, ",".join(["t", *names(0)]) + "\n" + rows1))
    assert s1.names == tuple(names(0))


def _long_log(tmp_path: Path, header: bool, iso: bool = False) -> tuple[Path, Path]:
    """The same field session as a wide file and as a long-format log: ACC rows interleaved
    with GYR rows and a slower MAG channel, each row naming its sensor."""
    from accelcal.sim.field import field_session

    s = field_session(fs=100.0, n_dwells=16, dwell_s=10.0, move_s=3.0, max_tilt_deg=80,
                      sigma=3e-3, rng=5)
    rng = np.random.default_rng(0)
    wide, long = ["t,ax,ay,az"], ["t,sensor,x,y,z"] if header else []
    def stamp(t: float) -> str:  # ISO-8601 (a file over the 2 MB head) or s
        return f"2026-11-26T10:{int(t) // 60:02d}:{t % 60:09.6f}" if iso else f"{t:.4f}"

    for i, (t, r) in enumerate(zip(s.t, s.samples, strict=True)):
        xyz = ",".join(f"{v:.6f}" for v in r)
        wide.append(f"{t:.4f},{xyz}")
        long.append(f"{stamp(t)},ACC,{xyz}" if header else f"ACC,{stamp(t)},{xyz}")
        g = ",".join(f"{v:.6f}" for v in rng.normal(size=3))
        long.append(f"{stamp(t + 0.002)},GYR,{g}" if header else f"GYR,{stamp(t + 0.002)},{g}")
        if i % 10 == 0:
            long.append(f"{stamp(t + 0.004)},MAG,{g}" if header else
                        f"MAG,{stamp(t + 0.004)},{g}")
    pw, pl = tmp_path / "wide.csv", tmp_path / "long.csv"
    pw.write_text("\n".join(wide) + "\n")
    pl.write_text("\n".join(long) + "\n")
    return pw, pl


@pytest.mark.parametrize(("header", "iso"), [(True, False), (False, False), (True, True)])
def test_long_format_logs_read_their_accelerometer_rows(tmp_path: Path, header: bool,
                                                        iso: bool) -> None:
    pw, pl = _long_log(tmp_path, header, iso)
    w, lg = read_stream(pw), read_stream(pl)
    np.testing.assert_array_equal(lg.samples, w.samples)
    np.testing.assert_allclose(lg.t, w.t)
    assert lg.fs == pytest.approx(w.fs, rel=1e-9)
    col = "sensor" if header else "0"
    assert any(f"the {len(w)} rows labelled 'ACC' in column '{col}' are the accelerometer's"
               f" (of {2 * len(w) + len(w) // 10} rows; the others: GYR {len(w)}, MAG "
               f"{len(w) // 10})" in n for n in lg.notes), lg.notes
    dw, _ = ac.io._stream_dwells(pw)
    dl, _ = ac.io._stream_dwells(pl)
    assert len(dl) == len(dw) == 16
    np.testing.assert_array_equal(dl.mean, dw.mean)
    # Compressed, the same log reads the same, under its own name.
    import gzip

    pz = tmp_path / "long.csv.gz"
    pz.write_bytes(gzip.compress(pl.read_bytes()))
    lz = read_stream(pz)
    np.testing.assert_array_equal(lz.samples, w.samples)
    assert lz.path == str(pz) and any("gzip-compressed" in n for n in lz.notes)
    # Comment lines anywhere (pandas reads through a filter that drops them, in pieces).
    lines = pl.read_text().splitlines(keepends=True)
    pc = tmp_path / "commented.csv"
    pc.write_text("# logger 1.2\n" + "".join(
        ln + ("% pause\n" if i % 997 == 0 else "// note\n" if i % 1499 == 0 else "")
        for i, ln in enumerate(lines)))
    lc = read_stream(pc)
    np.testing.assert_array_equal(lc.samples, w.samples)


def test_the_comment_filter_hands_out_pieces_of_the_uncommented_text() -> None:
    """The long-format reader's filter: any read sizes join to the text without its
    comment lines, a field's own '#' kept."""
    import io as _io

    text = "# head\na,b\n1,pose #3\n  % pct\n2,x\n// c\n3,y\n"
    want = "a,b\n1,pose #3\n2,x\n3,y\n"
    for size in (1, 2, 5, 7, 64, -1):
        f = ac.io._Uncommented(_io.StringIO(text))
        got = []
        while piece := f.read(size):
            assert size < 0 or len(piece) <= size
            got.append(piece)
        assert "".join(got) == want, size
    assert "".join(ac.io._Uncommented(_io.StringIO(text))) == want


def test_a_repeated_header_says_files_were_joined(tmp_path: Path) -> None:
    part = "".join(f"{i / 100:.2f},{i % 3},{i % 5},9.8\n" for i in range(500))
    p = write(tmp_path, "t,ax,ay,az\n" + part + "t,ax,ay,az\n" + part)
    st = read_stream(p)  # the header line is left out, and what it means is said
    assert len(st) == 1000
    assert any('(the first, line 502: column "t": "t" is not a number): the line repeats the '
               "header: files joined one after the other?" in n for n in st.notes), st.notes
    assert any("steps back 1 time(s)" in n for n in st.notes)
    _, rec = ac.io._stream_dwells(p, window_s=0.5, min_dwell_s=0.5)
    assert any("files joined" in n for n in rec.notes())


@pytest.mark.parametrize("kind", ["gzip", "bz2", "xz"])
def test_compressed_text_is_read(tmp_path: Path, kind: str) -> None:
    import bz2
    import gc
    import glob
    import gzip
    import lzma
    import os
    import tempfile

    x = _table(3000, 4)
    text = "t,ax,ay,az,temp\n" + "\n".join(",".join(r) for r in _fmt(x)) + "\n"
    plain = write(tmp_path, text)
    opener = {"gzip": gzip.open, "bz2": bz2.open, "xz": lzma.open}[kind]
    p = tmp_path / f"rec.csv.{kind}"
    with opener(p, "wt") as fh:
        fh.write(text)
    before = set(glob.glob(f"{tempfile.gettempdir()}/accelcal-*.txt"))
    s, ref = read_stream(p), read_stream(plain)
    np.testing.assert_array_equal(s.samples, ref.samples)
    assert s.fs == ref.fs and s.path == str(p)
    assert any(f"{kind}-compressed text" in n for n in s.notes)
    np.testing.assert_array_equal(np.concatenate([c for c, _ in iter_stream(p, chunk_rows=777)]),
                                  ref.samples)
    gc.collect()
    assert set(glob.glob(f"{tempfile.gettempdir()}/accelcal-*.txt")) == before  # cleaned up
    if os.path.isdir("/proc/self/fd"):
        # While a chunk is being read the expansion has no name in the temporary folder (a
        # killed process leaves nothing behind: SIGTERM left a 393 MB file there).
        it = iter_stream(p, chunk_rows=777)
        next(it)
        assert set(glob.glob(f"{tempfile.gettempdir()}/accelcal-*.txt")) == before
        np.testing.assert_array_equal(np.concatenate([c for c, _ in it]), ref.samples[777:])
    # A damaged archive is a clear error.
    bad = tmp_path / f"bad.csv.{kind}"
    bad.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])
    with pytest.raises(CalibrationError, match=rf"cannot decompress it \({kind}\)"):
        read_stream(bad)


def test_headerless_table_of_many_channels_finds_the_accelerometer_by_its_norm(
        tmp_path: Path) -> None:
    """A logger's headerless export: time, accelerometer (m/s^2), gyroscope, magnetometer and
    pressure. The accelerometer is the only three adjacent columns whose norm stays at 1 g,
    and it is taken with a note; the fit equals the one with the columns given."""
    from accelcal.sim.field import field_session

    truth = [1.002, 0.998, 1.001, 0.05, -0.03, 0.08, 0.001, 0.002, -0.001]
    s = field_session(fs=50.0, n_dwells=14, dwell_s=6.0, move_s=2.0, max_tilt_deg=80.0,
                      truth=truth, sigma=0.01, rng=4)
    rng = np.random.default_rng(0)
    n = len(s.t)
    gyro = 0.01 * rng.standard_normal((n, 3))
    mag = np.array([30.0, 5.0, -40.0]) + 0.5 * rng.standard_normal((n, 3))
    table = np.column_stack([s.t, s.samples, gyro, mag, np.full(n, 97.5)])
    p = tmp_path / "log.txt"
    np.savetxt(p, table, fmt="%.6f", delimiter="\t")
    st = read_stream(p)
    np.testing.assert_allclose(st.samples, np.round(s.samples, 6), atol=1e-9)
    assert st.fs == pytest.approx(50.0)
    assert any("columns 1, 2, 3 (0-based) taken as the accelerometer" in x and "m/s^2" in x
               for x in st.notes)
    auto = ac.fit_static(stream_dwells(p), s.g, observability="ignore")
    given = ac.fit_static(stream_dwells(p, columns=[1, 2, 3], time_column=0), s.g,
                          observability="ignore")
    np.testing.assert_array_equal(auto.vector, given.vector)
    assert np.all(np.abs(auto.vector - truth) < 5 * auto.std + 1e-12)
    # A head at rest with the z axis up: (ax, ay, az), (ay, az, gx) and (az, gx, gy) all
    # keep a norm of 1 g, so none is chosen, and the error names them.
    rest = np.column_stack([np.arange(300) / 50.0,
                            [0.02, -0.01, 9.81] + 0.01 * rng.standard_normal((300, 3)),
                            0.01 * rng.standard_normal((300, 3)), np.full(300, 97.5)])
    p2 = tmp_path / "rest.txt"
    np.savetxt(p2, rest, fmt="%.6f", delimiter="\t")
    with pytest.raises(CalibrationError, match=r"8 columns and no header row: cannot tell "
                       r"which are the accelerometer x, y, z \(each of the adjacent columns "
                       r"1,2,3; 2,3,4; 3,4,5 keeps a norm of about 1 g: 9\.81\d? m/s\^2\); "
                       r"give columns="):
        read_stream(p2)


def test_unnamed_accelerometer_columns_are_found_by_their_norm(tmp_path: Path) -> None:
    """A header whose names do not say accelerometer (``# time tx ty tz wx wy wz mx my mz qx
    qy qz qw``, a research IMU's log): the one adjacent triple at 1 g is taken, with a note;
    the unit quaternion's components (norm near 1) are not candidates."""
    from accelcal.sim.field import field_session

    truth = [1.001, 0.999, 1.002, 0.02, -0.04, 0.03, 0.001, -0.002, 0.001]
    s = field_session(fs=100.0, n_dwells=12, dwell_s=4.0, move_s=1.5, max_tilt_deg=70.0,
                      truth=truth, sigma=0.01, rng=6)
    rng = np.random.default_rng(1)
    n = len(s.t)
    gyro = 0.005 * rng.standard_normal((n, 3))
    mag = [0.2, -0.05, 0.4] + 0.01 * rng.standard_normal((n, 3))
    q = np.column_stack([0.02 * rng.standard_normal((n, 2)), 0.1 * rng.standard_normal(n),
                         np.ones(n)])
    q /= np.linalg.norm(q, axis=1)[:, None]
    p = tmp_path / "imu.txt"
    np.savetxt(p, np.column_stack([s.t, s.samples, gyro, mag, q]), fmt="%.6f",
               header="time tx ty tz wx wy wz mx my mz qx qy qz qw")
    st = read_stream(p)
    np.testing.assert_allclose(st.samples, np.round(s.samples, 6), atol=1e-9)
    assert st.fs == pytest.approx(100.0)
    assert any("columns 'tx', 'ty', 'tz' taken as the accelerometer x, y, z: no name says so"
               in x for x in st.notes)
    # Without a triple at 1 g the error stays, and names what it saw.
    p2 = tmp_path / "none.csv"
    np.savetxt(p2, np.column_stack([s.t, 0.5 * s.samples]), fmt="%.6f", delimiter=",",
               header="time,u,v,w", comments="")
    with pytest.raises(CalibrationError, match=r"no accelerometer columns recognised among "
                       r"\['time', 'u', 'v', 'w'\]; give columns="):
        read_stream(p2)


def test_signed_16_bit_values_stored_as_unsigned_are_read_as_signed(tmp_path: Path) -> None:
    """A flight computer's older log keeps the int16 registers as uint16 (65404 for -132).
    The accelerometer is found by its norm once read as signed, with a note, in a headerless
    file, under names and as a uint16 ``.npy``; the fit equals the one on the signed values.
    A 16-bit ADC that is unsigned by design (mid-scale 32768) is left as it is."""
    from accelcal.sim.field import field_session

    truth = [1.003, 0.997, 1.001, 0.04, -0.06, 0.02, 0.001, 0.002, -0.001]
    s = field_session(fs=100.0, n_dwells=14, dwell_s=4.0, move_s=1.5, max_tilt_deg=85.0,
                      truth=truth, sigma=0.02, rng=9)
    counts = np.round(s.samples / s.g * 2048.0).astype(np.int64)
    rng = np.random.default_rng(2)
    gyro = np.round(30.0 * rng.standard_normal((len(s.t), 3))).astype(np.int64)
    stored = np.column_stack([counts, gyro]) & 0xFFFF
    assert stored.min() >= 0 and stored.max() > 60000
    plain = tmp_path / "signed.txt"
    np.savetxt(plain, np.column_stack([s.t, counts]), fmt=["%.2f", "%d", "%d", "%d"])
    p = tmp_path / "unsigned.txt"
    np.savetxt(p, np.column_stack([s.t, stored]), fmt=["%.2f"] + ["%d"] * 6)
    st = read_stream(p)
    np.testing.assert_array_equal(st.samples, counts)
    assert any("columns 1, 2, 3 (0-based) hold signed 16-bit values stored as unsigned" in x
               and "counts at 2048/g" in x for x in st.notes)
    ref = ac.fit_static(stream_dwells(plain), 2048.0, observability="ignore", check_g=False)
    got = ac.fit_static(stream_dwells(p), 2048.0, observability="ignore", check_g=False)
    np.testing.assert_array_equal(got.vector, ref.vector)
    # Named columns, and an explicit choice of them, get the same reading.
    named = tmp_path / "named.csv"
    np.savetxt(named, np.column_stack([s.t, stored[:, :3]]), fmt=["%.2f", "%d", "%d", "%d"],
               delimiter=",", header="t,ax,ay,az", comments="")
    for kw in ({}, {"columns": ["ax", "ay", "az"]}):
        sn = read_stream(named, **kw)
        np.testing.assert_array_equal(sn.samples, counts)
        assert any("'ax', 'ay', 'az' hold signed 16-bit values stored as unsigned" in x
                   for x in sn.notes)
    # A uint16 array (a binary dump) is viewed as int16, without a copy of the file.
    npy = tmp_path / "raw.npy"
    np.save(npy, stored[:, :3].astype(np.uint16))
    sa = read_stream(npy, fs=100.0)
    assert sa.samples.dtype == np.int16
    np.testing.assert_array_equal(sa.samples, counts)
    # A z offset of half a g (SunDevil's Rev1 board: 24384 counts at z up, 16384/g): the norm
    # is not steady, so the columns are given, and the wrap is still seen and undone.
    big = np.round(s.samples / s.g * 16384.0 + [-132.0, 196.0, 8000.0]).astype(np.int64)
    p4 = tmp_path / "rev1.txt"
    np.savetxt(p4, np.column_stack([s.t, big & 0xFFFF, np.zeros(len(s.t))]),
               fmt=["%.3f", "%d", "%d", "%d", "%d"], delimiter="\t")
    s4 = read_stream(p4, columns=[1, 2, 3], time_column=0)
    np.testing.assert_array_equal(s4.samples, big)
    assert any("hold signed 16-bit values stored as unsigned" in x for x in s4.notes)
    # An ADC that is unsigned by design: 1 g is 2048 counts about mid-scale. Its norm is not
    # 1 g either way, so nothing is reinterpreted.
    adc = 32768 + counts
    p3 = tmp_path / "adc.csv"
    np.savetxt(p3, np.column_stack([s.t, adc]), fmt=["%.2f", "%d", "%d", "%d"],
               delimiter=",", header="t,ax,ay,az", comments="")
    s3 = read_stream(p3)
    np.testing.assert_array_equal(s3.samples, adc)
    assert not any("stored as unsigned" in x for x in s3.notes)


def test_a_named_time_column_that_does_not_count_time_is_not_the_time(tmp_path: Path) -> None:
    """A ground station's log names a GPS clock ``UTC`` that was never set (all zeros): it is
    not taken as the time (a note says why), so fs= gives the rate; ``time_column="none"``
    drops a time column on request (the CLI's ``--time-column none``)."""
    from accelcal.sim.field import field_session

    s = field_session(fs=20.0, n_dwells=12, dwell_s=6.0, move_s=2.0, max_tilt_deg=80.0,
                      sigma=0.01, rng=3)
    n = len(s.t)
    p = tmp_path / "gs.csv"
    np.savetxt(p, np.column_stack([np.full(n, 68.0), np.zeros(n), s.samples]),
               fmt="%.6f", delimiter=",", header="movement,UTC,accelX,accelY,accelZ",
               comments="")
    st = read_stream(p, fs=20.0)
    assert st.fs == 20.0 and st.t is not None
    np.testing.assert_allclose(st.t, np.arange(n) / 20.0)
    assert any("column 'UTC' is named as a time but holds 0 in every one of the first" in x
               for x in st.notes)
    with pytest.raises(CalibrationError, match="the sample rate is unknown"):
        stream_dwells(p)
    # A clock that runs backwards is refused when named, and dropped with "none".
    p2 = tmp_path / "back.csv"
    np.savetxt(p2, np.column_stack([s.t[::-1], s.samples]), fmt="%.6f", delimiter=",",
               header="time,ax,ay,az", comments="")
    with pytest.raises(CalibrationError, match=r"time_column= none"):
        read_stream(p2, time_column="time")
    st2 = read_stream(p2, fs=20.0, time_column="none")
    np.testing.assert_allclose(st2.t, np.arange(n) / 20.0)
    from accelcal.cli import main
    from click.testing import CliRunner

    r = CliRunner().invoke(main, ["dwells", str(p2), "--fs", "20", "--time-column", "none"])
    assert r.exit_code == 0 and "12 dwells" in r.output, r.output


@pytest.mark.parametrize("layout", ["imucal", "flags"])
def test_an_annotated_session_gives_its_labelled_sections_as_dwells(tmp_path: Path,
                                                                    layout: str) -> None:
    """imucal's annotated Ferraris session (``part,samples,acc_x,...``, rows grouped by part,
    so out of time order; rotations ``x_rot`` between the faces), or a static/moving flag per
    row: the static runs are the dwells, named by their label, in time order; the motions are
    left out with a note; the statistics equal dwell_stats on the same rows."""
    rng = np.random.default_rng(5)
    faces = {"x_p": [1, 0, 0], "x_a": [-1, 0, 0], "y_p": [0, 1, 0], "y_a": [0, -1, 0],
             "z_p": [0, 0, 1], "z_a": [0, 0, -1]}
    parts, blocks = [], []
    for name, f in faces.items():
        n = int(rng.integers(300, 600))
        blocks.append(np.round(2048 * np.array(f) + [12, -40, 25] + 6 * rng.standard_normal(
            (n, 3))))
        parts += [name] * n
        blocks.append(np.round(2048 * rng.uniform(-1, 1, (200, 3))))  # the turn after it
        parts += [f"{name[0]}_rot"] * 200
    acc = np.concatenate(blocks)
    n = len(acc)
    gyr = np.round(5 * rng.standard_normal((n, 3)))
    if layout == "imucal":
        label = np.array(parts)
        order = np.argsort(label, kind="stable")  # grouped by part, as imucal writes it
        text = "part,samples,acc_x,acc_y,acc_z,gyr_x,gyr_y,gyr_z\n" + "".join(
            f"{label[i]},{i},{acc[i, 0]:.1f},{acc[i, 1]:.1f},{acc[i, 2]:.1f},"
            f"{gyr[i, 0]:.1f},{gyr[i, 1]:.1f},{gyr[i, 2]:.1f}\n" for i in order)
        names = list(faces)
    else:
        label = np.array(["moving" if p.endswith("rot") else "static" for p in parts])
        text = "state,ax,ay,az\n" + "".join(
            f"{label[i]},{acc[i, 0]:.1f},{acc[i, 1]:.1f},{acc[i, 2]:.1f}\n" for i in range(n))
        names = ["static"] * 6
    p = write(tmp_path, text, "annotated.csv")
    d = stream_dwells(p)
    assert d.names == names
    cut = np.r_[0, np.flatnonzero(label[1:] != label[:-1]) + 1, n]
    bounds = [[a, b] for a, b in zip(cut[:-1], cut[1:], strict=True)
              if not label[a].endswith("rot") and label[a] != "moving"]
    ref = ac.dwell_stats(acc, bounds)
    np.testing.assert_array_equal(d.mean, ref.mean)
    np.testing.assert_allclose(d.var, ref.var, rtol=1e-12)
    st = read_stream(p)
    assert any("labels the session's sections" in x and "left out as motions" in x
               for x in st.notes)
    # The labels give the dwells, so a missing rate costs only their times.
    no_rate = [x for x in st.notes if x.startswith("the sample rate is not in the file")]
    assert len(no_rate) == 1 and "the dwells' times need it" in no_rate[0], st.notes
    fit = ac.fit_static(d, 9.81, model="diag")
    np.testing.assert_allclose(fit.vector[:3], 2048 / 9.81, rtol=2e-3)
    from accelcal.cli import main
    from click.testing import CliRunner

    r = CliRunner().invoke(main, ["dwells", str(p)])  # no rate: said, not a crash
    assert r.exit_code == 0 and f"{n} samples rate unknown -> 6 dwells" in r.output, r.output
    # The fleet reads it the same way.
    row = ac.calibrate_many([str(p)], g=9.81, model="diag", workers=1, progress=False).iloc[0]
    assert row["n_dwells"] == 6 and "labels the session's sections" in row["message"]
    np.testing.assert_allclose([row["sx"], row["sy"], row["sz"]], fit.vector[:3], rtol=1e-12)


def _rests_log(rng: np.random.Generator, poses: int = 40, block: int = 100,
               same: tuple[int, ...] = (7, 21)) -> tuple[np.ndarray, np.ndarray]:
    """A logger that stores ``block`` samples per pose in g (int16 steps of 1/16384 g) and
    nothing while the sensor is turned; the poses after those in ``same`` repeat them (no
    jump between the two blocks). Returns the samples and the true poses."""
    v = rng.standard_normal((poses, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for k in same:
        v[k + 1] = v[k]
    truth = v * [1.01, 0.99, 1.02] + [0.02, -0.01, 0.015]  # raw = K a + b, in g
    s = np.repeat(truth, block, axis=0) + 3e-3 * rng.standard_normal((poses * block, 3))
    return np.round(s * 16384) / 16384, truth


def test_a_log_that_holds_only_the_rests_gives_one_dwell_per_block(tmp_path: Path) -> None:
    """CK-Explorer's acc_log.csv (ax,ay,az in g, no time, 160 blocks of 100 samples, nothing
    recorded between poses): the window detector saw a rest no longer than its window and
    found no dwell ("raise --k", which could not help). The blocks are now the dwells, with
    no rate needed, and two poses with no jump between them are cut on the logger's grid.
    The fleet reads it the same way; a recording with its moves is left to the detector."""
    rng = np.random.default_rng(11)
    s, truth = _rests_log(rng)
    p = tmp_path / "acc_log.csv"
    np.savetxt(p, s, delimiter=",", header="ax,ay,az", comments="", fmt="%.7g")
    d, rec = ac.io._stream_dwells(p)
    assert len(d) == 40
    np.testing.assert_array_equal(np.column_stack([d.start, d.stop]),
                                  [[100 * k, 100 * (k + 1)] for k in range(40)])
    ref = dwell_stats(np.loadtxt(p, delimiter=",", skiprows=1), [[100 * k, 100 * k + 100]
                                                                 for k in range(40)])
    np.testing.assert_allclose(d.mean, ref.mean, rtol=0, atol=1e-15)
    notes = rec.notes()
    assert any("holds only the rests: 37 jumps" in n and "100 samples per pose" in n
               and "2 of them cut on the logger's grid" in n for n in notes), notes
    assert any("the dwells do not need it here" in n for n in notes), notes
    fit = ac.fit_static(d, 1.0)
    np.testing.assert_allclose(fit.vector[:6], [1.01, 0.99, 1.02, 0.02, -0.01, 0.015],
                               atol=3e-3)
    from accelcal.cli import main
    from click.testing import CliRunner

    r = CliRunner().invoke(main, ["calibrate", "static", str(p), "--g", "1", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["n_dwells"] == 40
    row = ac.calibrate_many([str(p)], g=1.0, workers=1, progress=False).iloc[0]
    assert row["n_dwells"] == 40 and "holds only the rests" in row["message"]
    np.testing.assert_allclose([row["sx"], row["sy"], row["sz"]], fit.vector[:3], rtol=1e-12)
    # detect_dwells (the window detector) finds none in it, and says where to turn.
    with pytest.raises(ac.DegenerateDataError, match=r"no static dwell found.*reads as a log "
                       r"that holds only the rests.*accelcal\.io\.step_log_dwells"):
        detect_dwells(s, 100.0)
    got = ac.io.step_log_dwells(s, None, None, None)
    assert got is not None and len(got[0]) == 40
    # The same poses with 2 s turns recorded between them: not a log of rests.
    from accelcal.sim.field import field_session

    f = field_session(fs=100.0, n_dwells=12, dwell_s=4.0, move_s=2.0, sigma=1e-3, rng=3)
    q = write_csv(tmp_path / "moves.csv", f.t, f.samples)
    d2, rec2 = ac.io._stream_dwells(q)
    assert not any("holds only the rests" in n for n in rec2.notes())
    assert len(d2) == len(detect_dwells(f.samples, f.fs))


def test_calibrate_given_a_recording_instead_of_a_system_says_which_command(
        tmp_path: Path) -> None:
    from accelcal.cli import main
    from click.testing import CliRunner

    p = write(tmp_path, "t,ax,ay,az\n0,0,0,9.8\n")
    r = CliRunner().invoke(main, ["calibrate", str(p), "--g", "9.81"])
    assert r.exit_code == 2
    assert (f"is a recording, not a system: name the system first, `accelcal calibrate static "
            f"{p} --g 9.81`") in r.output, r.output
    r = CliRunner().invoke(main, ["calibrate", "statc"])  # a typo is click's own error
    assert r.exit_code == 2 and "No such command 'statc'" in r.output


def test_a_fourth_column_names_the_temperature_of_a_headerless_file(tmp_path: Path) -> None:
    """SunDevil's table session: 13 columns, no header, the temperature in column 12. It
    could not be named, and the diagnosis said "no temperature was recorded". A fourth entry
    of columns= (--columns 1,2,3,4) is the temperature column."""
    from accelcal.sim.field import field_session

    f = field_session(fs=50.0, n_dwells=14, dwell_s=4.0, move_s=2.0, sigma=1e-3, rng=8)
    temp = 30.0 + np.linspace(0.0, 5.0, len(f.t))
    p = tmp_path / "headerless.txt"
    np.savetxt(p, np.column_stack([f.t, f.samples, temp]), delimiter="\t", fmt="%.9g")
    d = stream_dwells(p, columns="1,2,3,4", time_column=0)
    assert d.temperature is not None
    ref = dwell_stats(f.samples, np.column_stack([d.start, d.stop]), temperature=temp)
    np.testing.assert_allclose(d.temperature, ref.temperature, rtol=1e-9)  # %.9g in the file
    assert stream_dwells(p, columns=[1, 2, 3], time_column=0).temperature is None
    with pytest.raises(CalibrationError, match="temperature column .* is also an accel"):
        stream_dwells(p, columns="1,2,3,3", time_column=0)
    with pytest.raises(CalibrationError, match=r"exactly 3 columns \(x, y, z\), or 4"):
        stream_dwells(p, columns="1,2", time_column=0)
    from accelcal.cli import main
    from click.testing import CliRunner

    r = CliRunner().invoke(main, ["diagnose", str(p), "--g", f"{f.g}", "--columns", "1,2,3,4",
                                  "--time-column", "0"])
    assert r.exit_code == 0 and "no temperature given" not in r.output, r.output
    r = CliRunner().invoke(main, ["diagnose", str(p), "--g", f"{f.g}", "--columns", "1,2,3",
                                  "--time-column", "0"])
    assert "or as the 4th of the columns given (columns=, --columns)" in r.output, r.output


def test_a_serial_capture_preamble_is_skipped_with_a_note(tmp_path: Path) -> None:
    """A logger's banner and prompts before the data (an AltIMU serial capture: 'TURN SENSOR
    VERY SLOWLY AND CAREFULLY IN 3D') read as column names: "header has 1 names but data rows
    have 6 columns". Text without the data's delimiter is now a preamble, skipped with a
    note; a header that has the delimiter but the wrong count is still refused."""
    rows = "".join(f"{14800 + i},{3500 - i},{1500 + 2 * i},{-427},{-462},{-101}\n"
                   for i in range(50))
    pre = ("AltIMU-10 V3 calibration data collection\r\nGyro bias collection ... KEEP SENSOR "
           "STILL\r\nCollecting 300 points for scaling, 3/second\r\nTURN SENSOR VERY SLOWLY "
           "AND CAREFULLY IN 3D\r\n")
    p = write(tmp_path, pre + rows.replace("\n", "\r\n"))
    r = read_stream(p, fs=3.0, columns=[0, 1, 2])
    assert r.samples.shape == (50, 3) and r.samples[0, 0] == 14800
    assert any("before the first data row are text without its delimiter" in n
               and "a preamble, skipped" in n for n in r.notes), r.notes
    q = write(tmp_path, "t,ax,ay,az\n" + rows, name="bad.csv")
    with pytest.raises(CalibrationError, match="header has 4 names but data rows have 6"):
        read_stream(q, fs=3.0, columns=[0, 1, 2])


def test_text_on_the_last_line_is_named_as_a_trailer(tmp_path: Path) -> None:
    """A serial capture that ends with the logger's closing message ('Done. rms Acc =
    16384.66, ...'): the row is left out, and the note names the line and says it is the
    file's last; a line cut off at the file's end is said as such; text in the middle of the
    data gets neither hint. Text on the last line of a file that does not read otherwise
    (more rows that do not parse) gets the command that deletes it."""
    from accelcal.io import _trailer_hint

    rows = "".join(f"{i * 0.1:.1f},0.01,0.02,9.8\n" for i in range(40))
    p = write(tmp_path, "t,ax,ay,az\n" + rows + "Done. rms Acc = 1.0, rms Mag = 2.0\n\n")

    def note(path: Path) -> str:
        st = read_stream(path)
        assert len(st) == 40
        return next(n for n in st.notes if "do not parse" in n)

    assert "(the first, line 42: " in note(p) and note(p).endswith(
        "the file's last line: text after the data (a logger's closing message)?")
    cut = write(tmp_path, "t,ax,ay,az\n" + rows + "4.0,0.01,0.", name="cut.csv")
    assert "the file's last line, cut off (no line end)" in note(cut)
    q = write(tmp_path, "t,ax,ay,az\n" + rows + "pause\n" + rows.replace("0.01", "0.02"),
              name="mid.csv")
    st = read_stream(q)
    assert len(st) == 80 and not any("last line" in n for n in st.notes)
    assert _trailer_hint(str(p), "line 42: column \"t\": \"Done. rms Acc\" is not a number") \
        .endswith("sed '42d' FILE > data.csv)")


@pytest.mark.parametrize(("name", "scale"), [("ustime", 1e-6), ("ms_time", 1e-3),
                                             ("timeus", 1e-6), ("us-timestamp", 1e-6)])
def test_a_time_column_with_its_unit_glued_on_is_the_time(tmp_path: Path, name: str,
                                                          scale: float) -> None:
    """A logger's 'ustime' column (micros() of a 150 Hz MPU-6050 log) was not taken for the
    time: "the sample rate is unknown". A unit glued to 'time' is now read as the time, in
    that unit."""
    step = 6.6e-3 / scale  # 6.6 ms in the column's unit
    rows = "".join(f"{2314922586 + i * step:.0f} 45 -65 -44 -16531 -126 1133\n"
                   for i in range(400))
    p = write(tmp_path, f"{name} gx gy gz ax ay az\n" + rows)
    r = read_stream(p, columns=[4, 5, 6])
    assert r.fs == pytest.approx(1 / 6.6e-3, rel=1e-3)
    assert r.t is not None and (r.t[-1] - r.t[0]) / 399 == pytest.approx(6.6e-3, rel=1e-3)


def _stamped_log(tmp_path: Path, t: Any, name: str) -> Path:
    x = np.random.default_rng(2).normal(0, 0.01, (t.size, 3)) + [0, 0, 9.81]
    p = tmp_path / name
    np.savetxt(p, np.column_stack([t, x]), delimiter=",", header="time_s,ax,ay,az",
               comments="", fmt="%.6f")
    return p


def test_samples_lost_from_the_time_column_are_said(tmp_path: Path) -> None:
    t = np.arange(30_000) / 100.0
    keep = np.ones(t.size, bool)
    keep[20_000:20_050] = False  # 50 samples lost after 200 s
    keep[25_000:25_004] = False  # and 4 more
    st = read_stream(_stamped_log(tmp_path, t[keep], "lost.csv"))
    gaps = [n for n in st.notes if "skips" in n]
    assert len(gaps) == 1, st.notes
    assert ("skips 2 time(s) by more than 3 sample intervals (the longest 510 ms, between "
            "data rows 20000 and 20001; about 54 samples") in gaps[0]
    # The same when streamed in blocks that cut the gap.
    assert any("about 54 samples" in n for n in
               ac.io._stream_dwells(_stamped_log(tmp_path, t[keep], "lost2.csv"),
                                    chunk_rows=20_000)[1].notes())


@pytest.mark.parametrize("kind", ["clean", "jitter", "bursts"])
def test_a_time_column_without_lost_samples_gives_no_gap_note(tmp_path: Path,
                                                              kind: str) -> None:
    rng = np.random.default_rng(3)
    t = np.arange(30_000) / 100.0
    if kind == "jitter":  # +-40 % of an interval
        t = t + rng.uniform(-0.004, 0.004, t.size)
    elif kind == "bursts":  # stamped 5 samples at a time (a radio link's packets)
        t = np.repeat(t[::5], 5)
    st = read_stream(_stamped_log(tmp_path, t, f"{kind}.csv"))
    assert st.fs == pytest.approx(100.0, rel=1e-2)
    assert not any("skips" in n for n in st.notes), st.notes


def test_a_stray_first_line_of_a_serial_capture_is_skipped(tmp_path: Path) -> None:
    rows = "".join(f"{61153 + 52 * i},0.05,1.00,-0.04\n" for i in range(300))
    for head in ("04\n", "1.00,-0.04\n", "t_ms,ax,ay,az\n04\n"):
        st = read_stream(write(tmp_path, head + rows), time_column="0 [ms]")
        assert len(st) == 300 and st.fs == pytest.approx(1000 / 52)
        assert any("split unlike the rows after them (4 fields): a logger's leftovers, "
                   "skipped" in n for n in st.notes), st.notes
    # A first line like the rest is data, whatever follows it.
    st = read_stream(write(tmp_path, rows), time_column="0 [ms]")
    assert len(st) == 300 and not any("leftovers" in n for n in st.notes)


def test_a_unit_in_the_column_names_is_checked_against_the_norms() -> None:
    from accelcal.io import declared_units_note

    g_names = ("aX (g)", "aY (g)", "aZ (g)")
    assert "the outputs look like m/s^2" in declared_units_note(g_names, 9.88)
    assert declared_units_note(g_names, 1.01) == ""
    assert declared_units_note(("acc_x [m/s^2]", "acc_y [m/s^2]", "acc_z [m/s^2]"), 9.8) == ""
    assert "look like g" in declared_units_note(("ax_mps2", "ay_mps2", "az_mps2"), 1.0)
    assert "(raw counts?)" in declared_units_note(("ax_g", "ay_g", "az_g"), 16384.0)
    assert declared_units_note(("ax", "ay", "az"), 16384.0) == ""  # no unit declared
    assert declared_units_note(("ax (g)", "ay [m/s^2]", "az"), 9.8) == ""  # no single unit


def test_rows_of_label_value_pairs_are_read_by_their_labels(tmp_path: Path) -> None:
    """A serial monitor's log, `Ax 0.00 Ay -1.23 Az -10.12` per line (cuspaceflight/kestrel's
    acc_data.txt): "no numeric data rows found", whatever --columns. Now the labels name the
    columns (also `ax: 1.0, ay: ...` and `t=0.01 ax=...`), a line of other text is left out
    with a note, and a file that is mostly other text is still refused."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(40, 3)).round(2)
    p = write(tmp_path, "".join(f"Ax {a:.2f} Ay {b:.2f} Az {c:.2f}\n" for a, b, c in x),
              "acc_data.txt")
    s = read_stream(p, fs=10.0)
    np.testing.assert_array_equal(s.samples, x)
    assert any("rows of label-value pairs (Ax, Ay, Az)" in n for n in s.notes), s.notes
    text = "MPU6050 ready\n" + "".join(
        f"t={i / 100:.2f}, ax: {a:.2f}, ay: {b:.2f}, az: {c:.2f}\n" for i, (a, b, c) in
        enumerate(x))
    s = read_stream(write(tmp_path, text, "serial.log"))
    np.testing.assert_array_equal(s.samples, x)
    assert s.fs == pytest.approx(100.0)
    assert any("1 row(s) of other text left out" in n for n in s.notes), s.notes
    # A unit after each number (`Ax: 0.88 g`, `Ax: 8.64 m/s2`): skipped, not read as a label.
    for unit in ("g", "m/s2", "m/s^2"):
        text = "".join(f"Ax: {a:.2f} {unit}  Ay: {b:.2f} {unit}  Az: {c:.2f} {unit}\n"
                       for a, b, c in x)
        s = read_stream(write(tmp_path, text, "units.txt"), fs=10.0)
        np.testing.assert_array_equal(s.samples, x)
    mostly = "".join(f"reading {i}\n" for i in range(20)) + "Ax 1 Ay 2 Az 3\n" * 5
    with pytest.raises(CalibrationError, match=r"label-value pairs \(Ax Ay Az\) in only 5 of "
                       r"its 25 rows"):
        read_stream(write(tmp_path, mostly, "mostly.txt"), fs=10.0)


def test_adafruit_example_rows_name_their_sensor(tmp_path: Path) -> None:
    """The Adafruit sensor libraries' examples print `Acceleration X: 0.11, Y: -0.18, Z: 10.16
    m/s^2`, then `Rotation X: ...` and `Temperature: 25.3 degC` (MPU-6050), or `\t\tAccel X:
    ...` (LSM6DS): "no numeric data rows found". Now the sensor's name prefixes the labels, the
    accelerometer's rows are read however many rows of other sensors sit between them, and a
    decimal comma is read too."""
    rng = np.random.default_rng(1)
    x = rng.normal(size=(40, 3)).round(2)
    mpu = "".join(f"Acceleration X: {a:.2f}, Y: {b:.2f}, Z: {c:.2f} m/s^2\n"
                  f"Rotation X: 0.01, Y: {-b / 9:.2f}, Z: 0.00 rad/s\nTemperature: 25.3 degC\n\n"
                  for a, b, c in x)
    s = read_stream(write(tmp_path, "Adafruit MPU6050 test!\nMPU6050 Found!\n" + mpu,
                          "mpu.txt"), fs=10.0)
    np.testing.assert_array_equal(s.samples, x)
    note = next(n for n in s.notes if "label-value pairs" in n)
    assert "(Acceleration X, Acceleration Y, Acceleration Z)" in note, note
    assert "40 row(s) of other sensors' pairs (Rotation) left out" in note, note
    assert "42 row(s) of other text left out" in note, note  # 2 + 40 temperatures
    lsm = "".join(f"\t\tAccel X: {a:.2f} \tY: {b:.2f} \tZ: {c:.2f} m/s^2 \n"
                  f"\t\tGyro X: 0.01 \tY: 0.02 \tZ: 0.03 radians/s \n" for a, b, c in x)
    s = read_stream(write(tmp_path, lsm, "lsm.txt"), fs=10.0)
    np.testing.assert_array_equal(s.samples, x)
    dc = "".join(f"Acceleration X: {a:.2f}; Y: {b:.2f}; Z: {c:.2f} m/s^2\n".replace(".", ",")
                 for a, b, c in x)
    s = read_stream(write(tmp_path, dc, "dc.txt"), fs=10.0)
    np.testing.assert_array_equal(s.samples, x)
    # Another sensor's name does not lift the rule: mostly other rows is still refused.
    other = "".join(f"Magnetic X: {a:.2f}, Y: {b:.2f}, Z: {c:.2f} uT\n" for a, b, c in x)
    with pytest.raises(CalibrationError, match=r"write the accelerometer's rows to a file"):
        read_stream(write(tmp_path, other + "Gyro X: 1, Y: 2, Z: 3\n" * 60, "mag.txt"),
                    fs=10.0)


def test_more_sketch_outputs_are_read_by_their_labels(tmp_path: Path) -> None:
    """Rows that real sketches print and that were refused ("labels repeat", "no numeric data
    rows found") or read wrong: the LIS3DH example's raw counts and m/s^2 on one line (labels
    X, Y, Z twice) or on alternate lines (read as one stream of both), SparkFun's BMI270
    (`Acceleration in g's\tX: ...\tRotation in deg/sec\tX: ...`) and `Accel: X=... Gyro:
    X=...`, SparkFun's ICM-20948 (`Scaled. Acc (mg) [ x, y, z ], Gyr (DPS) [ ... ]`), units
    attached or not in the short list (`0.01g`, `LSB`, `[m/s^2]`), a row cut short before its
    unit (its Z read as 1), and a `c0,c1,c2` header taken for pairs c 0, c 1, c 2."""
    rng = np.random.default_rng(2)
    x = rng.normal(size=(40, 3)).round(4)
    raw = (x * 1000).round()

    def read(text: str, name: str, **kw: Any) -> Any:
        return read_stream(write(tmp_path, text, name), fs=10.0, **kw)

    same = "".join(f"X:  {r[0]:.0f}  \tY:  {r[1]:.0f}  \tZ:  {r[2]:.0f}\t\tX: {a:.4f} \tY: "
                   f"{b:.4f} \tZ: {c:.4f}  m/s^2 \n" for r, (a, b, c) in zip(raw, x, strict=True))
    s = read("LIS3DH test!\n" + same, "lis.txt")
    np.testing.assert_array_equal(s.samples, x)
    assert any("the accelerometer's: X.2, Y.2, Z.2" in n for n in s.notes), s.notes
    np.testing.assert_array_equal(read(same, "lis1.txt", columns="X,Y,Z").samples, raw)
    alt = "".join(f"X:  {r[0]:.0f}  \tY:  {r[1]:.0f}  \tZ:  {r[2]:.0f}\nX: {a:.4f} \tY: "
                  f"{b:.4f} \tZ: {c:.4f}  m/s^2 \n" for r, (a, b, c) in zip(raw, x, strict=True))
    s = read(alt, "alt.txt")
    np.testing.assert_array_equal(s.samples, x)
    assert any("40 row(s) of the same labels without the unit" in n for n in s.notes), s.notes
    bmi = "".join(f"Acceleration in g's\tX: {a:.4f}\tY: {b:.4f}\tZ: {c:.4f}\tRotation in "
                  f"deg/sec\tX: 0.1\tY: 0.2\tZ: 0.3\n" for a, b, c in x)
    np.testing.assert_array_equal(read("BMI270 connected!\n" + bmi, "bmi.txt").samples, x)
    eq = "".join(f"Accel: X={a:.4f} Y={b:.4f} Z={c:.4f}\tGyro: X=1 Y=2 Z=3\n" for a, b, c in x)
    np.testing.assert_array_equal(read(eq, "eq.txt").samples, x)
    icm = "".join(f"Scaled. Acc (mg) [ {a:.4f}, {b:.4f}, {c:.4f} ], Gyr (DPS) [ 0.1, -0.3, 0.5 "
                  f"], Mag (uT) [ 12.0, -22.5, 40.1 ], Tmp (C) [ 25.12 ]\n" for a, b, c in x)
    s = read(icm, "icm.txt")
    np.testing.assert_array_equal(s.samples, x)
    np.testing.assert_array_equal(s.temperature, np.full(40, 25.12))
    for unit in ("g", "LSB", "[m/s^2]", "counts"):
        sep = "" if unit == "g" else " "
        text = "".join(f"X: {a:.4f}{sep}{unit} Y: {b:.4f}{sep}{unit} Z: {c:.4f}{sep}{unit}\n"
                       for a, b, c in x)
        np.testing.assert_array_equal(read(text, "u.txt").samples, x)
    cut = "".join(f"Acceleration X: {a:.4f}, Y: {b:.4f}, Z: {c:.4f} m/s^2\n" for a, b, c in x)
    s = read(cut + "Acceleration X: 0.11, Y: -0.18, Z: 1\n", "cut.txt")
    np.testing.assert_array_equal(s.samples, x)  # the cut row's Z of 1 is not read
    ones = np.abs(rng.normal(size=(40, 3))) * 0.01 + [0, 0, 1]
    p = write(tmp_path, "c0,c1,c2\n" + "".join(f"{a},{b},{c}\n" for a, b, c in ones), "c.csv")
    np.testing.assert_array_equal(read_stream(p, fs=10.0).samples, ones)  # no label pairs


@pytest.mark.parametrize("suffix", [".parquet", ".feather"])
def test_parquet_and_feather_tables_are_read_by_their_column_names(tmp_path: Path,
                                                                  suffix: str) -> None:
    """A logger that writes Parquet (or Feather): "no numeric data rows found", the binary
    file read as text. Now read through pyarrow as a DataFrame: columns by name, a timestamp
    column as the time, a temperature column; a broken file names its format."""
    import pandas as pd  # the [parquet] extra; installed by make test
    rng = np.random.default_rng(5)
    n = 500
    df = pd.DataFrame({"timestamp": pd.date_range("2024-03-01T12:00:00Z", periods=n,
                                                  freq="4ms"),
                       "gyr_x": rng.normal(size=n), "acc_x": rng.normal(size=n),
                       "acc_y": rng.normal(size=n), "acc_z": 9.8 + rng.normal(size=n),
                       "temp_c": np.linspace(20, 25, n)})
    p = tmp_path / f"rec{suffix}"
    getattr(df, "to_" + suffix[1:])(p)
    s = read_stream(p)
    np.testing.assert_array_equal(s.samples, df[["acc_x", "acc_y", "acc_z"]].to_numpy())
    assert s.fs == pytest.approx(250.0) and s.t0.startswith("2024-03-01T12:00:00")
    np.testing.assert_allclose(s.t, np.arange(n) * 0.004, atol=1e-9)
    np.testing.assert_array_equal(s.temperature, df["temp_c"].to_numpy())
    (tmp_path / f"bad{suffix}").write_text("ax,ay,az\n1,2,3\n")
    with pytest.raises(CalibrationError, match=r"bad\.\w+: cannot read the (Parquet|Feather) "
                                               r"file"):
        read_stream(tmp_path / f"bad{suffix}")


def test_a_clock_in_ms_beside_a_rate_given_is_named_not_called_lost_samples(
        tmp_path: Path) -> None:
    """`t=10, 20, ...` (ms) read in s beside --fs 100: "the logger lost samples ... 99.9 %
    missing", which was false. Now the note names the unit that fits, with or without a
    header; a real gap is still a gap."""
    t = np.arange(3000) * 10.0
    x = np.array([0.0, 0.0, 9.8]) + 0.01 * np.random.default_rng(0).standard_normal((3000, 3))
    body = "".join(f"{a:g},{b:.5f},{c:.5f},{d:.5f}\n" for a, (b, c, d) in zip(t, x, strict=True))
    for text, name in (("t,ax,ay,az\n" + body, "t"), (body, "0")):
        s = read_stream(write(tmp_path, text), fs=100.0)
        assert not any("lost samples" in n for n in s.notes), s.notes
        assert any("looks like a clock in ms read in s" in n and f"'{name} [ms]'" in n
                   for n in s.notes), s.notes
    ts = np.arange(3000) / 100.0
    ts[1500:] += 2.0  # 2 s lost
    body = "".join(f"{a:.2f},{b:.5f},{c:.5f},{d:.5f}\n" for a, (b, c, d) in
                   zip(ts, x, strict=True))
    s = read_stream(write(tmp_path, "t,ax,ay,az\n" + body), fs=100.0)
    assert any("the logger lost samples" in n for n in s.notes), s.notes


def six_faces_ms(path: Path, rng: np.random.Generator, bump: tuple[int, int] | None = None,
                 n: int = 207) -> np.ndarray:
    """Six faces logged one file each and joined (the softdream recording): ``t_ms ax ay az``
    in g, no header, about 84.45 Hz, the clock restarting near 1000 ms at each face (it steps
    back 5 times), nothing recorded between the faces. ``bump`` (face, axis): a 0.1 g knock
    (Gaussian, 4 samples std) within that face's run. Returns the table written."""
    k, b = np.array([1.005, 1.002, 1.01]), np.array([0.03, 0.004, -0.053])
    faces = np.array([[0, 0, 1], [0, 0, -1], [0, 1, 0], [0, -1, 0], [1, 0, 0], [-1, 0, 0]],
                     dtype=np.float64)
    rows = []
    for j, f in enumerate(faces):
        s = k * f + b + 3e-3 * rng.standard_normal((n, 3))
        if bump is not None and j == bump[0]:
            s[:, bump[1]] += 0.1 * np.exp(-0.5 * ((np.arange(n) - 120) / 4.0) ** 2)
        t = int(rng.integers(1000, 1100)) + np.round(np.arange(n) * 1000 / 84.45)
        rows.append(np.column_stack([t, s]))
    table = np.vstack(rows)
    np.savetxt(path, table, fmt=["%d", "%.6f", "%.6f", "%.6f"], delimiter=" ")
    return table


def test_a_run_that_varies_far_more_than_the_others_is_named(tmp_path: Path) -> None:
    """softdream's joined faces: read as a log of rests, each run is taken whole, and in
    right.txt's a 0.15 g knock made its std on y 4x the others' (0.0138 against 0.0033)
    with nothing said. The run and the axis are now named (by dwells, calibrate static and
    the fleet alike); the samples used stay the same."""
    from accelcal.cli import main
    from click.testing import CliRunner

    p = tmp_path / "faces.txt"
    six_faces_ms(p, np.random.default_rng(1), bump=(3, 1))
    table = np.loadtxt(p)
    d, rec = ac.io._stream_dwells(p)
    runs = [[207 * j, 207 * (j + 1)] for j in range(6)]
    ref = dwell_stats(table[:, 1:], runs)  # the runs whole, as before
    np.testing.assert_array_equal(np.column_stack([d.start, d.stop]), runs)
    np.testing.assert_allclose(d.mean, ref.mean, rtol=0, atol=1e-15)
    std = np.sqrt(ref.var)
    others = np.median(np.delete(ref.var[:, 1], 3))
    said = (f"dwell 3 (start 621, stop 828) varies far more than the other runs on y: sample "
            f"std {std[3, 1]:.3g} against a median {np.sqrt(others):.3g} over the others "
            f"({ref.var[3, 1] / others:.3g}x the variance, std in the file's units)")
    assert any(n.startswith(said) and "look at the dwells plot" in n for n in rec.notes()), \
        rec.notes()
    for args in (["dwells", str(p)], ["calibrate", "static", str(p), "--g", "1", "--model",
                                      "diag"]):
        r = CliRunner().invoke(main, args)
        assert r.exit_code == 0 and said in r.output and "dwell bounds (--bounds)" in r.output, \
            r.output
    row = ac.calibrate_many([str(p)], g=1.0, model="diag", workers=1,
                            progress=False).iloc[0]
    assert said in row["message"], row["message"]
    # The same faces without the knock: every run alike, nothing said.
    q = tmp_path / "calm.txt"
    six_faces_ms(q, np.random.default_rng(1))
    _, rec2 = ac.io._stream_dwells(q)
    assert any("holds only the rests" in n for n in rec2.notes())
    assert not any("varies far more" in n for n in rec2.notes()), rec2.notes()


def test_columns_found_by_their_norm_say_the_median_norm_in_the_files_units(
        tmp_path: Path) -> None:
    """"(1.003, g)" said neither what 1.003 was nor what g meant there."""
    p = tmp_path / "faces.txt"
    six_faces_ms(p, np.random.default_rng(2))
    table = np.loadtxt(p)
    level = float(np.median(np.linalg.norm(table[:, 1:], axis=1)))
    notes = read_stream(p).notes
    said = (f"the only three adjacent columns whose norm stays near 1 g (median norm "
            f"{level:.4g} in the file's units: about 1 g if they are g) over the first")
    assert any(said in n for n in notes), notes
    # Read in m/s^2: the same note names that unit.
    q = tmp_path / "mps2.txt"
    ms = table.copy()
    ms[:, 1:] *= 9.80665
    np.savetxt(q, ms, fmt=["%d", "%.5f", "%.5f", "%.5f"], delimiter=" ")
    level = float(np.median(np.linalg.norm(np.loadtxt(q)[:, 1:], axis=1)))
    assert any(f"(median norm {level:.4g} in the file's units: about 1 g if they "
               "are m/s^2)" in n for n in read_stream(q).notes)


def test_a_transposed_array_is_named_as_such(tmp_path: Path) -> None:
    """A (3, N) array saved by mistake: the error says it looks transposed and how to fix it
    (it only spoke of N columns and no header row); saved as its transpose it reads as the
    session, and its dwells give the truth."""
    from accelcal.sim import field_session

    s = field_session(fs=500.0, n_dwells=12, dwell_s=4.0, move_s=2.0, rng=1)
    for name, a in (("x.npy", s.samples.T), ("xt.npy", np.vstack([s.t, s.samples.T]))):
        np.save(tmp_path / name, a)
        with pytest.raises(CalibrationError, match=r"\(\d, N\) array .* transposed: save a\.T"):
            read_stream(tmp_path / name, fs=s.fs)
    with pytest.raises(CalibrationError, match=r"looks like a \(3, N\) array.*samples\.T"):
        detect_dwells(s.samples.T, s.fs)
    np.save(tmp_path / "ok.npy", s.samples.T.T)
    st = read_stream(tmp_path / "ok.npy", fs=s.fs)
    np.testing.assert_array_equal(st.samples, s.samples)
    fit = ac.fit_static(detect_dwells(st), s.g, observability="ignore")
    assert np.all(np.abs(fit.vector - s.truth) < 5 * fit.std)


OOM_PUSH = """
import resource, sys
import numpy as np
from accelcal._core import RawDwellAccumulator

acc = RawDwellAccumulator(fs=100.0, block_s=0.02)  # a block every 2 samples
x = np.zeros((500_000, 3))
x[:, 2] = 9.81
acc.push(x)
with open("/proc/self/status") as fh:
    vm = next(int(ln.split()[1]) for ln in fh if ln.startswith("VmSize:")) * 1024
resource.setrlimit(resource.RLIMIT_AS, (vm + (200 << 20), resource.RLIM_INFINITY))
pushed = acc.position
try:
    for _ in range(400):
        acc.push(x)
        pushed = acc.position
except MemoryError as e:
    print("MemoryError:", e)
    print("unchanged" if acc.position == pushed else "changed")
    sys.exit(0)
print("no error")
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_AS, /proc")
def test_core_out_of_memory_is_a_memory_error_not_an_abort() -> None:
    """The dwell detector's block statistics grew until the allocator failed, which aborted
    the process ('memory allocation of N bytes failed', exit 134)."""
    import subprocess

    r = subprocess.run([sys.executable, "-c", OOM_PUSH], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, (r.returncode, r.stderr[-1000:])
    assert "MemoryError: out of memory: the dwell detector's block statistics" in r.stdout
    assert "bytes)" in r.stdout and "unchanged" in r.stdout, r.stdout
