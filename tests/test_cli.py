"""The command line end to end on the real recordings and on bad input."""

from __future__ import annotations

import json
import re
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from accelcal.cli import main
from click.testing import CliRunner
from conftest import clipped_session, shared_data, vibrating_session, write_csv

XSENS = partial(shared_data, 'xsens-mti', 'xsens_acc.txt')
MPU = partial(shared_data, 'mpu6050-10poses', 'example_data_calibration.csv')
IMUCAL = partial(shared_data, 'imucal', 'example_ferraris_session.csv')
SEED004 = partial(shared_data, 'seed004')
PRINTED_TABLE = partial(shared_data, 'seed004', 'table1_as_printed.csv')




def run(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(main, list(args))
    assert "Traceback" not in r.output
    return r.exit_code, r.output


def test_demo_quick_finds_all_dwells_and_writes_figures(tmp_path: Path) -> None:
    code, out = run("demo", "--quick", "--out", str(tmp_path / "figs"))
    assert code == 0, out
    m = re.search(r"(\d+)/(\d+) detected dwells lie inside a true static interval", out)
    assert m and m.group(1) == m.group(2) == "20"
    for section in ("Static field", "gap diagnosis", "Centrifuge", "Gradiometer"):
        assert section.lower() in out.lower()
    pngs = sorted(p.name for p in (tmp_path / "figs").glob("*.png"))
    assert pngs == ["field_norm.png", "gap.png", "planned_poses.png"]


def test_demo_json_reports_the_field_fit_against_the_truth() -> None:
    from accelcal.sim import SEED000_TRUTH

    code, out = run("demo", "--quick", "--no-figures", "--json")
    assert code == 0, out
    res = json.loads(out)
    assert set(res["sections"]) == {"field", "gap", "centrifuge", "gradiometer"}
    assert res["field"]["n_dwells"] == 20 and res["figures"] is None
    fit = res["field"]["fit"]
    v = np.array(fit["vector"])
    std = np.array(fit["std"])
    # The demo's field session is simulated with the seed-000 truth: within 5 reported std.
    assert np.all(np.abs(v - SEED000_TRUTH) < 5 * std), (v, std)
    assert res["gap"]["best"] in res["sections"]["gap"]


def test_calibrate_apply_round_trip_on_xsens(tmp_path: Path) -> None:
    cal = tmp_path / "cal.json"
    code, out = run("calibrate", "static", str(XSENS()), "--g", "9.81744", "-o", str(cal),
                    "--json")
    assert code == 0, out
    res = json.loads(out)
    assert res["n_dwells"] >= 38
    # imu_tk's independent fit on its 38 intervals leaves 0.00098 m/s^2 on dwell means.
    assert 5e-4 < res["rms"] < 2e-3
    assert json.loads(cal.read_text())["version"] >= 1
    # Apply it to the same recording: static samples then have |a| close to g.
    calibrated = tmp_path / "cal.npy"
    code, out = run("apply", str(cal), str(XSENS()), "-o", str(calibrated), "--quiet")
    assert code == 0, out
    ta = np.load(calibrated)
    assert ta.shape == (51175, 4)  # t_s, ax, ay, az: the time column is kept
    np.testing.assert_array_equal(ta[:, 0], np.loadtxt(XSENS())[:, 0])
    a = ta[:, 1:]
    norm = np.linalg.norm(a[:4000], axis=1)  # the initial 40 s of rest
    assert abs(np.mean(norm) - 9.81744) < 5e-3
    # CSV output carries time and the same numbers (shortest round-trip text: identical).
    csv = tmp_path / "cal.csv"
    code, _ = run("apply", str(cal), str(XSENS()), "-o", str(csv), "--quiet")
    assert code == 0
    lines = csv.read_text().splitlines()
    head = [ln for ln in lines if ln.startswith("#")]
    assert lines[len(head)] == "t_s,ax,ay,az" and "# units: m/s^2" in head
    tab = np.loadtxt(csv, delimiter=",", skiprows=len(head) + 1)
    np.testing.assert_array_equal(tab, ta)


def test_calibrate_static_plot_and_readable_output(tmp_path: Path) -> None:
    png = tmp_path / "norm.png"
    code, out = run("calibrate", "static", str(XSENS()), "--g", "9.81744", "--plot", str(png))
    assert code == 0, out
    assert png.stat().st_size > 10_000
    for name in ("sx", "bz", "m3"):
        assert re.search(rf"^\s+{name}\s", out, re.M)


def test_weak_and_degenerate_designs_are_explained() -> None:
    code, out = run("calibrate", "static", str(MPU()), "--g", "9.81")
    assert code == 0
    assert "weak" in out.lower() and "m1" in out
    code, out = run("calibrate", "static", str(IMUCAL()), "--fs", "102.4", "--g", "9.81")
    assert code == 2
    assert "cannot determine" in out and "diag" in out
    code, out = run("calibrate", "static", str(IMUCAL()), "--fs", "102.4", "--g", "9.81",
                    "--model", "diag", "--json")
    assert code == 0
    assert len(json.loads(out)["vector"]) == 6


def test_diagnose_reports_the_xsens_gap(tmp_path: Path) -> None:
    code, out = run("diagnose", str(XSENS()), "--g", "9.81744", "--json")
    assert code == 0, out
    rep = json.loads(out)
    assert rep["chi2_per_dof"] > 3  # the documented real gap
    blind = json.dumps(rep["blind_spots"])
    assert "temperature" in blind  # not recorded: not testable, never "no effect"


def test_centrifuge_and_gradiometer_tables(tmp_path: Path) -> None:
    code, out = run("calibrate", "centrifuge", str(SEED004() / "table1_as_printed.csv"),
                    "--radius", "1", "--g", "9.8", "--json")
    assert code == 0, out
    res = json.loads(out)
    assert len(res["outliers"]) == 23
    np.testing.assert_allclose(res["scale"], [1.29, 1.21, 1.26], rtol=1e-6)
    tab = tmp_path / "startup.csv"
    # y = bias + R(2 theta) gamma with bias (3, -2) E and gradient (10, 5) E.
    rows = ["azimuth_deg,inline_E,cross_E"]
    for th in (0.0, 45.0, 90.0, 135.0):
        c, s = np.cos(np.radians(2 * th)), np.sin(np.radians(2 * th))
        rows.append(f"{th},{3 + c * 10 + s * 5},{-2 - s * 10 + c * 5}")
    tab.write_text("\n".join(rows) + "\n")
    code, out = run("calibrate", "gradiometer", str(tab), "--json")
    assert code == 0, out
    np.testing.assert_allclose(json.loads(out)["bias_E"], [3.0, -2.0], atol=1e-9)


def test_plan_prints_attitudes_and_predicted_std() -> None:
    code, out = run("plan", "--n", "12", "--max-tilt", "30", "--json")
    assert code == 0, out
    p = json.loads(out)
    assert len(p["tilts_deg"]) == 12
    assert all(abs(v) <= 30 + 1e-9 for row in p["tilts_deg"] for v in row)
    assert p["predicted_std"]["bz"] > 0


@pytest.mark.parametrize(
    "args, needle",
    [
        (["dwells", "/nonexistent/recording.txt", "--fs", "100"], "/nonexistent/recording.txt"),
        (["calibrate", "static", XSENS], "--g"),
        (["calibrate", "static", XSENS, "--g", "-1"], "g"),
        (["calibrate", "centrifuge", PRINTED_TABLE, "--radius", "-1"], "radius"),
        (["apply", "/nonexistent/cal.json", XSENS, "-o", "/tmp/x.csv"], "cal.json"),
        (["calibrate", "static", IMUCAL, "--g", "9.81"], "--fs"),
    ],
)
def test_bad_input_is_one_clear_line(args: list[Any], needle: str) -> None:
    code, out = run(*(str(a()) if callable(a) else a for a in args))
    assert code == 2
    lines = [ln for ln in out.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("accelcal: error:")
    assert needle in lines[0]


def test_unreadable_file_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "garbage.txt"
    bad.write_bytes(b"\x00\xff\x00 not numbers at all\nfoo bar baz\n")
    code, out = run("dwells", str(bad), "--fs", "100")
    assert code == 2
    assert str(bad) in out


# ---- streaming commands: dwells, apply, reading options ----------------------------------------
def _calibration(tmp_path: Path) -> Path:
    cal = tmp_path / "cal.json"
    code, out = run("calibrate", "static", str(XSENS()), "--g", "9.81744", "-o", str(cal),
                    "--quiet")
    assert code == 0, out
    return cal


def test_apply_writes_every_format_with_time_and_json(tmp_path: Path) -> None:
    import h5py
    from accelcal import TriadModel
    from accelcal.io import read_stream

    cal = _calibration(tmp_path)
    st = read_stream(XSENS())
    want = TriadModel.load(cal).apply(st.samples)
    got: dict[str, Any] = {}
    for ext in ("csv", "npy", "npz", "h5"):
        out = tmp_path / f"out.{ext}"
        code, text = run("apply", str(cal), str(XSENS()), "-o", str(out), "--chunk-rows",
                         "7000", "--json")
        assert code == 0, text
        res = json.loads(text)
        assert res["rows"] == 51175 and res["format"] == ext and res["time_column"] is True
        assert res["units"] == "m/s^2"
        if ext == "csv":
            r = read_stream(out)
            got[ext] = (r.t, r.samples)
        elif ext == "npy":
            a = np.load(out)
            got[ext] = (a[:, 0], a[:, 1:])
        elif ext == "npz":
            with np.load(out) as z:
                got[ext] = (z["t"], z["samples"])
        else:
            with h5py.File(out, "r") as f:
                got[ext] = (f["t"][()], f["samples"][()])
                assert f.attrs["units"] == "m/s^2"
    for ext, (t, a) in got.items():
        np.testing.assert_array_equal(t, st.t, err_msg=ext)
        np.testing.assert_array_equal(a, want, err_msg=ext)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "cal.json", "out.csv", "out.h5", "out.npy", "out.npz"]  # no temporary files left


def test_interrupted_apply_leaves_the_old_output(tmp_path: Path) -> None:
    cal = _calibration(tmp_path)
    good = tmp_path / "rec.csv"
    rows = "".join(f"{i / 100},{33000 + i % 7},{33200 - i % 5},{36400 + i % 3}\n"
                   for i in range(200_000))
    good.write_text("t,ax,ay,az\n" + rows)
    bad = tmp_path / "bad.csv"
    # 3000 rows that do not parse among 200 000 (1.5 %): found at the end of the pass, after
    # output has been written.
    bad.write_text("t,ax,ay,az\n" + rows + "2000,1,2,three\n" * 3000)
    for ext in ("csv", "npy", "npz", "h5"):
        out = tmp_path / f"out.{ext}"
        code, text = run("apply", str(cal), str(good), "-o", str(out), "--quiet")
        assert code == 0, text
        before = out.read_bytes()
        code, text = run("apply", str(cal), str(bad), "-o", str(out), "--quiet")
        assert code == 2 and "line 200002" in text and "three" in text, text
        assert "3000 of the 203000 data rows do not parse" in text, text
        assert out.read_bytes() == before, ext
    left = [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
    assert left == []


def test_calibration_file_without_k_is_one_line(tmp_path: Path) -> None:
    cal = _calibration(tmp_path)
    d = json.loads(cal.read_text())
    del d["K"]
    broken = tmp_path / "broken.json"
    broken.write_text(json.dumps(d))
    code, out = run("apply", str(broken), str(XSENS()), "-o", str(tmp_path / "x.csv"))
    assert code == 2, out
    lines = out.strip().splitlines()
    assert len(lines) == 1 and "'K'" in lines[0] and "internal error" not in out


def test_dwell_table_feeds_calibrate_static(tmp_path: Path) -> None:
    table = tmp_path / "dwells.csv"
    code, out = run("dwells", str(XSENS()), "-o", str(table), "--quiet")
    assert code == 0, out
    code, a = run("calibrate", "static", str(XSENS()), "--g", "9.81744", "--json", "--quiet")
    assert code == 0, a
    code, b = run("calibrate", "static", str(table), "--g", "9.81744", "--json")
    assert code == 0, b
    ra, rb = json.loads(a), json.loads(b)
    assert ra["n_dwells"] == rb["n_dwells"] >= 38
    np.testing.assert_array_equal(ra["vector"], rb["vector"])
    assert rb["samples"] is None and ra["samples"] == 51175
    # Without its first comment lines (a table a user cut down, or wrote with a script of
    # their own), with or without --means, it is still the dwell table: the variances and
    # counts are the noise model (they were dropped, and the noise estimated, before).
    bare = tmp_path / "bare.csv"
    bare.write_text("".join(ln for ln in table.read_text().splitlines(keepends=True)
                            if not ln.startswith("#")))
    for extra in ((), ("--means",)):
        code, c = run("calibrate", "static", str(bare), "--g", "9.81744", "--json", *extra)
        assert code == 0, c
        rc = json.loads(c)
        assert rc["noise_model"] == rb["noise_model"] and "variance" in rc["noise_model"]
        np.testing.assert_allclose(rc["vector"], rb["vector"], rtol=1e-9)
    code, c = run("calibrate", "static", str(bare), "--g", "9.81744", "--count", "10")
    assert code == 2 and "is a dwell table already" in c, c


def test_stdin_and_column_options(tmp_path: Path) -> None:
    r = CliRunner().invoke(main, ["dwells", "-", "--json"], input=XSENS().read_bytes())
    assert r.exit_code == 0, r.output
    piped = json.loads(r.stdout)
    code, out = run("dwells", str(XSENS()), "--json", "--columns", "1,2,3")
    assert code == 0, out
    by_index = json.loads(out)
    assert piped["mean"] == by_index["mean"] and piped["samples"] == 51175
    # --columns by index keeps the time column: dwell mid times are times, not indices/fs.
    assert by_index["t"] == piped["t"] and by_index["fs_hz"] == pytest.approx(100.0, rel=1e-3)


def test_messages_name_command_line_options(tmp_path: Path) -> None:
    code, out = run("dwells", str(IMUCAL()))
    assert code == 2 and "--fs" in out and "fs=" not in out, out
    code, out = run("dwells", str(XSENS()), "--columns", "ax,ay")
    assert code == 2 and "--columns" not in out or "columns" in out, out
    wide = tmp_path / "wide.txt"
    wide.write_text("".join(f"{i % 3} {i % 5} 1 2 3\n" for i in range(300)))
    code, out = run("dwells", str(wide), "--fs", "100")
    assert code == 2 and "--columns" in out and "--time-column" in out, out
    assert "columns=" not in out and "time_column=" not in out
    # A time column that disagrees with --fs is said (on stderr, with the table on stdout).
    r = CliRunner().invoke(main, ["dwells", str(XSENS()), "--fs", "200"])
    assert r.exit_code == 0
    assert "note:" in r.stderr and "200 Hz is used" in r.stderr and "--fs" in r.stderr
    assert "note:" not in r.stdout


def test_dwells_plot_shows_the_stream_with_dwells(tmp_path: Path) -> None:
    png = tmp_path / "dwells.png"
    code, out = run("dwells", str(XSENS()), "--plot", str(png), "--quiet")
    assert code == 0, out
    assert png.stat().st_size > 20_000
    # The figure itself: three axes in the file's units against time, one span per dwell.
    import matplotlib.pyplot as plt
    from accelcal.io import read_stream, stream_dwells
    from accelcal.plots import dwells_figure

    st = read_stream(XSENS())
    d = stream_dwells(XSENS())
    t = st.t - st.t[0]
    fig = dwells_figure(t, st.samples, st.samples, st.samples, d, units="counts")
    axes = fig.axes
    assert [a.get_ylabel() for a in axes] == ["x [counts]", "y [counts]", "z [counts]"]
    assert axes[-1].get_xlabel() == "time [s]"
    spans = [p for p in axes[0].patches]
    assert len(spans) == len(d) >= 38
    x0 = sorted(p.get_x() for p in spans)
    np.testing.assert_allclose(x0, np.sort(d.start / d.fs))
    plt.close(fig)


def test_diagnose_reads_a_dwell_table(tmp_path: Path) -> None:
    table = tmp_path / "dwells.csv"
    code, out = run("dwells", str(XSENS()), "-o", str(table), "--quiet")
    assert code == 0, out
    code, a = run("diagnose", str(XSENS()), "--g", "9.81744", "--noise", "white", "--json",
                  "--quiet")
    assert code == 0, a
    code, b = run("diagnose", str(table), "--g", "9.81744", "--noise", "white", "--json")
    assert code == 0, b
    ra, rb = json.loads(a), json.loads(b)
    assert ra["chi2_per_dof"] == pytest.approx(rb["chi2_per_dof"], rel=1e-12)
    assert ra["chi2_per_dof"] > 3


def test_ctrl_c_during_apply_leaves_the_old_output(tmp_path: Path) -> None:
    """The recording arrives on stdin and the test holds the rest back, so apply is still
    running whatever the machine's speed when SIGINT comes."""
    import signal
    import subprocess
    import sys
    import time

    from accelcal import _core

    cal = _calibration(tmp_path)
    i = np.arange(500_000, dtype=np.float64)
    x = np.column_stack([33000 + i % 7, 33200 - i % 5, 36400 + i % 3])
    first = b"t,ax,ay,az\n" + _core.format_rows(x, i / 100.0)
    out = tmp_path / "out.npy"
    np.save(out, np.zeros((2, 4)))
    before = out.read_bytes()
    code = "import sys; from accelcal.cli import main; main(sys.argv[1:])"
    p = subprocess.Popen([sys.executable, "-c", code, "apply", str(cal), "-", "--fs", "100",
                          "-o", str(out), "--chunk-rows", "20000"],
                         stdin=subprocess.PIPE, stderr=subprocess.DEVNULL)
    assert p.stdin is not None
    p.stdin.write(first)
    p.stdin.flush()
    deadline = time.monotonic() + 60
    while not any(q.name.startswith(".accelcal-tmp-out.npy") for q in tmp_path.iterdir()):
        assert p.poll() is None and time.monotonic() < deadline, "apply ended too soon"
        time.sleep(0.01)
    p.send_signal(signal.SIGINT)
    time.sleep(0.2)
    p.stdin.close()  # the rest of the recording never comes
    assert p.wait(timeout=60) != 0
    assert out.read_bytes() == before
    assert [q.name for q in tmp_path.iterdir() if q.name.startswith(".")] == []


def test_dwells_line_counts_the_dropouts(tmp_path: Path) -> None:
    from accelcal.sim import field_session

    s = field_session(fs=100.0, n_dwells=8, dwell_s=10.0, move_s=3.0, rng=4)
    x = s.samples.copy()
    bad = np.array([s.bounds[k, 0] + 500 for k in (1, 4, 6)])  # inside three dwells
    x[bad] = np.nan
    p = tmp_path / "drops.csv"
    np.savetxt(p, np.column_stack([s.t, x]), delimiter=",", header="t,ax,ay,az",
               comments="", fmt="%.9g")
    code, out = run("dwells", str(p), "--quiet")
    assert code == 0, out
    m = re.search(r"-> (\d+) dwells \((\d+) rows with NaN or inf samples: dropouts", out)
    assert m and m.group(2) == "3", out
    # The dropouts are left out of the statistics: no dwell is split around them.
    assert int(m.group(1)) == 8, out


def test_saturated_dwells_are_left_out_and_named(tmp_path: Path) -> None:
    s, x, truth = clipped_session()
    p = write_csv(tmp_path / "clipped.csv", s.t, x, fmt=["%.4f", "%d", "%d", "%d"])
    n, k = len(truth), len(s.bounds)
    code, out = run("calibrate", "static", str(p), "--g", "9.80665", "--quiet")
    assert code == 0, out
    assert f"note: {n} of {k} dwells left out, {k - n} used" in out
    named = {int(m.group(1)) for m in re.finditer(
        r"dwell (\d+) \(t = [\d.]+ s\): [xyz] = -?1556[45] in all \d+ samples .*saturated", out)}
    assert named == set(truth)
    assert f"-> {k} dwells" in out and f"{k - n} dwells, g = 9.80665" in out
    code, js = run("calibrate", "static", str(p), "--g", "9.80665", "--quiet", "--json")
    fit = json.loads(js)
    assert code == 0 and fit["n_dwells"] == k - n and fit["chi2_dof"] < 2
    # The dwell table keeps every dwell and says which are faulty; calibrating from it leaves
    # the same ones out.
    table = tmp_path / "dwells.csv"
    code, out = run("dwells", str(p), "-o", str(table), "--quiet")
    assert code == 0 and f"{n} of {k} dwells have an output that did not follow" in out, out
    code, js2 = run("calibrate", "static", str(table), "--g", "9.80665", "--json")
    assert code == 0 and json.loads(js2)["vector"] == pytest.approx(fit["vector"], rel=1e-9)
    code, js3 = run("dwells", str(p), "--quiet", "--json")
    listed = json.loads(js3)["faults"]
    assert code == 0 and {f["dwell"]: f["kind"] for f in listed} == truth
    assert all(f["value"] == f["rail"] and abs(f["rail"]) == 15564 for f in listed)
    code, out = run("diagnose", str(p), "--g", "9.80665", "--quiet")
    assert code == 0 and f"{n} of {k} dwells left out" in out, out
    chi2 = float(re.search(r"chi2/dof = ([\d.]+)", out).group(1))  # type: ignore[union-attr]
    assert chi2 < 3, out


def test_vibrating_poses_are_named_when_too_few_dwells_remain(tmp_path: Path) -> None:
    s, x = vibrating_session(axes=(1.0, 1.0, 1.0))
    p = write_csv(tmp_path / "pump.csv", s.t, x)
    code, out = run("calibrate", "static", str(p), "--g", "9.80665", "--quiet")
    assert code != 0 and "8 dwells found" in out, out
    m = re.search(r"Note: 8 stretch\(es\) \([\d.]+ s in all, the first at [\d.]+ s\) look still "
                  r".* --k (\d+) would take them", out)
    assert m, out
    code, out = run("calibrate", "static", str(p), "--g", "9.80665", "--quiet", "--k", m.group(1))
    assert code == 0 and "-> 16 dwells" in out, out


def test_bounds_file_replaces_detection(tmp_path: Path) -> None:
    js = str(shared_data("imucal", "example_ferraris_session_list.json"))
    code, out = run("dwells", str(IMUCAL()), "--fs", "102.4", "--bounds", js, "--json")
    assert code == 0, out
    rep = json.loads(out)
    assert rep["count"] == [731, 741, 484, 412, 453, 607] and rep["start"][0] == 540
    assert any("x_rot, y_rot, z_rot" in n for n in rep["notes"])
    code, out = run("dwells", str(IMUCAL()), "--fs", "102.4", "--bounds", js, "--plot",
                    str(tmp_path / "d.png"))
    assert code == 0 and (tmp_path / "d.png").stat().st_size > 10_000, out
    code, out = run("calibrate", "static", str(IMUCAL()), "--fs", "102.4", "--g", "9.81",
                    "--model", "diag", "--bounds", js, "--json")
    assert code == 0, out
    assert json.loads(out[out.index("{"):])["dof"] == 0  # six faces, six parameters
    # Seconds from the first sample, in a CSV (a sequencer's log).
    secs = tmp_path / "log.csv"
    secs.write_text("face,start_s,stop_s\n" + "".join(
        f"f{i},{a / 102.4!r},{b / 102.4!r}\n" for i, (a, b) in enumerate(
            [(540, 1271), (1620, 2361), (2814, 3298), (3740, 4152), (4522, 4975),
             (5376, 5983)])))
    code, out2 = run("dwells", str(IMUCAL()), "--fs", "102.4", "--bounds", str(secs), "--json")
    assert code == 0 and json.loads(out2)["count"] == rep["count"], out2
    code, out = run("diagnose", str(IMUCAL()), "--fs", "102.4", "--g", "9.81", "--bounds", js)
    assert code == 2 and "needs at least 10 dwells" in out  # 6 faces, 9 parameters
    assert "check a calibration made on another session against this one with --calibration " \
        "(a TriadModel): 2 dwells suffice" in out
    code, out = run("calibrate", "static", str(IMUCAL()), str(XSENS()), "--g", "9.81",
                    "--bounds", js)
    assert code == 2 and "--bounds takes one recording" in out
    far = tmp_path / "far.json"
    far.write_text("[[0, 100], [500, 99999999]]")
    code, out = run("dwells", str(IMUCAL()), "--fs", "102.4", "--bounds", str(far))
    assert code == 2 and f"{far} (dwell bounds of " in out and "out of range" in out, out
    far.write_text("[[100, 50]]")
    code, out = run("dwells", str(IMUCAL()), "--fs", "102.4", "--bounds", str(far))
    assert code == 2 and "empty or reversed" in out and "time column" not in out, out


def test_a_named_pipe_is_refused_not_waited_on(tmp_path: Path) -> None:
    import os
    import subprocess
    import sys

    fifo = str(tmp_path / "rec.csv")
    os.mkfifo(fifo)  # nobody writes: opening it for reading would block for ever
    exe = str(Path(sys.executable).with_name("accelcal"))
    for args in (["dwells", fifo], ["calibrate", "static", fifo, "--g", "9.81"],
                 ["diagnose", fifo, "--g", "9.81"]):
        r = subprocess.run([exe, *args], capture_output=True, text=True, timeout=60)
        assert r.returncode == 2, (args, r.stderr)
        assert "is not a regular file (a pipe or a device)" in r.stderr, r.stderr


def test_diagnose_takes_the_detector_settings_of_a_low_rate_log(tmp_path: Path) -> None:
    """A logger at 4 Hz: the default 1 s window is too short (the error names --window and
    the shortest one that works); diagnose takes --window as calibrate does, with the same
    dwells, and runs the Allan noise model on the samples with those settings."""
    from accelcal.sim.field import field_session

    s = field_session(fs=4.0, n_dwells=16, dwell_s=30.0, move_s=8.0, max_tilt_deg=80.0,
                      sigma=0.01, rng=8)
    p = write_csv(tmp_path / "slow.csv", s.t, s.samples)
    code, out = run("diagnose", str(p), "--g", str(s.g))
    assert code == 2 and "give --window 2 s or more" in out, out
    code, out = run("diagnose", str(p), "--g", str(s.g), "--window", "3")
    assert code == 0, out
    m = re.search(r"(\d+) samples at 4 Hz -> (\d+) dwells", out)
    assert m and int(m.group(2)) == 16, out
    code, cal = run("calibrate", "static", str(p), "--g", str(s.g), "--window", "3", "--json")
    assert code == 0 and json.loads(cal)["n_dwells"] == 16


def test_a_static_recording_too_short_is_told_the_length_it_needs(tmp_path: Path) -> None:
    """1.5 s at rest: no dwell, because the stream's outer half windows and the trims leave
    under --min-dwell. The error gives the length needed in CLI words (it used to advise a
    larger k, which cannot help); 2.5 s gives one dwell."""
    rng = np.random.default_rng(1)
    t = np.arange(250) / 100.0
    s = np.array([0.0, 0.0, 9.81]) + 0.01 * rng.standard_normal((250, 3))
    short = write_csv(tmp_path / "short.csv", t[:150], s[:150])
    code, out = run("dwells", str(short))
    assert code == 2 and "the whole stream is static but too short" in out, out
    assert "about 2.20 s in all. Record longer, or lower --min-dwell or --window" in out, out
    assert "--k" not in out and "raise k" not in out
    code, out = run("dwells", str(write_csv(tmp_path / "long.csv", t, s)))
    assert code == 0 and "250 samples at 100 Hz -> 1 dwell\n" in out, out


@pytest.mark.parametrize(("fs", "rest_s", "window"), [(19.0, 1.0, "0.5"), (100.0, 0.4, "0.1")])
def test_brief_rests_are_told_the_settings_that_find_them(
        tmp_path: Path, fs: float, rest_s: float, window: str) -> None:
    """A hand-turned sensor held a second in each pose at 19 Hz (AhmedFouad23's MPU-6050
    captures), or 0.2-0.4 s at 100 Hz (mgiurato's LSM303 log): the defaults need rests of
    2.2 s and found none, and "lower --min-dwell or --window" could not reach them while the
    0.1 s trim stayed. Now the refusal names shorter settings (--trim among them) that find
    every rest, and following it gives the simulator's calibration."""
    from accelcal.sim.field import field_session

    tilts = np.random.default_rng(1).uniform(-80, 80, size=(18, 2))
    s = field_session(fs=fs, dwell_s=rest_s, move_s=1.0, tilts_deg=tilts, sigma=2e-3, rng=2)
    p = write_csv(tmp_path / "brief.csv", s.t, s.samples)
    code, out = run("calibrate", "static", str(p), "--g", str(s.g))
    assert code == 2 and "no static dwell found" in out, out
    assert "a rest must last a window, the shortest dwell and two trims, 2.200 s here" in out
    m = re.search(r"Shorter settings, --window ([\d.]+) s with --min-dwell ([\d.]+) s and "
                  r"--trim ([\d.]+) s, find 18 steady dwell\(s\)", out)
    assert m and m.group(1) == window, out
    code, out = run("calibrate", "static", str(p), "--g", str(s.g), "--window", m.group(1),
                    "--min-dwell", m.group(2), "--trim", m.group(3), "--json")
    assert code == 0, out
    res = json.loads(out)
    assert res["n_dwells"] == 18
    got, std = np.array(res["vector"]), np.array(res["std"])
    assert np.all(np.abs(got - s.truth) < 5 * std), (got - s.truth) / std


def test_a_short_file_counts_every_sample_in_its_refusal(tmp_path: Path) -> None:
    """89 rows at 100 Hz: the refusal said "88 samples" (the detector's whole blocks)."""
    t = np.arange(89) / 100.0
    x = np.array([0.0, 0.0, 9.81]) + 0.01 * np.random.default_rng(0).standard_normal((89, 3))
    code, out = run("dwells", str(write_csv(tmp_path / "short.csv", t, x)))
    assert code == 2 and "89 samples" in out and "88 samples" not in out, out


def test_a_session_mostly_in_motion_is_told_how_to_find_shorter_rests(tmp_path: Path) -> None:
    """Brief pauses (1.4 s) between long moves (a hand-waved sensor, as an imu_tk fork's data
    showed): too few dwells for the model, and the error says how little was still and the
    trade-off of a shorter window (here a 0.2 s window takes the slow ends of the moves)."""
    from accelcal.sim.field import field_session

    s = field_session(fs=100.0, n_dwells=14, dwell_s=1.4, move_s=9.0, max_tilt_deg=80.0,
                      sigma=0.01, rng=2)
    p = write_csv(tmp_path / "waved.csv", s.t, s.samples)
    code, out = run("calibrate", "static", str(p), "--g", str(s.g))
    assert code == 2 and "8 dwells found" in out, out
    m = re.search(r"Only (\d+) % of the recording was taken as still \(dwells of at least "
                  r"--min-dwell 1 s, window 1 s\): if the sensor rested in shorter pauses, a "
                  r"shorter --window and --min-dwell find them, but also take the slow ends "
                  r"of moves; check the dwells plot and the fit's chi2/dof", out)
    assert m and int(m.group(1)) < 25, out
    code, out = run("calibrate", "static", str(p), "--g", str(s.g), "--min-dwell", "0.4",
                    "--window", "0.2", "--json")
    assert code == 0 and json.loads(out)["chi2_dof"] > 30, out  # the trade-off, measured
    # Too few dwells even for the bias + scale model: that hint is not given.
    q = write_csv(tmp_path / "two.csv", s.t[:1500], s.samples[:1500])
    code, out = run("calibrate", "static", str(q), "--g", str(s.g))
    assert code == 2 and "even --model diag (bias + scale) needs 6 dwells" in out, out
    assert "Try --model diag" not in out


def test_a_single_long_rest_is_refused_without_dead_end_advice(tmp_path: Path) -> None:
    """tomisuarez2's initialisation-time recording: one rest of 449 s. Every refusal is
    right, but the advice led nowhere: "Try --model diag" for dwells that are one pose (diag
    fails alike), --calibration for 1 dwell (it needs 2), "1 dwells"; and the dwell table's
    noise line is the detector's noise level (a low quantile), not the noise std."""
    rng = np.random.default_rng(2)
    n = 3000
    s = np.array([2643.6, -642.7, 14791.4]) + [53.0, 49.0, 75.0] * rng.standard_normal((n, 3))
    p = tmp_path / "rest.csv"
    p.write_text("Fs,100\nax,ay,az\n" + "".join(f"{a:.0f},{b:.0f},{c:.0f}\n" for a, b, c in s))
    code, out = run("dwells", str(p))
    assert code == 0 and "-> 1 dwell\n" in out, out
    assert "detector's noise level per axis x, y, z (a low quantile of the window stds" in out
    code, out = run("calibrate", "static", str(p), "--g", "9.80665")
    assert code == 2 and "1 dwell found in" in out and "1 dwell cannot determine" in out, out
    assert "Try --model diag" not in out
    code, out = run("diagnose", str(p), "--g", "9.80665")
    assert code == 2 and "1 dwell: the 9-parameter model needs at least 10 dwells" in out, out
    assert "--calibration" not in out and "2 dwells suffice" not in out
    # Cut by hand into 10 pieces: one pose, so no model can be fitted; diag is not offered.
    b = tmp_path / "pieces.csv"
    b.write_text("start,stop\n" + "".join(f"{300 * k},{300 * k + 290}\n" for k in range(10)))
    code, out = run("calibrate", "static", str(p), "--g", "9.80665", "--bounds", str(b))
    assert code == 2 and "the 10 dwells are one pose" in out, out
    assert "Try --model diag" not in out


def test_a_refusal_with_json_is_json_on_stdout(tmp_path: Path) -> None:
    """With --json, a refusal printed nothing on stdout (the error went to stderr only): a
    script parsing stdout got an empty string. It now gets {"error": ..., "exit_code": 2}."""
    p = tmp_path / "rest.csv"
    rng = np.random.default_rng(1)
    s = np.array([0.0, 0.0, 9.81]) + 0.01 * rng.standard_normal((2000, 3))
    p.write_text("Fs,100\nax,ay,az\n" + "".join(f"{a:.5f},{b:.5f},{c:.5f}\n" for a, b, c in s))
    r = CliRunner().invoke(main, ["calibrate", "static", str(p), "--g", "9.81", "--json"])
    assert r.exit_code == 2
    out = json.loads(r.stdout)
    assert out["exit_code"] == 2 and out["error"].startswith("1 dwell found in"), r.stdout
    assert "accelcal: error: 1 dwell found" in r.stderr
    r = CliRunner().invoke(main, ["calibrate", "static", str(p), "--g", "9.81"])
    assert r.exit_code == 2 and r.stdout == ""  # without --json: stderr only


def test_model_diag_is_offered_only_when_it_fits(tmp_path: Path) -> None:
    """The refusal's "Try --model diag" is checked by fitting it: poses turned only about the
    x axis (x never towards gravity) leave the bias + scale model undetermined too, so it is
    not offered there; six faces (misalignments barely seen) fit it, and it is named."""
    from accelcal import DwellSet

    rng = np.random.default_rng(4)

    def table(gravity: np.ndarray, name: str) -> Path:
        """Dwell means of one sensor (scales, biases) at these gravity vectors, noise 1e-4."""
        m = gravity @ np.diag([1.01, 0.99, 1.02]).T + [0.05, -0.03, 0.02]
        m = m + 1e-4 * rng.standard_normal(m.shape)
        path = tmp_path / name
        DwellSet(m, np.full((len(m), 3), 1e-6), np.full(len(m), 100)).to_csv(path)
        return path

    th = np.linspace(0.0, 2 * np.pi, 14, endpoint=False)
    p = table(9.80665 * np.column_stack([np.zeros_like(th), np.cos(th), np.sin(th)]),
              "about_x.csv")
    code, out = run("calibrate", "static", str(p), "--g", "9.80665")
    assert code == 2 and "cannot determine" in out, out
    assert "Try --model diag" not in out
    code, out = run("calibrate", "static", str(p), "--g", "9.80665", "--model", "diag")
    assert code == 2, out  # what the hint would have led to
    q = table(np.vstack([np.eye(3), -np.eye(3), np.eye(3), -np.eye(3)]) * 9.80665, "faces.csv")
    code, out = run("calibrate", "static", str(q), "--g", "9.80665")
    assert code == 2 and "--model diag" in out, out
    code, out = run("calibrate", "static", str(q), "--g", "9.80665", "--model", "diag")
    assert code == 0, out


def test_no_command_writes_over_its_own_input(tmp_path: Path) -> None:
    """Only `apply FILE -o FILE` was refused: `calibrate static r.csv -o r.csv`, `--dwells-out
    r.csv`, `dwells r.csv -o r.csv`, `apply cal.json r.csv -o cal.json` and the centrifuge and
    gradiometer tables' -o each replaced their input with exit 0. Now every command refuses
    before it reads or writes anything, and the inputs keep their bytes."""
    from accelcal.sim.field import field_session

    s = field_session(fs=200.0, n_dwells=12, dwell_s=3.0, move_s=1.0, max_tilt_deg=80.0,
                      sigma=2e-3, rng=3)
    rec = write_csv(tmp_path / "rec.csv", s.t, s.samples)
    cal = tmp_path / "cal.json"
    code, out = run("calibrate", "static", str(rec), "--g", str(s.g), "-o", str(cal))
    assert code == 0, out
    grad = tmp_path / "g.csv"
    grad.write_text("azimuth_deg,inline_E,cross_E\n0,52.3,-32.1\n90,-26.9,17.5\n"
                    "180,52.4,-32.2\n270,-26.8,17.4\n")
    before = {p: p.read_bytes() for p in (rec, cal, grad)}
    other = str(tmp_path / "other.json")
    cases = [
        (["calibrate", "static", str(rec), "--g", "9.81", "-o", str(rec)],
         f"-o {rec} would overwrite the recording {rec}"),
        (["calibrate", "static", str(rec), "--g", "9.81", "--dwells-out", str(rec)],
         f"--dwells-out {rec} would overwrite the recording"),
        (["calibrate", "static", str(rec), "--g", "9.81", "--plot", str(rec)],
         "--plot"),
        (["calibrate", "static", str(rec), "--g", "9.81", "-o", other, "--dwells-out", other],
         f"-o and --dwells-out name the same file ({other})"),
        (["dwells", str(rec), "-o", str(rec)], "would overwrite the recording"),
        (["apply", str(cal), str(rec), "-o", str(rec)], "would overwrite the recording"),
        (["apply", str(cal), str(rec), "-o", str(cal)],
         f"-o {cal} would overwrite the calibration file {cal}"),
        (["diagnose", str(rec), "--g", "9.81", "--calibration", str(cal), "--plot", str(cal)],
         "would overwrite the calibration file"),
        (["calibrate", "gradiometer", str(grad), "-o", str(grad)],
         f"-o {grad} would overwrite the table {grad}"),
    ]
    for args, want in cases:
        code, out = run(*args)
        assert code == 2 and want in out and "nothing was written" in out, (args, out)
    assert {p: p.read_bytes() for p in (rec, cal, grad)} == before
    assert not (tmp_path / "other.json").exists()


def test_diagnose_with_a_calibration_takes_its_g_and_refuses_another_unit(
        tmp_path: Path) -> None:
    """`diagnose FILE --calibration cal.json` demanded --g although the file stores the g it
    was made with; and `--g 1` against a calibration in m/s^2 gave "best = k3". Now the
    stored g is used (with a note), and a g in other units is refused in CLI words."""
    from accelcal.sim.field import field_session

    cal = tmp_path / "cal.json"
    recs = []
    for seed in (2, 3):
        s = field_session(fs=200.0, n_dwells=24, dwell_s=4.0, move_s=2.0, max_tilt_deg=80,
                          rng=seed)
        recs.append(write_csv(tmp_path / f"rec{seed}.csv", s.t, s.samples))
    code, out = run("calibrate", "static", str(recs[0]), "--g", str(s.g), "-o", str(cal))
    assert code == 0, out
    code, out = run("diagnose", str(recs[1]), "--calibration", str(cal))
    assert code == 0, out
    assert "g = 9.80665 m/s^2 from the calibration file" in out, out
    assert "common offset" not in out
    code, out = run("diagnose", str(recs[1]), "--calibration", str(cal), "--g", "1")
    assert code == 2 and "the calibration was made with g = 9.80665" in out, out
    assert "--no-check-g" in out and "check_g=False" not in out, out


def test_several_dwells_at_one_pose_are_said_to_be_one_pose(tmp_path: Path) -> None:
    """A helper's real one-pose file read with a long window gave 3 dwells and "Add
    attitudes", without saying that the 3 are one attitude (the one-file-per-pose hint came
    only when detection merged them into one). Now it counts the poses, not the dwells."""
    rng = np.random.default_rng(2)
    t = np.arange(3000) / 100.0
    x = np.array([0.4, -0.1, 9.3]) + 0.01 * rng.standard_normal((3000, 3))
    x[990:1010] += 0.5  # two knocks split one rest into three dwells
    x[1990:2010] -= 0.5
    code, out = run("calibrate", "static", str(write_csv(tmp_path / "one.csv", t, x)),
                    "--g", "9.81")
    assert code == 2 and "3 dwells found" in out, out
    assert "The recording holds 3 dwells at one pose: if the other poses are in other files" \
        in out, out


def test_apply_writes_compressed_text_or_standard_output_and_refuses_unknown_formats(
        tmp_path: Path) -> None:
    """`apply -o x.csv.gz` wrote plain text under a .gz name, `-o -` a file named '-', and an
    unknown suffix silently became CSV. Now .gz/.bz2/.xz text is compressed (and reads back
    as the .csv does), - writes the rows to standard output (the summary to stderr), and an
    unknown format is refused before anything is written."""
    import accelcal
    from accelcal.sim.field import field_session

    s = field_session(fs=100.0, n_dwells=12, dwell_s=3.0, move_s=1.0, max_tilt_deg=80.0,
                      sigma=2e-3, rng=3)
    rec = write_csv(tmp_path / "rec.csv", s.t, s.samples)
    cal = tmp_path / "cal.json"
    assert run("calibrate", "static", str(rec), "--g", str(s.g), "-o", str(cal))[0] == 0
    plain = tmp_path / "out.csv"
    assert run("apply", str(cal), str(rec), "-o", str(plain))[0] == 0
    for suffix in (".csv.gz", ".csv.bz2", ".csv.xz"):
        packed = tmp_path / f"out{suffix}"
        code, out = run("apply", str(cal), str(rec), "-o", str(packed))
        assert code == 0, out
        assert packed.read_bytes()[:2] != b"# "  # compressed, not text
        a, b = accelcal.read_stream(plain), accelcal.read_stream(packed)
        np.testing.assert_array_equal(a.samples, b.samples)
    r = CliRunner().invoke(main, ["apply", str(cal), str(rec), "-o", "-"])
    assert r.exit_code == 0 and r.stdout.startswith("# calibrated by accelcal"), r.output
    assert "to standard output" in r.stderr and not (tmp_path / "-").exists()
    assert r.stdout.count("\n") == plain.read_text().count("\n")
    code, out = run("apply", str(cal), str(rec), "-o", str(tmp_path / "out.foo"))
    assert code == 2 and "unknown output format '.foo'" in out, out
    assert not (tmp_path / "out.foo").exists()


def test_apply_to_dropouts_only_says_nothing_from_numpy(tmp_path: Path) -> None:
    """A recording of NaN rows only (a logger's dropouts): the calibrated-norm check leaked
    numpy's "All-NaN slice encountered" warning to stderr. The rows pass through as NaN."""
    import warnings

    from accelcal.sim.field import field_session

    s = field_session(fs=100.0, n_dwells=12, dwell_s=3.0, move_s=1.0, max_tilt_deg=80.0,
                      sigma=2e-3, rng=3)
    cal = tmp_path / "cal.json"
    rec = write_csv(tmp_path / "rec.csv", s.t, s.samples)
    assert run("calibrate", "static", str(rec), "--g", str(s.g), "-o", str(cal))[0] == 0
    nan = tmp_path / "nan.csv"
    nan.write_text("t,ax,ay,az\n0,nan,nan,nan\n0.01,nan,nan,nan\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        code, out = run("apply", str(cal), str(nan), "-o", str(tmp_path / "o.csv"))
    assert code == 0 and "All-NaN" not in out, out
    assert "nan,nan,nan" in (tmp_path / "o.csv").read_text()


def test_a_file_named_dash_is_not_overwritten_by_dash_output(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`dwells ./- -o -` replaced the input file named '-' (the overwrite check took '-' as
    standard input and output, but these commands write a file of that name)."""
    from accelcal.sim.field import field_session

    s = field_session(fs=100.0, n_dwells=12, dwell_s=3.0, move_s=1.0, max_tilt_deg=80.0,
                      sigma=2e-3, rng=3)
    monkeypatch.chdir(tmp_path)
    rec = write_csv(tmp_path / "-", s.t, s.samples)
    before = rec.read_bytes()
    code, out = run("dwells", "./-", "-o", "-")
    assert code == 2 and "would overwrite the recording" in out, out
    assert rec.read_bytes() == before


def test_a_clock_in_ms_read_in_s_is_not_offered_a_longer_window(tmp_path: Path) -> None:
    """softdream's up.txt (t in ms, no header, 2.4 s at 84.5 Hz) read in s gives 0.084 Hz:
    the error offered "--window 95.07 s or more" beside the right fix (the clock in ms). The
    unit is now the only advice; and no window longer than the whole recording is offered."""
    from test_io import six_faces_ms

    joined = tmp_path / "faces.txt"
    six_faces_ms(joined, np.random.default_rng(3))
    up = tmp_path / "up.txt"
    up.write_text("".join(joined.read_text().splitlines(keepends=True)[:207]))
    code, out = run("calibrate", "static", str(up), "--g", "1")
    assert code == 2 and "the detector needs at least 8 samples per window;" in out, out
    assert "name its unit with --time-column (e.g. '0 [ms]')" in out, out
    assert "else give --window" not in out and " s or more" not in out, out
    # A rate in Hz that is plausible keeps the advice (a 4 Hz logger: test above) unless the
    # window it needs is longer than the recording: 5 rows at 2 Hz span 2.5 s, not 4.
    few = tmp_path / "few.csv"
    write_csv(few, np.arange(5) * 0.5, np.tile([0.0, 0.0, 1.0], (5, 1)))
    code, out = run("dwells", str(few))
    assert code == 2 and "else give --window 4 s or more" not in out, out
    assert "At 2 Hz a window needs 4 s or more, longer than the whole recording" in out, out


def test_apply_says_why_the_time_column_is_not_written(tmp_path: Path) -> None:
    """softdream's six faces joined (t in ms, the clock restarting at each face): apply wrote
    ax,ay,az only, with no word of the time column; now a note says why and how to keep it
    (--time-column '0 [ms]', which writes t_s in s)."""
    from test_io import six_faces_ms

    p = tmp_path / "faces.txt"
    table = six_faces_ms(p, np.random.default_rng(4))
    cal = tmp_path / "cal.json"
    code, out = run("calibrate", "static", str(p), "--g", "1", "--model", "diag", "-o",
                    str(cal))
    assert code == 0, out
    code, out = run("apply", str(cal), str(p), "-o", str(tmp_path / "out.csv"))
    assert code == 0, out
    lines = (tmp_path / "out.csv").read_text().splitlines()
    assert [ln for ln in lines if not ln.startswith("#")][0] == "ax,ay,az"
    steps = np.diff(table[:, 0])
    rate = 1000.0 / np.mean(steps[steps > 0])  # the true rate, Hz, of the clock in ms
    m = re.search(r"note: no time column \(t_s\) written: the sample rate is unknown .*column 0 "
                  r"\(0-based\) looks like a clock \(mean step [\d.]+; it steps back 5 times "
                  r"in the first 1242 rows: joined files\?\): if it is the time in ms "
                  r"\(([\d.]+) Hz\).*name it with --time-column \(e\.g\. '0 \[ms\]'\) to "
                  r"write t_s", out)
    assert m and float(m.group(1)) == pytest.approx(rate, rel=1e-3), out
    # As the note says: with the unit named, t_s is written, in s.
    code, out = run("apply", str(cal), str(p), "-o", str(tmp_path / "t.csv"), "--time-column",
                    "0 [ms]")
    assert code == 0 and "with t_s" in out and "no time column" not in out, out
    rows = [ln for ln in (tmp_path / "t.csv").read_text().splitlines() if ln[:1] != "#"]
    assert rows[0] == "t_s,ax,ay,az"
    got = np.loadtxt(rows[1:], delimiter=",")
    assert got.shape == (1242, 4)
    np.testing.assert_allclose(np.diff(got[:207, 0]), np.diff(table[:207, 0]) / 1000.0,
                               atol=1e-6)
    # A file with no clock at all loses none: nothing to say.
    q = tmp_path / "noclock.csv"
    np.savetxt(q, table[:, 1:], delimiter=",", header="ax,ay,az", comments="", fmt="%.6f")
    code, out = run("apply", str(cal), str(q), "-o", str(tmp_path / "q.csv"))
    assert code == 0 and "wrote 1242 calibrated samples (g) to" in out, out
    assert "time column" not in out and "note:" not in out, out


def test_files_joined_with_their_clocks_restarting_are_read_once_noted(tmp_path: Path) -> None:
    """Six one-pose files joined, each clock from 0 in ms (softdream/imu_calibration's faces):
    the dwell pass warned again what the reader had noted (a raw TimeStepWarning line, an
    "internal error" under warnings-as-errors), and diagnose sorted the dwells by those
    times and called drift testable. Now one note from the reader; diagnose drops the times."""
    rng = np.random.default_rng(4)
    truth_s, truth_b = np.array([1.005, 1.002, 1.01]), np.array([0.03, 0.004, -0.05])
    rows = []
    for face in np.vstack([np.eye(3), -np.eye(3)]):
        y = truth_s * face + truth_b + rng.normal(0, 3e-3, (200, 3))
        t_ms = np.arange(200) * 11.84 + rng.uniform(0, 0.5, 200)
        rows += [f"{t:.0f} {a:.6f} {b:.6f} {c:.6f}\n" for t, (a, b, c) in zip(t_ms, y, strict=True)]
    p = tmp_path / "faces.txt"
    p.write_text("".join(rows))
    cal = tmp_path / "cal.json"
    code, out = run("calibrate", "static", str(p), "--g", "1", "--time-column", "0 [ms]",
                    "--model", "diag", "-o", str(cal))
    assert code == 0, out
    assert "TimeStepWarning" not in out and out.count("steps back 5 time(s)") == 1, out
    code, out = run("diagnose", str(p), "--g", "1", "--time-column", "0 [ms]",
                    "--calibration", str(cal))
    assert code == 0, out
    assert "TimeStepWarning" not in out
    assert "the times are not used, so drift and the time tests are not testable" in out
    assert re.search(r"drift\s+no_time", out), out


def test_clock_stamps_not_understood_name_the_way_round(tmp_path: Path) -> None:
    import datetime as dt

    rng = np.random.default_rng(2)
    a = rng.normal(0, 0.01, (600, 3)) + [0.1, -0.2, 9.8]
    t0 = dt.datetime(2024, 3, 1, 23, 59, 58)
    stamps = [(t0 + dt.timedelta(milliseconds=10 * i)).strftime("%d-%b-%Y %H:%M:%S")
              for i in range(len(a))]
    p = tmp_path / "c.csv"
    p.write_text("time,ax,ay,az\n" + "\n".join(
        s + "," + ",".join(f"{v:.6f}" for v in r) for s, r in zip(stamps, a, strict=True)) + "\n")
    code, out = run("dwells", str(p))
    assert code == 2
    assert ("column 'time' holds time stamps in a format not understood ('01-Mar-2024 "
            "23:59:58', data row 1); give --time-column none --fs RATE") in out, out
    code, out = run("dwells", str(p), "--time-column", "none", "--fs", "100", "--json")
    assert code == 0, out
    d = json.loads(out[out.index("{"):])
    assert d["n_dwells"] == 1 and d["fs_hz"] == 100.0
    lo, hi = d["start"][0], d["stop"][0]
    np.testing.assert_allclose(d["mean"][0], a[lo:hi].mean(axis=0), atol=1e-6)


def test_clock_stamps_across_midnight_give_the_rate(tmp_path: Path) -> None:
    import datetime as dt

    rng = np.random.default_rng(3)
    a = rng.normal(0, 0.01, (600, 3)) + [0.1, -0.2, 9.8]
    t0 = dt.datetime(2024, 3, 1, 23, 59, 58)
    stamps = [(t0 + dt.timedelta(milliseconds=10 * i)) for i in range(len(a))]
    p = tmp_path / "c.csv"
    p.write_text("time,ax,ay,az\n" + "\n".join(
        f"{w:%H:%M:%S}.{w.microsecond // 1000:03d}," + ",".join(f"{v:.6f}" for v in r)
        for w, r in zip(stamps, a, strict=True)) + "\n")
    code, out = run("dwells", str(p))
    assert code == 0, out
    assert "past midnight 1 time(s)" in out and "100 Hz" in out, out


def test_apply_header_names_the_calibration_by_hash_and_the_version(tmp_path: Path) -> None:
    """The header named the calibration only by the path given: a file replaced under that
    name gave an identical header. Now its SHA-256 and the accelcal version too."""
    import hashlib

    import accelcal

    cal, out = tmp_path / "cal.json", tmp_path / "out.csv"
    code, text = run("calibrate", "static", str(XSENS()), "--g", "9.81744", "-o", str(cal))
    assert code == 0, text
    code, text = run("apply", str(cal), str(XSENS()), "-o", str(out), "--quiet")
    assert code == 0, text
    head = [ln for ln in out.read_text().splitlines()[:8] if ln.startswith("#")]
    assert head[:4] == [f"# calibrated by accelcal from {cal}",
                        f"# calibration_sha256: {hashlib.sha256(cal.read_bytes()).hexdigest()}",
                        f"# accelcal_version: {accelcal.__version__}",
                        f"# source: {XSENS()}"]


def test_demo_prints_its_seed(monkeypatch: pytest.MonkeyPatch) -> None:
    from accelcal.demo import DemoResult

    monkeypatch.setattr("accelcal.demo.demo_result", lambda **kw: DemoResult(
        {"field": "F"}, None, 0, _FakeGap(), None, seed=kw["seed"]))
    code, out = run("demo", "--quick", "--no-figures", "--seed", "7")
    assert code == 0, out
    assert out == "seed 7 (accelcal demo --seed N simulates other sessions)\n\nF\n"
    code, out = run("demo", "--quick", "--no-figures", "--seed", "7", "--json")
    assert code == 0, out
    assert json.loads(out)["seed"] == 7


class _FakeGap:
    def to_dict(self) -> dict[str, Any]:
        return {}


def test_demo_table1_lookup_does_not_depend_on_the_current_folder(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The paper's Table 1 was also looked for in cwd/../shared/data: the demo printed
    differently by folder. Now ACCELCAL_SHARED_DATA, else the source tree's folder only, and
    a miss says where it looked and how to point to it."""
    import accelcal.demo.centrifuge as c

    table = shared_data("seed004", "table1_as_printed.csv")
    here = tmp_path / "work" / "here"
    beside = tmp_path / "work" / "shared" / "data" / "seed004"  # cwd/../shared/data/seed004
    for folder in (here, beside):
        folder.mkdir(parents=True)
    for f in table.parent.glob("table1_*.csv"):
        (beside / f.name).write_bytes(f.read_bytes())
    monkeypatch.chdir(here)
    monkeypatch.setenv(c.SHARED_DATA_ENV, str(tmp_path / "nowhere"))
    found, looked = c._table1_dir()
    assert looked[:2] == [tmp_path / "nowhere" / "seed004", tmp_path / "nowhere"]
    assert all(tmp_path / "work" not in p.parents for p in looked), looked
    assert found != beside
    monkeypatch.setenv(c.SHARED_DATA_ENV, str(tmp_path / "work" / "shared" / "data"))
    assert c._table1_dir()[0] == beside
    assert "Wang and Li (2021) Table 1 (sign-corrected)" in c.demo_section(0)
    # Nothing found: the line says where it looked and names the variable.
    monkeypatch.setattr(c, "_seed_dirs", lambda: [tmp_path / "nowhere"])
    last = c.demo_section(0).splitlines()[-1]
    assert last == (f"(the paper's Table 1 was not found (not in {tmp_path / 'nowhere'}): "
                    "skipping the reproduction lines; set ACCELCAL_SHARED_DATA to the shared "
                    "data folder that holds seed004/table1_as_printed.csv to include them)")
    monkeypatch.setattr(c, "_seed_dirs", lambda: [])
    assert "(ACCELCAL_SHARED_DATA is not set)" in c.demo_section(0).splitlines()[-1]


def _cli_subprocess(args: list[str], pre: str = "", timeout: float = 120,
                    **kw: Any) -> Any:
    """The CLI in a fresh interpreter (``pre`` run first: limits, patches)."""
    import subprocess
    import sys

    code = f"import sys\n{pre}\nfrom accelcal.cli import main\nmain(sys.argv[1:])\n"
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True,
                          timeout=timeout, **kw)


def test_apply_reads_a_calibration_from_a_pipe_once(tmp_path: Path) -> None:
    """A FIFO as the calibration hung (read a second time for its hash); a drained pipe
    recorded the hash of zero bytes."""
    import hashlib
    import os
    import threading

    cal = _calibration(tmp_path)
    data = cal.read_bytes()
    fifo = tmp_path / "cal.fifo"
    os.mkfifo(fifo)

    def feed() -> None:
        with open(fifo, "wb") as fh:  # once: a second reader would wait for ever
            fh.write(data)

    writer = threading.Thread(target=feed, daemon=True)
    writer.start()
    out = tmp_path / "out.csv"
    try:
        r = _cli_subprocess(["apply", str(fifo), str(XSENS()), "-o", str(out), "--quiet"],
                            timeout=60)
    finally:
        if writer.is_alive():  # release a reader that never came
            with open(fifo, "rb") as fh:
                fh.read()
    assert r.returncode == 0, r.stderr
    head = out.read_text().splitlines()[:3]
    assert f"# calibration_sha256: {hashlib.sha256(data).hexdigest()}" in head
    assert hashlib.sha256(b"").hexdigest() not in out.read_text()[:2000]


def test_apply_npz_temporaries_are_named_and_cleaned_as_the_output(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The per-array temporaries of a .npz were .out.npz.samples.*.tmp, which nothing
    cleaned after a kill -9: now named as the output's own temporary file, and a stale one
    removed by the next write."""
    import os
    import subprocess
    import sys

    from accelcal._files import TMP_PREFIX
    from accelcal.cli import stream

    cal = _calibration(tmp_path)
    dead = int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                              capture_output=True, text=True, check=True).stdout)
    stale = tmp_path / f"{TMP_PREFIX}out.npz-{dead}-abcd1234.samples.npy"
    stale.write_bytes(b"x" * 1000)
    seen: list[list[str]] = []
    orig = stream._NpyWriter.write

    def spy(self: Any, block: Any) -> None:
        seen.append(sorted(n for n in os.listdir(tmp_path) if n.startswith(".")))
        orig(self, block)

    monkeypatch.setattr(stream._NpyWriter, "write", spy)
    out = tmp_path / "out.npz"
    code, text = run("apply", str(cal), str(XSENS()), "-o", str(out), "--quiet")
    assert code == 0, text
    assert seen and len(seen[0]) == 3, seen  # the zip's, samples', t's
    assert all(n.startswith(f"{TMP_PREFIX}out.npz-") for n in seen[0]), seen
    assert not stale.exists()
    assert [n for n in os.listdir(tmp_path) if n.startswith(".")] == []


def test_apply_h5_write_error_is_one_line_naming_the_output(tmp_path: Path) -> None:
    """A write error (here a file size limit) while writing HDF5 through a Python file object
    crashed the process (segmentation fault): now one line naming the output, exit 2, and
    no temporary file left."""
    pytest.importorskip("h5py")
    cal = _calibration(tmp_path)
    out = tmp_path / "out.h5"
    pre = ("import resource, signal\n"
           "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
           "resource.setrlimit(resource.RLIMIT_FSIZE, (300_000, 300_000))\n")
    r = _cli_subprocess(["apply", str(cal), str(XSENS()), "-o", str(out), "--quiet"], pre,
                        text=True)
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert "Traceback" not in r.stderr
    assert str(out) in r.stderr and "File too large" in r.stderr, r.stderr
    assert ".accelcal-tmp" not in r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.json"]


def test_apply_to_dev_stdout_writes_as_dash_does(tmp_path: Path) -> None:
    """-o /dev/stdout was refused as a symbolic link although the docs promise /dev/stdout is
    written through: the rows on stdout, the summary on stderr, as with -o -."""
    cal = _calibration(tmp_path)
    r = _cli_subprocess(["apply", str(cal), str(XSENS()), "-o", "/dev/stdout", "--quiet"],
                        text=True)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].startswith("# calibrated by accelcal") and len(lines) > 51175
    assert "wrote 51175 calibrated samples" in r.stderr
    assert "wrote" not in r.stdout
    code, text = run("apply", str(cal), str(XSENS()), "-o", "/dev/stdout", "--json")
    assert code == 2 and "--json" in text


def test_calibrate_static_writes_through_dev_stdout(tmp_path: Path) -> None:
    r = _cli_subprocess(["calibrate", "static", str(XSENS()), "--g", "9.81744", "-o",
                         "/dev/stdout", "--overwrite", "--quiet"], text=True)
    assert r.returncode == 0, r.stderr
    assert '"format": "accelcal.TriadModel"' in r.stdout


def test_out_of_memory_is_a_clear_error_not_an_internal_one(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A MemoryError was reported as an internal error to report (exit 3)."""
    from accelcal.cli import stream

    def short(*a: Any, **k: Any) -> Any:
        raise MemoryError("Unable to allocate 11.4 MiB for an array with shape (500000, 3)")

    monkeypatch.setattr(stream, "open_recording", short)
    cal = _calibration(tmp_path)
    code, text = run("apply", str(cal), str(XSENS()), "-o", str(tmp_path / "o.csv"))
    assert code == 2, text
    assert "out of memory" in text and "11.4 MiB" in text and "--chunk-rows" in text
    assert "internal error" not in text
