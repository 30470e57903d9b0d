"""Fleet calibration: calibrate_many on simulated fleets (local pool, in-process, Dask), the
written table and calibration files, the fleet report, and the command line end to end."""

from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import accelcal as ac
import numpy as np
import pandas as pd
import pytest
from accelcal.cli import main
from accelcal.fleet import read_fleet_table
from accelcal.sim.fleet import CORRUPTIONS, fleet_recordings, random_calibration
from accelcal.sim.static import G0
from click.testing import CliRunner
from conftest import clipped_session, vibrating_session, write_csv

N = 32
OUTLIER = 3  # this sensor's sx is 12 fleet-sigma high
PARAMS = ["sx", "sy", "sz", "bx", "by", "bz", "m1", "m2", "m3"]
# What each corruption must be reported as, and words the message must contain. NaN rows are
# dropouts: left out of the dwell statistics (as in the single-file commands), with a note.
# A row that does not parse (the half-written last line of a file whose copy stopped, a line
# with an extra field) is left out with a note, as in the single-file commands.
CALIBRATED = {"nan_rows", "truncated", "wrong_columns"}
EXPECTED = {
    "garbled": ("error", r"line \d+: .*\"ERR\" is not a number \(\d+ of the \d+ data rows "
                         r"do not parse"),
    "truncated": ("weak", r"^1 data row\(s\) that do not parse .*the file's last line, cut off"),
    "nan_rows": ("ok", r"^3 of \d+ data rows hold NaN or inf samples \(dropouts\)"),
    "wrong_columns": ("ok", r"^1 data row\(s\) that do not parse .*5 fields where the data "
                            r"rows have 4"),
    "few_poses": ("degenerate", r"\b5 dwells\b"),
}


def _digest(paths: list[str]) -> dict[str, tuple[str, int]]:
    return {p: (hashlib.sha256(Path(p).read_bytes()).hexdigest(), os.stat(p).st_mtime_ns)
            for p in paths}


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    root = tmp_path_factory.mktemp("fleet")
    rng = np.random.default_rng(11)
    truths = np.array([random_calibration(rng) for _ in range(N)])
    truths[OUTLIER, 0] += 0.25
    recs = fleet_recordings(root / "rec", N, truths=truths, corrupt=5 / N, seed=3)
    paths = [r.path for r in recs]
    before = _digest(paths)
    df = ac.calibrate_many(sorted(paths), g=G0, out=root / "cals", workers=2, progress=False)
    return {"root": root, "recs": recs, "df": df, "before": before}


def test_one_row_per_recording_in_input_order_none_lost(fleet: dict[str, Any]) -> None:
    df, recs = fleet["df"], fleet["recs"]
    assert list(df["path"]) == sorted(r.path for r in recs)
    assert list(df["sensor_id"]) == [Path(p).stem for p in df["path"]]
    assert set(df["status"]) <= set(ac.fleet.STATUSES)
    # Two local processes did the work, not this one.
    workers = {w.split(":")[1] for w in df["worker"]}
    assert len(workers) == 2 and str(os.getpid()) not in workers


def test_parameters_match_the_simulator_truth_within_their_std(fleet: dict[str, Any]) -> None:
    df = fleet["df"].set_index("sensor_id")
    z = []
    for r in fleet["recs"]:
        if r.corruption and r.corruption not in CALIBRATED:
            continue
        row = df.loc[r.sensor_id]
        assert row["status"] == EXPECTED.get(r.corruption, ("ok",))[0], row["message"]
        # a dropout inside a dwell does not split it; a truncated file holds half the dwells
        assert row["n_dwells"] == (12 if r.corruption == "truncated" else 24)
        assert row["dropped_rows"] == (3 if r.corruption == "nan_rows" else 0)
        est = row[PARAMS].to_numpy(float)
        std = row[[f"{p}_std" for p in PARAMS]].to_numpy(float)
        assert np.all(std > 0)
        z.append((est - r.truth) / std)
        # residual RMS of the dwell norms: the simulated noise averaged over a dwell
        assert 0 < row["rms_mps2"] < 2e-3
    zz = np.array(z)
    assert np.abs(zz).max() < 4.5
    assert 0.6 < np.sqrt(np.mean(zz**2)) < 1.5


def test_every_corrupted_recording_is_reported_with_its_problem(fleet: dict[str, Any]) -> None:
    df = fleet["df"].set_index("sensor_id")
    kinds = [r.corruption for r in fleet["recs"] if r.corruption]
    assert sorted(kinds) == sorted(CORRUPTIONS)
    for r in fleet["recs"]:
        row = df.loc[r.sensor_id]
        if not r.corruption:
            assert row["message"] == ""
            continue
        status, pattern = EXPECTED[r.corruption]
        assert row["status"] == status, (r.corruption, row["message"])
        assert re.search(pattern, row["message"]), (r.corruption, row["message"])
        if r.corruption in CALIBRATED:
            assert np.isfinite(row[PARAMS].to_numpy(float)).all()
            assert row["cal_file"] != ""
        else:
            assert np.isnan(row[PARAMS].to_numpy(float)).all()
            assert row["cal_file"] == ""


def test_the_table_on_disk_equals_the_returned_one(fleet: dict[str, Any]) -> None:
    df = fleet["df"]
    cals = fleet["root"] / "cals"
    pd.testing.assert_frame_equal(pd.read_parquet(cals / "fleet.parquet"), df)
    pd.testing.assert_frame_equal(read_fleet_table(cals / "fleet.parquet"), df)
    pd.testing.assert_frame_equal(read_fleet_table(cals / "fleet.csv"), df, check_dtype=False)
    assert not list(cals.glob(".*.tmp"))


def test_one_calibration_file_per_calibrated_sensor(fleet: dict[str, Any]) -> None:
    df = fleet["df"]
    cals = fleet["root"] / "cals"
    ok = df[df["status"].isin(["ok", "weak"])]
    assert sorted(p.name for p in cals.glob("*.json")) == sorted(
        Path(p).name for p in ok["cal_file"])
    for r in ok.itertuples():
        assert re.fullmatch(rf"{r.sensor_id}_\d{{8}}T\d{{6}}Z\.json", Path(r.cal_file).name)
        m = ac.TriadModel.load(r.cal_file)
        assert m.sensor_id == r.sensor_id
        np.testing.assert_allclose(m.vector, [getattr(r, p) for p in PARAMS], rtol=1e-14)
        assert m.metadata["source"] == r.path


def test_nothing_the_user_gave_is_modified(fleet: dict[str, Any]) -> None:
    assert _digest(list(fleet["before"])) == fleet["before"]
    assert sorted(p.name for p in (fleet["root"] / "rec").iterdir()) == sorted(
        Path(p).name for p in fleet["before"])


def test_in_process_run_gives_the_pool_results(fleet: dict[str, Any]) -> None:
    paths = [r.path for r in fleet["recs"][:6]]
    one = ac.calibrate_many(paths, g=G0, workers=1, progress=False)
    assert set(one["worker"]) == {f"{os.uname().nodename}:{os.getpid()}"}
    pool = fleet["df"].set_index("path").loc[paths]
    np.testing.assert_allclose(one[PARAMS].to_numpy(float), pool[PARAMS].to_numpy(float),
                               rtol=1e-12, equal_nan=True)
    assert list(one["status"]) == list(pool["status"])


def test_dask_cluster_gives_the_local_results(fleet: dict[str, Any], dask_client: Any) -> None:
    paths = sorted(r.path for r in fleet["recs"])
    df = ac.calibrate_many(paths, g=G0, client=dask_client, progress=False)
    local = fleet["df"]
    assert list(df["status"]) == list(local["status"])
    assert list(df["message"]) == list(local["message"])
    np.testing.assert_allclose(df[PARAMS].to_numpy(float), local[PARAMS].to_numpy(float),
                               rtol=1e-12, equal_nan=True)
    dask_pids = {str(p) for p in dask_client.run(os.getpid).values()}
    assert {w.split(":")[1] for w in df["worker"]} <= dask_pids
    # a scheduler address works the same (the function makes and closes its own client)
    addr = dask_client.scheduler.address
    again = ac.calibrate_many(paths[:4], g=G0, client=addr, progress=False)
    assert list(again["status"]) == list(local["status"][:4])


@pytest.fixture
def quick_timeout(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ac.fleet, "_CONNECT_TIMEOUT_S", 1.0)


def test_unreachable_scheduler_is_a_clear_error(quick_timeout: None) -> None:
    with pytest.raises(ac.CalibrationError, match=r"cannot reach the Dask scheduler.*client="):
        ac.calibrate_many(["x.csv"], g=G0, client="tcp://127.0.0.1:1", progress=False)
    with pytest.raises(ac.CalibrationError, match="dask.distributed.Client"):
        ac.calibrate_many(["x.csv"], g=G0, client=42, progress=False)
    with pytest.raises(ac.CalibrationError, match="workers= sets local processes"):
        ac.calibrate_many(["x.csv"], g=G0, client="tcp://127.0.0.1:1", workers=2)


def test_a_cluster_without_workers_is_an_error_not_a_hang(quick_timeout: None) -> None:
    import distributed

    with distributed.LocalCluster(n_workers=0, processes=True, dashboard_address=":0") as cl:
        with distributed.Client(cl) as client:
            with pytest.raises(ac.CalibrationError, match=r"has no workers \(waited 1 s\)"):
                ac.calibrate_many(["x.csv"], g=G0, client=client, progress=False)


def _rayon_threads_started() -> int:
    """Threads the extension's rayon pool adds to a fresh process on first use."""
    from accelcal.sim import static_dwell_means

    before = len(os.listdir("/proc/self/task"))
    m = np.stack([static_dwell_means(20, rng=i).means for i in range(400)])
    ac.fit_static_batch(m, G0)
    return len(os.listdir("/proc/self/task")) - before


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="counts threads in /proc")
def test_pool_workers_run_rayon_with_one_thread() -> None:
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from accelcal.fleet import _init_worker

    ctx = multiprocessing.get_context("spawn")
    env = os.environ.pop("RAYON_NUM_THREADS", None)
    try:
        with ProcessPoolExecutor(1, mp_context=ctx, initializer=_init_worker) as ex:
            with_init = ex.submit(_rayon_threads_started).result()
        with ProcessPoolExecutor(1, mp_context=ctx) as ex:
            without = ex.submit(_rayon_threads_started).result()
    finally:
        if env is not None:
            os.environ["RAYON_NUM_THREADS"] = env
    assert with_init == 1
    assert without == (os.cpu_count() or 1)


def test_manifest_rows_override_the_defaults(fleet: dict[str, Any], tmp_path: Path) -> None:
    recs = [r for r in fleet["recs"] if not r.corruption][:4]
    # one recording without its fs line, so the manifest has to give it
    no_fs = tmp_path / "no_fs.csv"
    lines = Path(recs[3].path).read_text().splitlines(True)
    assert lines[:2] == ["# fs: 50\n", "t,ax,ay,az\n"]
    no_fs.write_text("n,ax,ay,az\n" + "".join(lines[2:]))  # no fs line, no time column
    rows = [
        {"path": os.path.relpath(recs[0].path, tmp_path), "sensor_id": "A-1", "g": None,
         "fs": None, "line": 7},
        {"path": os.path.relpath(recs[1].path, tmp_path), "sensor_id": "A-2", "g": 9.75,
         "fs": None, "line": 7},
        {"path": os.path.relpath(recs[2].path, tmp_path), "sensor_id": "A-3", "g": None,
         "fs": None, "line": 8},
        {"path": "no_fs.csv", "sensor_id": "A-4", "g": None, "fs": 50.0, "line": 8},
    ]
    man = pd.DataFrame(rows)
    man.to_csv(tmp_path / "manifest.csv", index=False)
    kept = man.copy()
    df = ac.calibrate_many(str(tmp_path / "manifest.csv"), g=G0, workers=2, progress=False)
    pd.testing.assert_frame_equal(man, kept)
    assert list(df["sensor_id"]) == ["A-1", "A-2", "A-3", "A-4"]
    assert list(df["status"]) == ["ok"] * 4, list(df["message"])
    assert list(df["line"]) == [7, 7, 8, 8]  # other manifest columns are carried over
    assert df["g_mps2"].tolist() == [G0, 9.75, G0, G0]
    assert df["g_source"].tolist()[:2] == ["given", "manifest g"]
    # With g 1 % low, the fitted scale factors come out 1 % high (K scales with 1/g).
    for i in (0, 1):
        est = df.loc[i, ["sx", "sy", "sz"]].to_numpy(float)
        expect = recs[i].truth[:3] * (G0 / df.loc[i, "g_mps2"])
        assert np.all(np.abs(est - expect) < 5 * df.loc[i, ["sx_std", "sy_std", "sz_std"]]
                      .to_numpy(float) + 1e-4)
    assert df.loc[3, "fs_hz"] == 50.0
    # The same manifest kept in a workbook (as production lines often keep them).
    man.to_excel(tmp_path / "manifest.xlsx", index=False)
    code, out = _cli("calibrate", "static", "--manifest", str(tmp_path / "manifest.xlsx"),
                     "--g", str(G0), "--workers", "1", "--json", "--quiet")
    assert code == 0, out
    from_xlsx = pd.DataFrame(json.loads(out))
    assert list(from_xlsx["sensor_id"]) == ["A-1", "A-2", "A-3", "A-4"]
    assert list(from_xlsx["line"]) == [7, 7, 8, 8]
    np.testing.assert_array_equal(from_xlsx[PARAMS].to_numpy(float), df[PARAMS].to_numpy(float))
    # without the fs column that recording has no sample rate: an error row naming fs
    man.loc[3, "fs"] = None
    df2 = ac.calibrate_many(man.assign(path=[str(tmp_path / p) for p in man["path"]]),
                            g=G0, workers=1, progress=False)
    assert df2.loc[3, "status"] == "error"
    assert "fs= (Hz)" in df2.loc[3, "message"]


def test_manifest_bounds_column_gives_known_dwells(fleet: dict[str, Any],
                                                   tmp_path: Path) -> None:
    from accelcal.io import read_stream

    r = next(r for r in fleet["recs"] if not r.corruption)
    st = read_stream(r.path)
    d = ac.detect_dwells(st.samples, st.fs, t=st.t)
    # A sequencer's log of the first 20 dwells, in seconds from the first sample.
    log = tmp_path / "seq.csv"
    log.write_text("pose,start_s,stop_s\n" + "".join(
        f"p{i},{float(a / st.fs)!r},{float(b / st.fs)!r}\n" for i, (a, b) in enumerate(
            zip(d.start[:20], d.stop[:20], strict=True)))
        + f"x_rot,{float(d.stop[0] / st.fs)!r},{float(d.start[1] / st.fs)!r}\n")
    man = pd.DataFrame({"path": [r.path, r.path], "sensor_id": ["known", "detected"],
                        "bounds": ["seq.csv", None]})
    man.to_csv(tmp_path / "m.csv", index=False)
    df = ac.calibrate_many(str(tmp_path / "m.csv"), g=G0, workers=1, progress=False)
    assert list(df["status"]) == ["ok", "ok"], list(df["message"])
    assert list(df["n_dwells"]) == [20, 24]
    # The bounds file's own note (a motion left out) reaches the row, as on the command line.
    assert "left out as motions, not static: x_rot" in df.loc[0, "message"]
    ref = ac.fit_static(ac.dwell_stats(st.samples, np.column_stack([d.start, d.stop])[:20],
                                       t=st.t, fs=st.fs), G0)
    np.testing.assert_allclose(df.loc[0, PARAMS].to_numpy(float), ref.vector, rtol=1e-12)
    bad = man.assign(bounds=["none.json", None])
    df = ac.calibrate_many(bad.assign(path=[r.path] * 2), g=G0, workers=1, progress=False)
    assert df.loc[0, "status"] == "error" and "bounds file not found" in df.loc[0, "message"]


def test_missing_files_folders_and_fifos_are_error_rows(fleet: dict[str, Any],
                                                        tmp_path: Path) -> None:
    fifo = tmp_path / "fifo.csv"
    os.mkfifo(fifo)  # reading it would block for ever
    good = next(r for r in fleet["recs"] if not r.corruption).path
    paths = [str(tmp_path / "gone.csv"), str(tmp_path), str(fifo), good]
    df = ac.calibrate_many(paths, g=G0, workers=1, progress=False)
    assert df["status"].tolist() == ["error", "error", "error", "ok"]
    assert "file not found" in df.loc[0, "message"]
    assert "is a folder" in df.loc[1, "message"]
    assert "not a regular file" in df.loc[2, "message"]


def test_latitude_gives_wgs84_gravity(fleet: dict[str, Any]) -> None:
    r = next(r for r in fleet["recs"] if not r.corruption)
    df = ac.calibrate_many([r.path], lat=48.0, height=300.0, workers=1, progress=False)
    assert df.loc[0, "g_mps2"] == pytest.approx(ac.local_gravity(48.0, 300.0), rel=1e-15)
    assert "WGS84" in df.loc[0, "g_source"]


def test_a_gravity_from_the_latitude_carries_its_error_as_the_single_file_command(
        fleet: dict[str, Any], tmp_path: Path) -> None:
    """The fleet fitted a --lat g as exact (the std 26 times too small against the formula's
    1e-4 relative error) where `calibrate static FILE --lat` counts sigma_g = 1e-3 m/s^2."""
    r = next(r for r in fleet["recs"] if not r.corruption)
    df = ac.calibrate_many([r.path], lat=48.0, height=300.0, out=tmp_path / "cals",
                           workers=1, progress=False)
    row = df.iloc[0]
    assert row["sigma_g_mps2"] == 1e-3
    gv = ac.local_gravity(48.0, 300.0)
    st = ac.io.read_stream(r.path)
    d = ac.detect_dwells(st.samples, st.fs, t=st.t)
    exact = ac.fit_static(d, gv, check_g=False)
    with_g = ac.fit_static(d, gv, check_g=False, sigma_g=1e-3)
    std = row[[f"{q}_std" for q in PARAMS]].to_numpy(float)
    np.testing.assert_allclose(std, with_g.std_realistic, rtol=1e-9)
    assert std[0] > 1.5 * exact.std_realistic[0]  # g's 1e-4 relative dominates
    m = ac.TriadModel.load(row["cal_file"])
    assert m.metadata["sigma_g"] == 1e-3 and "WGS84" in m.metadata["g_source"]
    assert m.metadata["sigma_g_source"].startswith("the latitude formula's typical error")
    np.testing.assert_allclose(m.std, std, rtol=1e-12)
    code, out = _cli("calibrate", "static", r.path, "--lat", "48", "--height", "300", "--json")
    assert code == 0, out
    one = json.loads(out)
    np.testing.assert_allclose([one["std"][q] for q in PARAMS] if isinstance(one["std"], dict)
                               else one["std"], std, rtol=1e-6)
    # A given g is exact unless its std is given: keyword, then a manifest column.
    df = ac.calibrate_many([r.path], g=G0, sigma_g=2e-4, workers=1, progress=False)
    assert df.loc[0, "sigma_g_mps2"] == 2e-4
    man = tmp_path / "m.csv"
    man.write_text(f"path,g,sigma_g\n{r.path},{G0},5e-4\n{r.path},{G0},\n")
    df = ac.calibrate_many(str(man), g=G0, workers=1, progress=False)
    assert df["sigma_g_mps2"].tolist() == [5e-4, 0.0]
    assert df.loc[0, "sx_std"] > df.loc[1, "sx_std"]
    code, out = _cli("calibrate", "static", r.path, r.path + "*", "--g", str(G0),
                     "--sigma-g", "2e-4", "--quiet", "--summary", str(tmp_path / "s.csv"))
    assert code == 0, out


def test_repeated_sensor_ids_get_distinct_files(fleet: dict[str, Any], tmp_path: Path) -> None:
    recs = [r for r in fleet["recs"] if not r.corruption][:4]
    man = pd.DataFrame({"path": [r.path for r in recs], "sensor_id": ["X", "X", "X", "Y"],
                        "date": ["2026-05-01T08:00:00Z", "2026-06-01T08:00:00+02:00",
                                 "2026-05-01T08:00:00Z", None]})
    df = ac.calibrate_many(man, g=G0, out=tmp_path / "c", workers=1, progress=False)
    names = [Path(p).name for p in df["cal_file"]]
    assert names[:3] == ["X_20260501T080000Z.json", "X_20260601T060000Z.json",
                         "X_20260501T080000Z-2.json"]
    assert re.fullmatch(r"Y_\d{8}T\d{6}Z\.json", names[3])
    for i in range(4):
        m = ac.TriadModel.load(df.loc[i, "cal_file"])
        assert m.sensor_id == df.loc[i, "sensor_id"] and m.vector[0] == df.loc[i, "sx"]
    assert ac.TriadModel.load(df.loc[1, "cal_file"]).date.startswith("2026-06-01T")


def test_diagnose_adds_the_gap_verdict(fleet: dict[str, Any]) -> None:
    r = next(r for r in fleet["recs"] if not r.corruption)
    df = ac.calibrate_many([r.path], g=G0, diagnose=True, workers=1, progress=False)
    st = ac.io.read_stream(r.path)
    rep = ac.diagnose(st.samples, g=G0, fs=st.fs, t=st.t)
    assert df.loc[0, "gap_best"] == rep.best
    assert df.loc[0, "gap_chi2_dof"] == pytest.approx(rep.chi2_per_dof, rel=1e-12)
    assert df.loc[0, "gap_held_out"] == pytest.approx(rep.held_out_gap, rel=1e-12)
    assert df.loc[0, "gap_error"] == ""


@pytest.mark.parametrize(
    ("kw", "needle"),
    [
        ({}, r"give the reference gravity: g= \(m/s\^2\) or lat=/height="),
        ({"g": G0, "model": "full"}, r"model= must be one of lower, diag, upper"),
        ({"g": G0, "method": "magic"}, r"method= must be one of"),
        ({"g": G0, "workers": 0}, r"workers= must be a positive integer"),
        ({"g": -1.0}, r"g= \(m/s\^2\) must be positive"),
    ],
)
def test_bad_calls_are_clear_errors(fleet: dict[str, Any], kw: dict[str, Any],
                                    needle: str) -> None:
    with pytest.raises(ac.CalibrationError, match=needle):
        ac.calibrate_many([fleet["recs"][0].path], progress=False, **kw)


def test_bad_sources_are_clear_errors(fleet: dict[str, Any], tmp_path: Path) -> None:
    with pytest.raises(ac.CalibrationError, match="no recording matches"):
        ac.calibrate_many(str(tmp_path / "*.csv"), g=G0)
    with pytest.raises(ac.CalibrationError, match="'path' column"):
        ac.calibrate_many(pd.DataFrame({"file": ["a.csv"]}), g=G0)
    with pytest.raises(ac.CalibrationError, match="must hold file paths"):
        ac.calibrate_many([1, 2], g=G0)
    # the summary may never replace a recording
    r = fleet["recs"][0].path
    with pytest.raises(ac.CalibrationError, match="would overwrite an input"):
        ac.calibrate_many([r], g=G0, summary=Path(r).with_suffix(".parquet"))


def test_fleet_report_names_outliers_and_failures(fleet: dict[str, Any]) -> None:
    rep = ac.fleet_report(fleet["df"])
    out_id = f"S{OUTLIER:05d}"
    assert {(o["sensor_id"], o["param"]) for o in rep.outliers} == {(out_id, "sx")}
    o = rep.outliers[0]
    truths = np.array([r.truth for r in fleet["recs"] if not r.corruption])
    assert o["z"] > 5
    sx = next(d for d in rep.distributions if d["param"] == "sx")
    assert sx["median"] == pytest.approx(np.median(truths[:, 0]), abs=0.01)
    assert 0.01 < sx["spread"] < 0.04  # the fleet's 2 % scale spread
    assert sx["max"] == pytest.approx(o["value"])
    listed = {f["sensor_id"]: f for f in rep.failed + rep.weak + rep.noted}
    bad = {r.sensor_id: r.corruption for r in fleet["recs"] if r.corruption}
    assert set(listed) == set(bad)
    assert {f["sensor_id"] for f in rep.noted + rep.weak} == {
        s for s, k in bad.items() if k in CALIBRATED}
    for sid, kind in bad.items():
        assert re.search(EXPECTED[kind][1], listed[sid]["message"])
    assert rep.counts == {"ok": N - 3, "weak": 1, "misfit": 0, "degenerate": 1, "error": 1}
    text = rep.summary()
    assert f"{out_id} (" in text and "sx = " in text and "z = +" in text
    assert "calibrated, with notes (2):" in text and "(dropouts)" in text
    assert rep.to_dict()["noted"] == rep.noted


def test_fleet_report_plot_marks_the_outliers(fleet: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rep = ac.fleet_report(fleet["df"])
    fig = rep.plot()
    try:
        axes = [a for a in fig.axes if a.get_xlabel()]
        assert [a.get_xlabel().split(" ")[0] for a in axes] == PARAMS
        assert "(recording units per m/s^2)" in axes[0].get_xlabel()
        assert all(a.get_ylabel() == "recordings" for a in axes)
        red = [ln.get_xdata()[0] for ln in axes[0].get_lines() if ln.get_color() == "tab:red"]
        assert red == [pytest.approx(rep.outliers[0]["value"])]
        assert not [ln for a in axes[1:] for ln in a.get_lines() if ln.get_color() == "tab:red"]
    finally:
        plt.close(fig)


# ---- command line -----------------------------------------------------------------------------
def _cli(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(main, list(args))
    assert "Traceback" not in r.output
    return r.exit_code, r.output


def test_cli_fleet_run_and_report(fleet: dict[str, Any], tmp_path: Path) -> None:
    files = sorted(r.path for r in fleet["recs"])
    summary = tmp_path / "fleet.parquet"
    code, out = _cli("calibrate", "static", *files, "--g", str(G0), "--summary", str(summary),
                     "--out", str(tmp_path / "cals"), "--workers", "2", "--quiet")
    assert code == 0, out
    assert f"calibrated {N} recordings" in out and f"{N - 3} ok, 1 weak" in out
    for r in fleet["recs"]:
        if r.corruption:
            assert f"{r.sensor_id} ({r.path}): {EXPECTED[r.corruption][0]}" in out
    table = pd.read_parquet(summary)
    assert (tmp_path / "fleet.csv").is_file()
    np.testing.assert_array_equal(table[PARAMS].to_numpy(float),
                                  fleet["df"][PARAMS].to_numpy(float))
    assert len(list((tmp_path / "cals").glob("*.json"))) == N - 2

    code, out = _cli("fleet", "report", str(summary))
    assert code == 0, out
    assert f"S{OUTLIER:05d}" in out and "outlier sensors (robust |z| > 5)" in out
    assert "failed recordings (2)" in out and "weakly determined (1)" in out
    assert "calibrated, with notes (2)" in out
    code, out = _cli("fleet", "report", str(tmp_path / "fleet.csv"), "--json",
                     "--plot", str(tmp_path / "fleet.png"))
    assert code == 0, out
    rep = json.loads(out)
    assert [(o["sensor_id"], o["param"]) for o in rep["outliers"]] == [(f"S{OUTLIER:05d}", "sx")]
    assert (tmp_path / "fleet.png").stat().st_size > 10_000


def test_cli_glob_json_and_single_file_still_single(fleet: dict[str, Any]) -> None:
    folder = Path(fleet["recs"][0].path).parent
    code, out = _cli("calibrate", "static", str(folder / "S0000[0-2].csv"), "--g", str(G0),
                     "--json", "--quiet", "--workers", "1")
    assert code == 0, out
    rows = json.loads(out)
    assert [r["sensor_id"] for r in rows] == ["S00000", "S00001", "S00002"]
    code, out = _cli("calibrate", "static", str(folder / "S00000.csv"), "--g", str(G0), "--json")
    assert code == 0, out
    assert "vector" in json.loads(out)  # the one-recording output, unchanged


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["-o", "x.json"], "-o/--output takes one recording"),
        (["--plot", "x.png"], "--plot takes one recording"),
        (["--sensor-id", "A"], "--sensor-id names one recording"),
        (["--scheduler", "tcp://127.0.0.1:1"], "cannot reach the Dask scheduler"),
    ],
)
def test_cli_fleet_errors_name_options(fleet: dict[str, Any], extra: list[str],
                                       needle: str, quick_timeout: None) -> None:
    files = [r.path for r in fleet["recs"][:2]]
    code, out = _cli("calibrate", "static", *files, "--g", str(G0), *extra)
    assert code == 2 and needle in out, out
    if "--scheduler" in extra:
        assert "--scheduler" in out and "client=" not in out


def test_cli_fleet_errors_without_gravity_or_files(fleet: dict[str, Any]) -> None:
    files = [r.path for r in fleet["recs"][:2]]
    code, out = _cli("calibrate", "static", *files)
    assert code == 2 and "--g (m/s^2) or --lat/--height" in out and "g=" not in out
    code, out = _cli("calibrate", "static", "--g", "9.8")
    assert code == 2 and "give the recordings" in out
    code, out = _cli("fleet", "report", "missing.parquet")
    assert code == 2 and "not found" in out


def test_cli_runs_as_a_program_with_a_progress_bar_off_a_terminal(fleet: dict[str, Any],
                                                                   tmp_path: Path) -> None:
    files = [r.path for r in fleet["recs"][:3]]
    exe = str(Path(sys.executable).with_name("accelcal"))
    p = subprocess.run([exe, "calibrate", "static", *files,
                        "--g", str(G0), "--summary", str(tmp_path / "s.parquet")],
                       capture_output=True, text=True, timeout=300, check=False)
    assert p.returncode == 0, p.stderr
    assert "calibrating" not in p.stderr  # stderr is a pipe: no bar
    assert pd.read_parquet(tmp_path / "s.parquet")["status"].tolist() == ["ok"] * 3


def test_missing_optional_dependencies_are_named(fleet: dict[str, Any], tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    r = next(r for r in fleet["recs"] if not r.corruption)
    with monkeypatch.context() as m:
        m.setitem(sys.modules, "distributed", None)  # import fails as if not installed
        with pytest.raises(ac.CalibrationError, match=r"pip install 'accelcal\[fleet\]'"):
            ac.calibrate_many([r.path], g=G0, client="tcp://127.0.0.1:1")
    with monkeypatch.context() as m:
        m.setitem(sys.modules, "pyarrow", None)
        with pytest.raises(ac.CalibrationError, match=r"Parquet needs pyarrow"):
            ac.calibrate_many([r.path], g=G0, workers=1, summary=tmp_path / "s.parquet",
                              progress=False)
    assert not (tmp_path / "s.parquet").exists() and not (tmp_path / "s.csv").exists()
    with monkeypatch.context() as m:
        m.setitem(sys.modules, "pandas", None)
        with pytest.raises(ac.CalibrationError, match=r"needs pandas"):
            ac.calibrate_many([r.path], g=G0)


def test_progress_bar_counts_recordings_when_asked(fleet: dict[str, Any],
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    paths = [r.path for r in fleet["recs"][:3]]
    ac.calibrate_many(paths, g=G0, workers=1, progress=True)
    err = capsys.readouterr().err
    assert "calibrating" in err and "/3 [" in err  # a bar over the 3 recordings
    ac.calibrate_many(paths, g=G0, workers=1, progress=False)
    assert capsys.readouterr().err == ""


def test_saturated_dwells_are_left_out_as_the_single_file_command_does(tmp_path: Path) -> None:
    s, x, truth = clipped_session()
    p = write_csv(tmp_path / "clipped.csv", s.t, x, fmt=["%.4f", "%d", "%d", "%d"])
    df = ac.calibrate_many([str(p)], g=s.g, diagnose=True, workers=1, progress=False)
    row = df.loc[0]
    assert row["status"] == "ok" and row["n_dwells"] == len(s.bounds) - len(truth)
    assert re.match(rf"{len(truth)} of {len(s.bounds)} dwells left out: their output did not "
                    r"follow the sensor \(dwell \d+ .*saturated", row["message"]), row["message"]
    d = ac.detect_dwells(x, s.fs).drop_faults()
    fit = ac.fit_static(d, s.g)
    np.testing.assert_allclose(row[PARAMS].to_numpy(float), fit.vector, rtol=1e-12)
    assert row["gap_error"] == "" and row["gap_chi2_dof"] < 3


def test_vibrating_poses_are_named_in_the_fleet_row(tmp_path: Path) -> None:
    s, x = vibrating_session(n_dwells=24, dwell_s=10.0, move_s=3.0, after=0.75,
                             axes=(1.0, 1.0, 1.0))
    p = write_csv(tmp_path / "pump.csv", s.t, x)
    row = ac.calibrate_many([str(p)], g=s.g, workers=1, progress=False).loc[0]
    assert row["status"] in ("ok", "weak") and row["n_dwells"] < 24
    m = re.search(r"(\d+) stretch\(es\) .* look still .* k=(\d+) would take them",
                  row["message"])
    assert m and int(m.group(1)) == 24 - row["n_dwells"], row["message"]
    again = ac.calibrate_many([str(p)], g=s.g, workers=1, progress=False,
                              detector=ac.DetectorSettings(k=float(m.group(2)))).loc[0]
    assert again["n_dwells"] == 24


def test_a_fleet_of_pose_mean_tables_from_folders_with_one_file_name(tmp_path: Path) -> None:
    """Two loggers' tables of pose means, both called acceldata.txt (rows a few degrees
    apart: not recognised as poses without --means). The fleet refused --means and said
    "give --fs" without naming it; both rows were "acceldata". Now --means reads every file as
    poses, the ids carry the folder, and the messages name command-line options."""
    from accelcal.sim.static import static_dwell_means

    truths = [[1.02, 0.98, 1.01, 0.01, -0.02, 0.015, 0.0, 0.0, 0.0],
              [0.99, 1.01, 1.0, -0.01, 0.02, 0.0, 0.0, 0.0, 0.0]]
    paths = []
    for name, truth in zip(("logger_a", "logger_b"), truths, strict=True):
        # a board turned slowly: consecutive poses 3 deg apart along a random walk
        rng = np.random.default_rng(len(paths))
        u = np.cumsum(rng.normal(0, 0.05, (300, 3)), axis=0) + [0, 0, 1]
        u = np.vstack([u / np.linalg.norm(u, axis=1)[:, None], -np.eye(3), np.eye(3)])
        s = static_dwell_means(u, truth=truth, g=1.0, sigma=1e-3, rng=7)
        (tmp_path / name).mkdir()
        p = tmp_path / name / "acceldata.txt"
        np.savetxt(p, s.means, fmt="%.5f")
        paths.append(str(p))
    code, out = _cli("calibrate", "static", *paths, "--g", "1")
    assert code == 1, out  # nothing calibrated
    assert "give --fs (Hz); or, if each row is a pose's mean (a table of dwell means), --means" \
        in out, out
    assert "each recording holds at most" not in out  # errors, not few poses
    code, out = _cli("calibrate", "static", *paths, "--g", "1", "--means", "--json")
    assert code == 0, out
    rows = json.loads(out)
    assert [r["sensor_id"] for r in rows] == ["logger_a_acceldata", "logger_b_acceldata"]
    for r, truth in zip(rows, truths, strict=True):
        assert r["status"] in ("ok", "weak") and r["n_dwells"] == 306
        assert "(306 rows: as asked)" in r["message"]
        np.testing.assert_allclose([r[p] for p in PARAMS[:6]], truth[:6], atol=2e-3)
    # A manifest's ids are kept as given, even when they collide with nothing.
    man = tmp_path / "m.csv"
    man.write_text(f"path,sensor_id\n{paths[0]},A\n{paths[1]},B\n")
    df = ac.calibrate_many(str(man), g=1.0, means=True, workers=1, progress=False)
    assert list(df["sensor_id"]) == ["A", "B"]


def test_a_fleet_of_one_pose_per_file_is_told_to_join_them(tmp_path: Path) -> None:
    from accelcal.sim.field import field_session

    s = field_session(fs=50.0, n_dwells=6, dwell_s=4.0, move_s=1.0, max_tilt_deg=80.0,
                      sigma=2e-3, rng=3)
    paths = []
    for i, (a, b) in enumerate(s.bounds):  # one file per face, as a student logged them
        paths.append(str(write_csv(tmp_path / f"pose{i}.csv", s.t[a:b], s.samples[a:b])))
    code, out = _cli("calibrate", "static", *paths, "--g", str(G0))
    assert code == 1, out
    assert "accelcal: no recording was calibrated; each recording holds 1 dwell: if " \
           "they are poses of one sensor, one file per pose, join them" in out, out


def test_a_fleet_of_one_pose_per_file_names_the_file_that_holds_none(tmp_path: Path) -> None:
    """softdream's six faces as a fleet: "each recording holds at most 1 dwell" when right.txt
    held none (its rest too short for the detector). The counts are now said as they are."""
    from accelcal.sim.field import field_session

    s = field_session(fs=50.0, n_dwells=6, dwell_s=4.0, move_s=1.0, max_tilt_deg=80.0,
                      sigma=2e-3, rng=3)
    paths = []
    for i, (a, b) in enumerate(s.bounds):
        if i == 4:  # a rest of 2 s: shorter than a window, a dwell and two trims (2.2 s)
            a, b = (a + b) // 2 - 50, (a + b) // 2 + 50
        paths.append(str(write_csv(tmp_path / f"pose{i}.csv", s.t[a:b], s.samples[a:b])))
    code, out = _cli("calibrate", "static", *paths, "--g", str(G0))
    assert code == 1, out
    assert "pose4 (" in out and "too short for a dwell" in out, out
    assert "accelcal: no recording was calibrated; the recordings hold 1 dwell each, except " \
           "pose4 (none): if they are poses of one sensor" in out, out
    assert "at most" not in out, out


def test_a_fleet_row_says_when_the_residuals_exceed_the_noise_model(tmp_path: Path) -> None:
    """The Xsens session (chi2/dof 15.6, p = 6e-80) was an 'ok' row with an empty message;
    the single-file summary says it."""
    from accelcal.sim.field import field_session

    s = field_session(fs=50.0, n_dwells=16, dwell_s=6.0, move_s=2.0, max_tilt_deg=70.0,
                      sigma=2e-3, rng=6)
    x = s.samples.copy()
    for a, b in s.bounds:  # a per-dwell offset 10 times the noise of a dwell mean
        x[a:b] += np.random.default_rng(a).normal(0, 2e-3 / np.sqrt(b - a) * 10, 3)
    p = write_csv(tmp_path / "offsets.csv", s.t, x)
    df = ac.calibrate_many([str(p)], g=G0, workers=1, progress=False)
    assert df.loc[0, "status"] in ("ok", "weak")
    assert "residuals exceed the noise model (chi2/dof" in df.loc[0, "message"]


def test_a_dead_worker_names_the_missing_main_guard(monkeypatch: pytest.MonkeyPatch) -> None:
    import types

    from accelcal.fleet import _died_hint

    monkeypatch.setitem(sys.modules, "__main__", types.SimpleNamespace(__file__="script.py"))
    assert "put the call under 'if __name__ == \"__main__\":'" in _died_hint()
    monkeypatch.setitem(sys.modules, "__main__", types.SimpleNamespace())
    assert _died_hint() == "run this recording alone to see why"


def test_a_parquet_recording_is_a_recording_and_a_parquet_manifest_a_manifest(
        fleet: dict[str, Any], tmp_path: Path) -> None:
    """A .parquet file was always taken for a manifest: a recording in Parquet was read as a
    table of recordings without a 'path' column. Now its columns decide."""
    rec = next(r for r in fleet["recs"] if not r.corruption)
    tab = pd.read_csv(rec.path, comment="#")
    pq = tmp_path / f"{rec.sensor_id}.parquet"
    tab.to_parquet(pq)
    man = tmp_path / "manifest.parquet"
    pd.DataFrame({"path": [rec.path, str(pq)]}).to_parquet(man)
    one = ac.calibrate_many(str(pq), g=G0, workers=1, progress=False)
    both = ac.calibrate_many(str(man), g=G0, workers=1, progress=False)
    assert one["status"].tolist() == ["ok"] and both["status"].tolist() == ["ok", "ok"]
    ref = fleet["df"].set_index("sensor_id").loc[rec.sensor_id, PARAMS].to_numpy(float)
    for row in (one.iloc[0], both.iloc[0], both.iloc[1]):
        np.testing.assert_allclose(row[PARAMS].to_numpy(float), ref, rtol=1e-9, atol=1e-12)
    code, out = _cli("calibrate", "static", "--manifest", str(pq), "--g", str(G0))
    assert code == 2 and "needs a 'path' column" in out, out
    # One FILE that is a table of recordings is a manifest (it was read as a recording: "the
    # table has no numeric columns").
    code, out = _cli("calibrate", "static", str(man), "--g", str(G0), "--summary",
                     str(tmp_path / "s.csv"), "--quiet")
    assert code == 0 and "calibrated 2 recordings" in out, out


def test_a_compressed_recording_is_named_without_its_suffixes() -> None:
    """A fleet run named `b.csv.gz`'s sensor `b.csv` (its calibration `b.csv_....json`)."""
    from accelcal.io import file_stem

    assert [file_stem(p) for p in ("a/b.csv.gz", "b.csv.bz2", "b.txt.xz", "b.csv", "b.v2.csv",
                                    "b")] == ["b", "b", "b", "b", "b.v2", "b"]


# ---- an --out folder shared by several runs, duplicate entries, a report without spread -------
def _good(fleet: dict[str, Any], n: int) -> list[str]:
    return [r.path for r in fleet["recs"] if not r.corruption][:n]


def _board_a(path: str) -> pd.DataFrame:
    """A manifest: one recording as board-A, on a day-level test date (one name per day)."""
    return pd.DataFrame({"path": [path], "sensor_id": ["board-A"], "date": ["2026-11-21"]})


BOARD_A = "board-A_20261121T000000Z"


def test_a_later_run_never_replaces_another_recordings_calibration_file(
        fleet: dict[str, Any], tmp_path: Path) -> None:
    a, b, c = _good(fleet, 3)
    out = tmp_path / "cals"
    first = ac.calibrate_many(_board_a(a), g=G0, out=out, workers=1, progress=False)
    f1 = Path(first.loc[0, "cal_file"])
    assert f1.name == f"{BOARD_A}.json" and first.loc[0, "message"] == ""
    kept = f1.read_bytes()
    second = ac.calibrate_many(_board_a(b), g=G0, out=out, workers=1, progress=False)
    third = ac.calibrate_many(_board_a(c), g=G0, out=out, workers=1, progress=False)
    # the board's history: one file per calibration, the earlier ones untouched
    assert f1.read_bytes() == kept
    assert sorted(p.name for p in out.glob("*.json")) == [
        f"{BOARD_A}-2.json", f"{BOARD_A}-3.json", f"{BOARD_A}.json"]
    for df, src, name in ((second, b, f"{BOARD_A}-2.json"), (third, c, f"{BOARD_A}-3.json")):
        assert Path(df.loc[0, "cal_file"]).name == name
        assert ac.TriadModel.load(df.loc[0, "cal_file"]).metadata["source"] == src
        msg = df.loc[0, "message"]
        assert df.loc[0, "status"] == "ok"
        assert f"{BOARD_A}.json" in msg and a in msg and f"written as {name}" in msg, msg
    assert ac.TriadModel.load(f1).metadata["source"] == a
    # the fleet report lists the renamed ones as calibrated with a note
    assert [n["sensor_id"] for n in ac.fleet_report(second).noted] == ["board-A"]


def test_a_rerun_of_the_same_recording_keeps_the_one_identical_file(
        fleet: dict[str, Any], tmp_path: Path) -> None:
    a = _good(fleet, 1)[0]
    out = tmp_path / "cals"
    first = ac.calibrate_many(_board_a(a), g=G0, out=out, workers=1, progress=False)
    f1 = Path(first.loc[0, "cal_file"])
    st = os.stat(f1)
    again = ac.calibrate_many(_board_a(a), g=G0, out=out, workers=2, progress=False)
    assert again.loc[0, "cal_file"] == str(f1) and again.loc[0, "message"] == ""
    assert [p.name for p in out.glob("*.json")] == [f1.name]
    assert os.stat(f1).st_mtime_ns == st.st_mtime_ns and os.stat(f1).st_ino == st.st_ino
    # the file records what the recording held
    m = ac.TriadModel.load(f1)
    assert m.metadata["source_sha256"] == hashlib.sha256(Path(a).read_bytes()).hexdigest()


def test_a_new_recording_under_an_old_file_name_does_not_replace_its_calibration(
        fleet: dict[str, Any], tmp_path: Path) -> None:
    """The same path, re-recorded (or two runs within one second): another recording."""
    a, b = _good(fleet, 2)
    rec = tmp_path / "S9.csv"
    rec.write_bytes(Path(a).read_bytes())
    out = tmp_path / "cals"
    man = _board_a(str(rec))
    first = ac.calibrate_many(man, g=G0, out=out, workers=1, progress=False)
    kept = Path(first.loc[0, "cal_file"]).read_bytes()
    rec.write_bytes(Path(b).read_bytes())  # the board recorded again, same file name
    second = ac.calibrate_many(man, g=G0, out=out, workers=1, progress=False)
    assert Path(first.loc[0, "cal_file"]).read_bytes() == kept
    assert Path(second.loc[0, "cal_file"]).name == f"{BOARD_A}-2.json"
    assert "written as" in second.loc[0, "message"]
    # a file of that name that is no calibration at all is not touched either
    (out / f"{BOARD_A}-3.json").write_text("my notes\n")
    (out / f"{BOARD_A}-4.json").symlink_to(out / f"{BOARD_A}-3.json")
    rec.write_bytes(Path(_good(fleet, 3)[2]).read_bytes())
    third = ac.calibrate_many(man, g=G0, out=out, workers=1, progress=False)
    assert Path(third.loc[0, "cal_file"]).name == f"{BOARD_A}-5.json"
    assert (out / f"{BOARD_A}-3.json").read_text() == "my notes\n"
    assert (out / f"{BOARD_A}-4.json").is_symlink()
    assert not [p for p in out.iterdir() if p.name.startswith(".accelcal-tmp-")]


def test_the_cli_says_when_a_calibration_file_name_was_taken(fleet: dict[str, Any],
                                                              tmp_path: Path) -> None:
    a, b = _good(fleet, 2)
    for i, p in enumerate((a, b)):
        _board_a(p).to_csv(tmp_path / f"m{i}.csv", index=False)
    out = str(tmp_path / "cals")
    code, _ = _cli("calibrate", "static", "--manifest", str(tmp_path / "m0.csv"), "--g",
                   str(G0), "--out", out, "--quiet")
    assert code == 0
    code, text = _cli("calibrate", "static", "--manifest", str(tmp_path / "m1.csv"), "--g",
                      str(G0), "--out", out, "--quiet")
    assert code == 0, text
    assert f"board-A ({b}): ok: " in text and f"written as {BOARD_A}-2.json" in text, text
    assert len(list(Path(out).glob("*.json"))) == 2


def test_a_recording_listed_twice_is_calibrated_once_under_its_own_name(
        fleet: dict[str, Any], tmp_path: Path) -> None:
    a, b = _good(fleet, 2)
    link = tmp_path / "link.csv"
    link.symlink_to(a)
    rel = os.path.relpath(a)
    df = ac.calibrate_many([a, b, rel, str(link)], g=G0, out=tmp_path / "c", workers=1,
                           progress=False)
    assert list(df["path"]) == [a, b]
    assert list(df["sensor_id"]) == [Path(a).stem, Path(b).stem]
    assert df["status"].tolist() == ["ok", "ok"] and df.loc[1, "message"] == ""
    msg = df.loc[0, "message"]
    assert "listed 3 times" in msg and rel in msg and str(link) in msg, msg
    assert "calibrated once" in msg
    assert len(list((tmp_path / "c").glob("*.json"))) == 2
    rep = ac.fleet_report(df)
    assert rep.n == 2 and rep.counts["ok"] == 2


def test_a_manifest_row_repeated_is_one_calibration_other_settings_are_two(
        fleet: dict[str, Any], tmp_path: Path) -> None:
    a, b = _good(fleet, 2)
    same = pd.DataFrame({"path": [a, b, a], "sensor_id": ["X", "Y", "X"]})
    df = ac.calibrate_many(same, g=G0, workers=1, progress=False)
    assert list(df["sensor_id"]) == ["X", "Y"] and "listed 2 times" in df.loc[0, "message"]
    # the same recording on two dates (or with known dwells and with detection): two
    # calibrations of one sensor, each row naming the other; the sensor keeps its file stem
    two = pd.DataFrame({"path": [a, b, a], "date": ["2026-05-01", None, "2026-06-01"]})
    df = ac.calibrate_many(two, g=G0, out=tmp_path / "c", workers=1, progress=False)
    assert list(df["path"]) == [a, b, a]
    assert list(df["sensor_id"]) == [Path(a).stem, Path(b).stem, Path(a).stem]
    assert df["status"].tolist() == ["ok"] * 3 and df.loc[1, "message"] == ""
    assert "also in manifest row 2, with other date" in df.loc[0, "message"]
    assert "also in manifest row 0, with other date" in df.loc[2, "message"]
    assert len(list((tmp_path / "c").glob("*.json"))) == 3


def test_the_cli_calibrates_a_file_matched_twice_once(fleet: dict[str, Any],
                                                      tmp_path: Path) -> None:
    a, b = _good(fleet, 2)
    out = tmp_path / "cals"
    code, text = _cli("calibrate", "static", a, b, a, "--g", str(G0), "--out", str(out),
                      "--quiet", "--workers", "1")
    assert code == 0, text
    assert "calibrated 2 recordings" in text and "1 duplicate entry skipped" in text, text
    assert f"{Path(a).stem} ({a}): ok: the same recording is listed 2 times" in text, text
    assert sorted(p.name.split("_")[0] for p in out.glob("*.json")) == sorted(
        [Path(a).stem, Path(b).stem])


def test_the_report_says_when_the_outlier_test_cannot_run(fleet: dict[str, Any]) -> None:
    ok = fleet["df"][fleet["df"]["status"] == "ok"].reset_index(drop=True)
    # five identical copies of one recording among three others: zero spread everywhere
    copies = pd.concat([ok.iloc[[0]]] * 5 + [ok.iloc[1:4]], ignore_index=True)
    rep = ac.fleet_report(copies)
    assert rep.outliers == []
    assert [u["param"] for u in rep.unscreened] == PARAMS
    assert all("spread is 0" in u["reason"] for u in rep.unscreened)
    assert all(d["screened"] is False for d in rep.distributions)
    text = rep.summary()
    assert "no outlier sensors" not in text
    assert "outlier test not run" in text and "spread is 0" in text, text
    assert rep.to_dict()["unscreened"] == rep.unscreened
    # only sx without spread: the other parameters are screened, sx is named as not
    some = ok.iloc[:9].copy()
    some.loc[:5, "sx"] = some.loc[0, "sx"]
    rep = ac.fleet_report(some)
    assert [u["param"] for u in rep.unscreened] == ["sx"]
    assert "3 of the 9 differ from it" in rep.unscreened[0]["reason"]
    text = rep.summary()
    assert "no outlier sensors among sy, sz, bx, by, bz, m1, m2, m3" in text, text
    assert "outlier test not run for sx" in text
    # too few recordings
    rep = ac.fleet_report(ok.iloc[:2])
    assert "fewer than 3" in rep.unscreened[0]["reason"]
    assert "no outlier sensors" not in rep.summary()


def test_cli_report_names_parameters_not_screened(fleet: dict[str, Any],
                                                  tmp_path: Path) -> None:
    ok = fleet["df"][fleet["df"]["status"] == "ok"]
    pd.concat([ok.iloc[[0]]] * 4, ignore_index=True).to_parquet(tmp_path / "t.parquet")
    code, text = _cli("fleet", "report", str(tmp_path / "t.parquet"))
    assert code == 0 and "outlier test not run" in text, text
    code, text = _cli("fleet", "report", str(tmp_path / "t.parquet"), "--json")
    assert code == 0 and len(json.loads(text)["unscreened"]) == 9


# ---- the std quoted, grossly faulty units, dead workers, interruptions, copies --------------
def _offsets_recording(path: Path, times_noise: float, seed: int = 6) -> Path:
    """A session whose dwell means carry an extra offset ``times_noise`` times the noise of a
    dwell mean: chi2/dof about ``times_noise**2``, the noise known from the dwell variances."""
    from accelcal.sim.field import field_session

    s = field_session(fs=50.0, n_dwells=16, dwell_s=6.0, move_s=2.0, max_tilt_deg=70.0,
                      sigma=2e-3, rng=seed)
    x = s.samples.copy()
    for a, b in s.bounds:
        x[a:b] += np.random.default_rng(a).normal(0, 2e-3 / np.sqrt(b - a) * times_noise, 3)
    return write_csv(path, s.t, x)


def test_the_table_quotes_the_std_the_calibration_file_and_the_single_file_command_do(
        tmp_path: Path) -> None:
    """The table gave the noise-model std (Xsens: sx_std 0.00857) where the calibration file
    and `calibrate static FILE` give the one scaled by chi2/dof (0.0338)."""
    p = _offsets_recording(tmp_path / "offsets.csv", 10.0)
    df = ac.calibrate_many([str(p)], g=G0, out=tmp_path / "cals", workers=1, progress=False)
    row = df.iloc[0]
    assert row["chi2_dof"] > 10 and "the std are scaled by chi2/dof" in row["message"]
    std = row[[f"{q}_std" for q in PARAMS]].to_numpy(float)
    m = ac.TriadModel.load(row["cal_file"])
    assert m.realistic == "scaled"
    np.testing.assert_allclose(std, m.std, rtol=1e-12)
    st = ac.io.read_stream(str(p))
    fit = ac.fit_static(ac.detect_dwells(st.samples, st.fs, t=st.t), G0)
    np.testing.assert_allclose(std, fit.std_realistic, rtol=1e-9)
    np.testing.assert_allclose(std, fit.std * np.sqrt(row["chi2_dof"]), rtol=1e-9)
    code, out = _cli("calibrate", "static", str(p), "--g", str(G0))
    assert code == 0, out
    printed = dict(re.findall(r"^\s+(sx|bx)\s+\S+\s+(\S+)", out, re.M))
    assert float(printed["sx"]) == pytest.approx(row["sx_std"], rel=2e-3)
    assert float(printed["bx"]) == pytest.approx(row["bx_std"], rel=2e-3)


def test_a_fit_far_beyond_its_noise_is_a_misfit_not_ok(tmp_path: Path) -> None:
    """A unit with a stuck bit (faults.py: chi2/dof 4.98e6, residual RMS 0.07 m/s^2) was an
    'ok' row, listed only under "calibrated, with notes"."""
    rec = tmp_path / "rec"
    rec.mkdir()
    bad = _offsets_recording(rec / "gross.csv", 1000.0)  # dwell offsets ~0.1 m/s^2
    fair = _offsets_recording(rec / "fair.csv", 10.0, seed=7)  # chi2/dof ~100, RMS ~1e-3
    df = ac.calibrate_many([str(bad), str(fair)], g=G0, out=tmp_path / "cals", workers=1,
                           progress=False)
    assert "misfit" in ac.fleet.STATUSES
    gross, ok = df.iloc[0], df.iloc[1]
    assert ok["status"] == "ok" and ok["chi2_dof"] > 10 and ok["cal_file"] != ""
    assert gross["status"] == "misfit", gross["message"]
    assert gross["chi2_dof"] > 1e3 and gross["rms_mps2"] > 1e-3 * G0
    assert re.search(r"residual RMS \S+ m/s\^2 \(\S+ g\) and chi2/dof \S+ against the noise "
                     r"of its dwells", gross["message"]), gross["message"]
    assert "no calibration file written" in gross["message"]
    # the fit is in the row (to look at), but no file a production line could load
    assert np.isfinite(gross[PARAMS].to_numpy(float)).all() and gross["cal_file"] == ""
    assert [p.name for p in (tmp_path / "cals").glob("*.json")] == [
        Path(ok["cal_file"]).name]
    rep = ac.fleet_report(tmp_path / "cals" / "fleet.parquet")
    assert rep.counts["misfit"] == 1
    assert [(f["sensor_id"], f["status"]) for f in rep.failed] == [("gross", "misfit")]
    assert [n["sensor_id"] for n in rep.noted] == ["fair"]
    text = rep.summary()
    assert "1 ok, 0 weak, 1 misfit, 0 degenerate, 0 error" in text
    assert re.search(r"failed recordings \(1\):\n  gross \(\S+\): misfit: .*residual RMS", text)
    code, out = _cli("calibrate", "static", str(bad), str(fair), "--g", str(G0), "--summary",
                     str(tmp_path / "s.parquet"), "--quiet")
    assert code == 0 and "1 ok, 0 weak, 1 misfit" in out, out
    assert re.search(r"gross \(\S+\): misfit: .*residual RMS", out), out
    # a misfit alone is not a calibration: exit 1, as when no recording was calibrated
    code, out = _cli("calibrate", "static", str(bad), "--g", str(G0), "--summary",
                     str(tmp_path / "t.parquet"), "--quiet")
    assert code == 1 and "no recording was calibrated" in out, out


def _children(pid: int) -> list[int]:
    """The child processes of ``pid`` (Linux)."""
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            continue
    return out


def _reader_of(parent: int, path: Path, timeout_s: float = 120.0) -> int:
    """The child of ``parent`` that has ``path`` open: a worker at work on that recording."""
    import time

    target = os.path.realpath(path)
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        for pid in _children(parent):
            try:
                fds = os.listdir(f"/proc/{pid}/fd")
                if any(os.readlink(f"/proc/{pid}/fd/{fd}") == target for fd in fds):
                    return pid
            except OSError:
                continue
        time.sleep(0.0005)
    raise AssertionError(f"no worker of {parent} opened {path} in {timeout_s} s")


def _slow(path: Path, mb: int = 384) -> Path:
    """A sparse file that keeps a worker busy for a second or so (hashing it; the reader then
    refuses it at once: NUL bytes), and takes no room on the disk."""
    with open(path, "wb") as fh:
        fh.truncate(mb << 20)
    return path


need_proc = pytest.mark.skipif(not Path("/proc/self/task").is_dir(),
                               reason="finds the workers in /proc")


@need_proc
def test_a_dead_worker_fails_only_its_own_recording(tmp_path: Path) -> None:
    """SIGKILL on one pool worker (killworker.py) gave 21 ok and 89 'a worker process died'
    rows: every recording still queued failed. Now only the dead worker's does."""
    import signal
    import threading

    small = [r.path for r in fleet_recordings(tmp_path / "rec", 4, corrupt=0, seed=4)]
    slow1, slow2 = _slow(tmp_path / "slow1.csv"), _slow(tmp_path / "slow2.csv")
    killed: list[int] = []

    def kill() -> None:
        pid = _reader_of(os.getpid(), slow1)
        os.kill(pid, signal.SIGKILL)
        killed.append(pid)

    t = threading.Thread(target=kill, daemon=True)
    t.start()
    df = ac.calibrate_many([str(slow1), str(slow2), *small], g=G0, workers=2,
                           out=tmp_path / "cals", progress=False)
    t.join(5)
    assert killed
    died = df.iloc[0]
    assert died["status"] == "error" and died["worker"] == ""
    assert re.match(r"the worker process calibrating this recording died \(killed by SIGKILL: "
                    r"out of memory, or killed from outside\); ",
                    died["message"]), died["message"]
    assert df.loc[1, "status"] == "error" and "NUL bytes" in df.loc[1, "message"]
    assert df["status"].tolist()[2:] == ["ok"] * 4
    assert str(killed[0]) not in {w.split(":")[-1] for w in df["worker"] if w}
    assert len(list((tmp_path / "cals").glob("*.json"))) == 4


@need_proc
def test_an_interrupted_run_keeps_what_finished(tmp_path: Path) -> None:
    """Ctrl-C 5 s into a 110-file run (sigint.py) left no calibration file and no table."""
    import signal

    recs = fleet_recordings(tmp_path / "rec", 4, corrupt=0, seed=8)
    slow = _slow(tmp_path / "rec" / "slow.csv", 512)
    paths = [recs[0].path, recs[1].path, str(slow), recs[2].path, recs[3].path]
    man = tmp_path / "manifest.csv"
    pd.DataFrame({"path": paths, "date": "2026-11-28"}).to_csv(man, index=False)
    out = tmp_path / "cals"
    exe = str(Path(sys.executable).with_name("accelcal"))
    cmd = [exe, "calibrate", "static", "--manifest", str(man), "--g", str(G0), "--out",
           str(out), "--workers", "2", "--quiet"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    try:
        _reader_of(p.pid, slow)
        os.killpg(p.pid, signal.SIGINT)  # as Ctrl-C does: the whole process group
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode != 0
    m = re.search(r"interrupted after (\d) of 5 recordings: wrote the table of those to "
                  r"\S+fleet.parquet and \S+fleet.csv, and their calibration files to", err)
    assert m, err
    k = int(m.group(1))
    assert 1 <= k <= 4
    df = read_fleet_table(out / "fleet.parquet")
    assert len(df) == k and set(df["status"]) == {"ok"} and str(slow) not in set(df["path"])
    files = sorted(out.glob("*.json"))
    assert sorted(Path(f).name for f in df["cal_file"]) == [f.name for f in files]
    for f in files:
        assert ac.TriadModel.load(f).metadata["source"] in paths
    assert not list(out.glob(".*"))  # no temporary file left
    # the rerun keeps the identical files (the same recording, settings and date)
    before = {f.name: f.stat().st_mtime_ns for f in files}
    again = ac.calibrate_many(str(man), g=G0, out=out, workers=2, progress=False)
    assert len(again.attrs["cal_files_kept"]) == k
    assert {f.name: f.stat().st_mtime_ns for f in files} == before
    assert len(list(out.glob("*.json"))) == 4


def test_a_copy_under_another_name_is_noted_and_an_error_row_names_its_file(
        tmp_path: Path) -> None:
    recs = fleet_recordings(tmp_path / "rec", 2, corrupt=0, seed=5)
    a = Path(recs[0].path)
    copy = tmp_path / "rec" / "S00000 copy.csv"
    copy.write_bytes(a.read_bytes())
    link = tmp_path / "rec" / "S00000 link.csv"
    link.symlink_to(a)
    cut = tmp_path / "rec" / "cut.csv"
    cut.write_bytes(a.read_bytes()[:1000])
    df = ac.calibrate_many([str(a), str(copy), recs[1].path, str(link), str(cut)], g=G0,
                           workers=1, progress=False)
    assert df["status"].tolist() == ["ok", "ok", "ok", "error"]  # the link: listed twice
    sha = hashlib.sha256(a.read_bytes()).hexdigest()[:12]
    assert f"the same bytes as {copy} (SHA-256 {sha}...)" in df.loc[0, "message"]
    assert re.search(rf"^the same bytes as {re.escape(str(a))} \(SHA-256 {sha}\.\.\.\): a copy "
                     "of one recording under another name", df.loc[1, "message"])
    assert "same bytes" not in df.loc[2, "message"]
    np.testing.assert_array_equal(df.loc[0, PARAMS].to_numpy(float),
                                  df.loc[1, PARAMS].to_numpy(float))
    assert re.match(rf"{re.escape(str(cut))}: stream too short for dwell detection",
                    df.loc[3, "message"]), df.loc[3, "message"]
    assert [n["sensor_id"] for n in ac.fleet_report(df).noted] == ["S00000", "S00000 copy"]


def test_fleet_files_and_tables_record_how_they_were_made(fleet: dict[str, Any],
                                                          tmp_path: Path) -> None:
    """A fleet calibration file records what `calibrate static -o` records (input, model,
    method, dwells_from, detector, command, written); the tables record the version, the
    detector settings and the command; a file of other settings is named with them."""
    recs = [r for r in fleet["recs"] if not r.corruption][:2]
    man = tmp_path / "manifest.csv"
    pd.DataFrame({"path": [r.path for r in recs], "sensor_id": [r.sensor_id for r in recs],
                  "date": ["2026-01-02T03:04:05Z"] * 2}).to_csv(man, index=False)
    out = tmp_path / "cals"
    args = ["calibrate", "static", "--manifest", str(man), "--g", str(G0), "--out", str(out),
            "--workers", "1", "--quiet"]
    code, text = _cli(*args)
    assert code == 0, text
    files = sorted(out.glob("*.json"))
    assert [f.name for f in files] == [f"{r.sensor_id}_20260102T030405Z.json" for r in recs]
    det = dict(ac.DetectorSettings().__dict__)
    for f, r in zip(files, recs, strict=True):
        md = json.loads(f.read_text())["metadata"]
        data = Path(r.path).read_bytes()
        assert md["input"] == {"path": os.path.abspath(r.path),
                               "sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
        assert (md["model"], md["method"], md["dwells_from"]) == ("lower", "lm", "detected")
        assert md["detector"] == det
        assert md["command"] == (f"accelcal calibrate static --g {G0} --quiet --out {out} "
                                 f"--workers 1 --manifest {man}")
        assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", md["written"])
    run = {"accelcal_version": ac.__version__, "detector": det,
           "command": json.loads(files[0].read_text())["metadata"]["command"]}
    lines = (out / "fleet.csv").read_text().splitlines()
    assert lines[:3] == [f"# accelcal_version: {ac.__version__}",
                         f"# detector: {json.dumps(det, sort_keys=True)}",
                         f"# command: {run['command']}"]
    assert lines[3].startswith("sensor_id,path,status,")
    from_csv, from_pq = read_fleet_table(out / "fleet.csv"), read_fleet_table(out / "fleet.parquet")
    assert list(from_csv.columns) == list(from_pq.columns)
    cols = ["sensor_id", "path", "status", *PARAMS]
    pd.testing.assert_frame_equal(from_csv[cols], from_pq[cols], check_dtype=False)
    for df in (from_csv, from_pq):
        assert {k: df.attrs.get(k) for k in run} == run
    import pyarrow.parquet as pq

    meta = pq.read_schema(out / "fleet.parquet").metadata
    assert meta[b"accelcal_version"] == ac.__version__.encode()
    assert json.loads(meta[b"accelcal_detector"]) == det
    assert meta[b"accelcal_command"] == run["command"].encode()
    code, text = _cli("fleet", "report", str(out / "fleet.csv"))
    assert code == 0 and "fleet: 2 recordings: 2 ok" in text, text

    # The same batch again (another time written): the files are kept, not written again.
    old = json.loads(files[0].read_text())
    old["metadata"]["written"] = "2000-01-01T00:00:00Z"
    files[0].write_text(json.dumps(old, indent=2) + "\n")
    kept = files[0].read_bytes()
    again = ac.calibrate_many(str(man), g=G0, out=out, workers=1, progress=False)
    assert sorted(again.attrs["cal_files_kept"]) == [str(f) for f in files]
    assert files[0].read_bytes() == kept and again.attrs["command"] is None
    # Other settings: a new file beside, and the row names the settings that differ.
    code, text = _cli(*args, "--k", "20", "--window", "0.5")
    assert code == 0, text
    assert len(list(out.glob("*.json"))) == 4
    want = (f"another calibration of {recs[0].path} (other settings: detector window_s 1.0 "
            "(this run: 0.5) and detector k 6.0 (this run: 20.0))")
    assert want in text, text


# ---- files beside the table, files that cannot be written -----------------------------------
def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def test_the_table_never_replaces_a_file_it_was_not_told_to(fleet: dict[str, Any],
                                                            tmp_path: Path) -> None:
    """`--summary results.parquet` also wrote results.csv, replacing the user's own
    results.csv without a word (and `--summary t.csv` replaced t.parquet). Now a file beside
    the table that is not a fleet table stops the run before any work, named, unless
    --overwrite; a fleet table written before is replaced (a rerun)."""
    a = _good(fleet, 1)[0]
    mine = tmp_path / "results.csv"
    mine.write_text("my hand-written results, not a fleet table\n")
    before = _sha(mine)
    out = tmp_path / "cals"
    with pytest.raises(ac.CalibrationError) as e:
        ac.calibrate_many([a], g=G0, out=out, summary=tmp_path / "results.parquet",
                          workers=1, progress=False)
    assert str(e.value) == (
        f"{str(mine)!r} exists and is not a fleet table: summary= {tmp_path / 'results.parquet'}"
        f" writes it beside {tmp_path / 'results.parquet'} (the table is written as Parquet "
        "and as CSV), which would replace it. Move it, choose another summary=, or give "
        "overwrite=True to replace it; nothing was done")
    assert _sha(mine) == before and not out.exists()
    assert not (tmp_path / "results.parquet").exists()
    # the command line: --summary t.csv and a t.parquet of the user's; then --overwrite
    other = tmp_path / "t.parquet"
    other.write_bytes(b"keep me")
    code, txt = _cli("calibrate", "static", a, "--g", str(G0), "--summary",
                     str(tmp_path / "t.csv"), "--quiet")
    assert code == 2 and f"{str(other)!r} exists and is not a fleet table: --summary " in txt
    assert "give --overwrite to replace it; nothing was done" in txt
    assert other.read_bytes() == b"keep me" and not (tmp_path / "t.csv").exists()
    code, txt = _cli("calibrate", "static", a, "--g", str(G0), "--summary",
                     str(tmp_path / "t.csv"), "--quiet", "--overwrite")
    assert code == 0, txt
    assert read_fleet_table(other).loc[0, "path"] == a
    # a fleet table there (this run's own, a rerun) is replaced without --overwrite
    code, txt = _cli("calibrate", "static", a, "--g", str(G0), "--summary",
                     str(tmp_path / "t.parquet"), "--quiet")
    assert code == 0, txt
    # --out alone: fleet.csv there that is not a fleet table is kept
    (out / "fleet.csv").parent.mkdir()
    (out / "fleet.csv").write_text("a,b\n1,2\n")
    with pytest.raises(ac.CalibrationError, match=r"fleet.csv' exists and is not a fleet "
                       r"table: out= writes the table there"):
        ac.calibrate_many([a], g=G0, out=out, workers=1, progress=False)
    assert (out / "fleet.csv").read_text() == "a,b\n1,2\n" and not list(out.glob("*.json"))


def test_a_calibration_file_that_cannot_be_written_is_its_rows_error(
        fleet: dict[str, Any], tmp_path: Path) -> None:
    """A calibration file whose name is too long for the file system (also: disk full, no
    permission) was taken for a dead worker: a 5 s wait and "the worker process ... died";
    with workers=1 the whole run stopped without a table. Now it is that row's error, naming
    the file and the OS error, and the run goes on."""
    a, b = _good(fleet, 2)
    long_id = "b" * 250
    man = pd.DataFrame({"path": [a, b], "sensor_id": [long_id, "short"],
                        "date": ["2026-11-21", "2026-11-21"]})
    for workers in (1, 2):
        out = tmp_path / f"cals{workers}"
        df = ac.calibrate_many(man, g=G0, out=out, workers=workers, progress=False)
        name = out / f"{long_id}_20261121T000000Z.json"
        assert df.loc[0, "status"] == "error" and df.loc[0, "cal_file"] == ""
        assert df.loc[0, "message"].startswith(
            f"the calibration file {name} could not be written ([Errno 36] File name too "
            "long); the fit is in this row"), df.loc[0, "message"]
        assert np.isfinite(df.loc[0, "sx"])
        assert df.loc[1, "status"] == "ok" and Path(df.loc[1, "cal_file"]).is_file()
        assert read_fleet_table(out / "fleet.parquet")["status"].tolist() == ["error", "ok"]


def test_a_full_disk_names_the_file_and_keeps_what_it_can(
        fleet: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A run that filled the disk ended with "[Errno 28] No space left on device" alone.
    Now each calibration file that could not be written is its row's error, the table's
    other file is still written, and the error names what failed and what was written."""
    import errno

    from accelcal import fleet as fleet_mod

    a, b = _good(fleet, 2)
    real_create, real_write = fleet_mod.atomic_create, fleet_mod.atomic_write
    full = {"on": False}

    def create(path: Any, data: Any) -> bool:
        if full["on"]:
            raise OSError(errno.ENOSPC, "No space left on device", str(path) + ".tmp")
        full["on"] = True  # the first file fits; then the disk is full
        return real_create(path, data)

    def write(path: Any, data: Any) -> Path:
        if str(path).endswith(".parquet"):
            raise OSError(errno.ENOSPC, "No space left on device", str(path) + ".tmp")
        return real_write(path, data)

    monkeypatch.setattr(fleet_mod, "atomic_create", create)
    monkeypatch.setattr(fleet_mod, "atomic_write", write)
    out = tmp_path / "cals"
    with pytest.raises(ac.CalibrationError) as e:
        ac.calibrate_many([a, b], g=G0, out=out, workers=1, progress=False)
    assert str(e.value) == (
        f"could not write the table: {out / 'fleet.parquet'} ([Errno 28] No space left on "
        f"device); wrote {out / 'fleet.csv'}; the calibration files written (1) are in {out}")
    df = read_fleet_table(out / "fleet.csv")
    assert df["status"].tolist() == ["ok", "error"]
    assert Path(df.loc[0, "cal_file"]).is_file() and df.loc[1, "cal_file"] == ""
    assert re.match(rf"the calibration file {re.escape(str(out))}/\S+\.json could not be "
                    r"written \(\[Errno 28\] No space left on device\)", df.loc[1, "message"])
