"""``accelcal calibrate static`` and ``accelcal plan``: messages in the terms of the command
line, one warning, units in every summary line, the stored uncertainty is the printed one, and
their figures (rendered with Agg, axes checked)."""

from __future__ import annotations

import json
import re
from functools import partial
from pathlib import Path

import accelcal as ac
import matplotlib
import numpy as np
import pytest
from accelcal import plots
from accelcal.cli import main
from click.testing import CliRunner
from conftest import shared_data

matplotlib.use("Agg")

XSENS = partial(shared_data, "xsens-mti", "xsens_acc.txt")
MPU = partial(shared_data, "mpu6050-10poses", "example_data_calibration.csv")
IMUCAL = partial(shared_data, "imucal", "example_ferraris_session.csv")


def run(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(main, list(args))
    assert "Traceback" not in r.output
    return r.exit_code, r.output


def test_saved_calibration_holds_the_printed_uncertainty(tmp_path: Path) -> None:
    cal = tmp_path / "cal.json"
    code, out = run("calibrate", "static", str(XSENS()), "--g", "9.81744", "-o", str(cal))
    assert code == 0, out
    printed = {m.group(1): float(m.group(3)) for m in
               re.finditer(r"^\s+(s[xyz]|b[xyz]|m[123])\s+(\S+)\s+(\S+)\s*$", out, re.M)}
    d = json.loads(cal.read_text())
    assert d["covariance_realistic"] == "scaled" and "std stored and printed: scaled" in out
    std = np.sqrt(np.diag(d["covariance"]))
    for i, name in enumerate(d["parameter_names"]):
        assert printed[name] == pytest.approx(std[i], rel=5e-3)  # printed to 3 digits
    np.testing.assert_allclose(d["covariance"], d["covariance_scaled"])
    assert not np.allclose(d["covariance_noise_model"], d["covariance_scaled"])
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", d["date"])
    # The same date format from Python.
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ",
                        ac.TriadModel(np.eye(3), [0, 0, 0]).date)


def test_summary_says_units_on_every_norm_line() -> None:
    code, out = run("calibrate", "static", str(XSENS()), "--g", "9.81744")
    assert code == 0, out
    lines = [ln for ln in out.splitlines() if ln.strip().startswith("norm")]
    assert len(lines) == 2
    for ln in lines:
        # mean, std and RMS in g, RMS also in m/s^2: every number has its unit.
        assert re.search(r"mean \|a\| = [\d.]+ g, std\(\|a\| - g\) = \S+ g, "
                         r"RMS\(\|a\| - g\) = \S+ g = \S+ m/s\^2$", ln), ln


def test_messages_name_cli_options() -> None:
    code, out = run("calibrate", "static", str(XSENS()), "--g", "5")
    assert code == 2 and "--no-check-g" in out and "check_g" not in out
    code, out = run("calibrate", "static", str(XSENS()), "--g", "5", "--no-check-g")
    assert code == 0, out
    code, out = run("calibrate", "static", str(IMUCAL()), "--fs", "102.4", "--g", "9.81")
    assert code == 2 and "--model diag" in out and 'model="diag"' not in out
    assert 'model "diag"' not in out
    code, out = run("plan", "--n", "5")
    assert code == 2 and out.startswith("accelcal: error: --n 5")
    code, out = run("plan", "--n", "12", "--max-tilt", "120")
    assert code == 2 and "--max-tilt" in out and "180" in out


def test_weak_design_warning_is_printed_once() -> None:
    code, out = run("calibrate", "static", str(MPU()), "--g", "9.81")
    assert code == 0, out
    assert out.count("m1 +-") == 1 and "--model diag" in out
    assert "warning:" not in out  # the summary's WEAK line says it


def test_plan_numbers_the_poses_and_prints_a_checklist(tmp_path: Path) -> None:
    png = tmp_path / "plan.png"
    code, out = run("plan", "--n", "12", "--max-tilt", "30", "--plot", str(png))
    assert code == 0, out
    steps = re.findall(r"^\[ \]\s+(\d+)\. (bottom down.*?)\s+\(platform tilt", out, re.M)
    assert [int(s[0]) for s in steps] == list(range(1, 13))
    assert all("deg" in s[1] or "level" in s[1] for s in steps)
    assert png.stat().st_size > 10_000
    code, out = run("plan", "--n", "12", "--max-tilt", "30", "--json")
    p = json.loads(out)
    assert len(p["poses"]) == 12 and p["poses"][0].startswith("bottom down")


def test_static_norm_figure_axes() -> None:
    raw = np.loadtxt(XSENS())[:, 1:4]
    fit = ac.fit_static(ac.detect_dwells(raw, fs=100), 9.81744)
    fig = plots.static_norm_figure(fit)
    top, bottom = fig.axes
    assert top.get_ylabel() == "|a| / g  [g]"
    assert bottom.get_ylabel() == "|a| - g  [mm/s^2]"
    assert bottom.get_xlabel() == "dwell (numbered from 0, as in the tables)"
    # The largest residual sits at the dwell number the reports give it.
    heights = np.array([b.get_height() for b in bottom.patches])
    xs = np.array([b.get_x() + b.get_width() / 2 for b in bottom.patches])
    assert xs[np.argmax(np.abs(heights))] == np.argmax(np.abs(fit.residuals))
    assert "before (fitted bias removed, one common scale)" in [
        t.get_text() for t in top.get_legend().get_texts()]
    # Counts are shown in g: the 'before' norms are near 1 g, not near 57000 counts.
    before = top.get_lines()[0].get_ydata()
    assert np.all(np.abs(before - 1) < 0.05)
    ticks = bottom.get_xticks()
    assert np.allclose(ticks, np.round(ticks))
    # Error bars are the noise model's std of each residual.
    bars = [c for c in bottom.collections if c.__class__.__name__ == "LineCollection"]
    seg = bars[0].get_segments()
    half = np.array([abs(s[1][1] - s[0][1]) / 2 for s in seg])
    np.testing.assert_allclose(half, 1e3 * fit.sigma_residual, rtol=1e-9)


def test_poses_figure_axes() -> None:
    plan = ac.plan_poses(14, None, rng=1)
    fig = plots.poses_figure(plan)
    assert len(fig.axes) == 2  # top up and top down: the full sphere
    labels = [t.get_text() for ax in fig.axes for t in ax.texts]
    assert sorted(int(t) for t in labels if t.isdigit()) == list(range(1, 15))
    for ax in fig.axes:
        assert "equal-area" in ax.get_xlabel() and "nose" in ax.get_xlabel()
        assert "left side" in ax.get_ylabel()
    one = plots.poses_figure(ac.plan_poses(12, 30, rng=1))
    assert len(one.axes) == 1


def test_gravity_from_latitude_is_not_refused_and_an_impossible_g_is(tmp_path: Path) -> None:
    from accelcal.sim.field import field_session

    g20 = ac.local_gravity(0.0, 20_000.0)  # 9.719 m/s^2, a balloon's: below the --g range
    s = field_session(fs=100.0, n_dwells=14, dwell_s=10.0, move_s=3.0, max_tilt_deg=80,
                      g=g20, sigma=2e-3, rng=3)
    p = tmp_path / "balloon.csv"
    np.savetxt(p, np.column_stack([s.t, s.samples]), delimiter=",", header="t,ax,ay,az",
               comments="")
    for cmd in ("calibrate static", "diagnose"):
        code, out = run(*cmd.split(), str(p), "--lat", "0", "--height", "20000")
        assert code == 0, out
    code, out = run("calibrate", "static", str(p), "--g", "9.8895")
    assert code != 0 and "not a plausible local gravity" in out and "--no-check-g" in out, out
    code, out = run("calibrate", "static", str(p), "--g", "9.8895", "--no-check-g")
    assert code == 0, out


def test_outputs_are_announced_and_apply_needs_no_rate(tmp_path: Path) -> None:
    from accelcal.sim.static import static_dwell_means

    s = static_dwell_means(30, max_tilt_deg=None, sigma=1e-4, g=1.0, rng=4)
    table = tmp_path / "means.txt"
    np.savetxt(table, s.means, fmt="%.6f")  # pose means in g: no rate, no header
    cal, dw = tmp_path / "cal.json", tmp_path / "dwells.csv"
    code, out = run("calibrate", "static", str(table), "--g", "1", "--means", "-o", str(cal),
                    "--dwells-out", str(dw))
    assert code == 0, out
    assert f"wrote {dw} (the dwell table: 30 dwells" in out and dw.is_file()
    code, out = run("apply", str(cal), str(table), "-o", str(tmp_path / "applied.csv"))
    assert code == 0 and "wrote 30 calibrated samples" in out, out
    assert "sample rate" not in out  # applying a calibration needs none
    # And the StaticFit's repr does not show the unit-weight chi2/dof as if it were a test.
    f = ac.fit_static(s.means, 1.0)
    assert "noise estimated" in repr(f) and "chi2_dof" not in repr(f)
    assert "chi2_dof=" in repr(ac.fit_static(s.means, 1.0, sigma=1e-4))


def test_one_file_per_face_with_a_units_trap(tmp_path: Path) -> None:
    """A real MPU-6050 lab: six files, one per face, headed 'aX (g)' but holding m/s^2
    (the sketch prints counts * 9.81 / 16384), a 'Timestamp' in ms. A face alone got "Add
    attitudes" and no word of joining the files; the units passed without a word; the rate
    read in s (0.063 Hz) came with no note from read_stream; and pose labels 'imu_data_posZ'
    made a table of the six means a 'long-format log' even with --means."""
    from accelcal.sim.field import field_session

    s = field_session(fs=62.5, n_dwells=6, dwell_s=5.0, move_s=1.0, max_tilt_deg=80.0,
                      sigma=0.02, rng=5)
    a, b = s.bounds[0]
    face = tmp_path / "x_axis_pos.csv"
    rows = "".join(f"{round(16 * i)},{x:.2f},{y:.2f},{z:.2f},26.1\n"
                   for i, (x, y, z) in enumerate(s.samples[a:b]))
    face.write_text("Timestamp,aX (g),aY (g),aZ (g),Temp (C)\n" + rows)
    st = ac.read_stream(face)
    assert st.fs < 1 and any("if it is in ms" in n and "no dwell can be detected" in n
                             for n in st.notes), st.notes
    code, out = run("calibrate", "static", str(face), "--g", "9.81", "--time-column",
                    "Timestamp [ms]")
    assert code == 2 and "The recording holds one pose: if the other poses are in " \
        "other files (one file per pose), join them" in out, out
    assert "the accelerometer columns say g (aX (g), aY (g), aZ (g)), but the dwell means' " \
        "norms are about 1" in out and "the outputs look like m/s^2" in out, out
    # A table of the face means, labelled as the lab labelled them.
    table = tmp_path / "means.csv"
    means = [s.samples[p:q].mean(axis=0) for p, q in s.bounds]
    table.write_text("pose,ax,ay,az\n" + "".join(
        f"imu_data_{k},{x},{y},{z}\n" for k, (x, y, z) in zip(
            ["posX", "negX", "posY", "negY", "posZ", "negZ"], means, strict=True)))
    code, out = run("calibrate", "static", str(table), "--g", "9.81", "--means", "--model",
                    "diag")
    assert "long-format" not in out and "kept as the rows' names" in out, out


def test_apply_says_when_the_calibration_does_not_fit_the_recording(tmp_path: Path) -> None:
    """The Xsens calibration (raw counts) applied to an MPU-9150 recording in m/s^2 wrote
    calibrated norms of 136 m/s^2 without a word."""
    from accelcal.sim.field import field_session

    s = field_session(fs=100.0, n_dwells=12, dwell_s=4.0, move_s=1.0, max_tilt_deg=80.0,
                      sigma=1e-3, rng=9)
    rec = tmp_path / "rec.csv"
    np.savetxt(rec, np.column_stack([s.t, s.samples]), delimiter=",", header="t,ax,ay,az",
               comments="")
    other = tmp_path / "other.csv"
    np.savetxt(other, np.column_stack([s.t, s.samples * 14.0]), delimiter=",",
               header="t,ax,ay,az", comments="")
    cal = tmp_path / "cal.json"
    assert run("calibrate", "static", str(rec), "--g", str(s.g), "-o", str(cal))[0] == 0
    code, out = run("apply", str(cal), str(rec), "-o", str(tmp_path / "a.csv"))
    assert code == 0 and "is this the sensor" not in out, out
    code, out = run("apply", str(cal), str(other), "-o", str(tmp_path / "b.csv"))
    assert code == 0 and "the calibrated output's norm is typically 1" in out \
        and "is this the sensor, and are these the units" in out, out


def test_calibrate_static_takes_the_reference_gravitys_std(tmp_path: Path) -> None:
    """--sigma-g adds the reference gravity's uncertainty to every std the command reports
    (the scale factors' std grows by the relative sigma_g), and a value in other units than
    --g is refused naming the option."""
    from accelcal.sim.static import static_dwell_means

    s = static_dwell_means(24, max_tilt_deg=None, sigma=1e-6, sigma_g=0.0, rng=5)
    p = tmp_path / "means.csv"
    p.write_text("ax,ay,az\n" + "\n".join(",".join(f"{v:.12g}" for v in r) for r in s.means))
    args = ["calibrate", "static", str(p), "--means", "--g", "9.80665", "--json"]
    base = json.loads(CliRunner().invoke(main, args).output)
    withg = json.loads(CliRunner().invoke(main, [*args, "--sigma-g", "1e-3"]).output)
    sx, sx_g = base["std"][0], withg["std"][0]
    assert sx_g > 10 * sx and abs(sx_g - base["vector"][0] * 1e-3 / 9.80665) < 0.2 * sx_g
    r = CliRunner().invoke(main, [*args, "--sigma-g", "1"])
    assert r.exit_code == 2 and "--sigma-g = 1 is more than 1 % of g" in r.output


def test_plan_writes_the_poses_as_csv_for_a_tilt_table(tmp_path: Path) -> None:
    """`accelcal plan` printed a checklist only: a test engineer wants a file the tilt table
    (or the checklist) reads. -o writes one row per pose: tilts in deg, the gravity direction
    in the sensor frame, the placement in words; the numbers are the plan's."""
    import csv

    out = tmp_path / "plan.csv"
    r = CliRunner().invoke(main, ["plan", "--n", "12", "--max-tilt", "30", "-o", str(out)])
    assert r.exit_code == 0 and f"wrote {out}" in r.output
    rows = list(csv.DictReader(out.read_text().splitlines()))
    plan = ac.plan_poses(12, 30.0)
    assert [int(x["pose"]) for x in rows] == list(range(1, 13))
    tilts = np.array([[float(x["tilt_x_deg"]), float(x["tilt_y_deg"])] for x in rows])
    dirs = np.array([[float(x[k]) for k in ("gx", "gy", "gz")] for x in rows])
    assert plan.tilts_deg is not None
    np.testing.assert_allclose(tilts, plan.tilts_deg, atol=1e-5)
    np.testing.assert_allclose(dirs, plan.directions, atol=1e-8)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-8)
    assert rows[0]["placement"] == plan.pose_names()[0]


def test_summary_gives_the_student_t_interval_when_the_noise_is_estimated() -> None:
    """With the noise estimated from few degrees of freedom the std is a t statistic (+-2
    std covered 84 % at 3 dof): the summary now says what a 95 % interval is."""
    from accelcal.sim.static import static_dwell_means

    s = static_dwell_means(12, max_tilt_deg=None, sigma=1e-4, rng=1)
    text = ac.fit_static(s.means, s.g_measured).summary()
    assert "estimated from 3 degrees of freedom: a 95 % interval is +-3.18 std" in text
    s = static_dwell_means(60, max_tilt_deg=None, sigma=1e-4, rng=1)
    assert "Student t" not in ac.fit_static(s.means, s.g_measured).summary()


def _recording(tmp_path: Path, name: str = "rec.csv", rng: int = 9) -> Path:
    from accelcal.sim.field import field_session

    s = field_session(fs=100.0, n_dwells=16, dwell_s=4.0, move_s=1.0, max_tilt_deg=85.0,
                      sigma=1e-3, rng=rng)
    rec = tmp_path / name
    np.savetxt(rec, np.column_stack([s.t, s.samples]), delimiter=",", header="t,ax,ay,az",
               comments="")
    return rec


def test_lat_calibration_carries_the_formulas_uncertainty_and_says_where_g_came_from(
        tmp_path: Path) -> None:
    """`--lat 45.5 --height 120` stored no g source and no sigma_g, and the scale factors' std
    (4e-6..2e-5 relative) ignored the formula's own 1e-3 m/s^2 (1e-4 relative) error. Now the
    formula's uncertainty is sigma_g unless --sigma-g is given, the output says so, and the
    file records g_source and sigma_g (0 included)."""
    rec = _recording(tmp_path)
    cal = tmp_path / "lat.json"
    code, out = run("calibrate", "static", str(rec), "--lat", "45.5", "--height", "120",
                    "-o", str(cal), "--quiet")
    assert code == 0, out
    assert "sigma_g = 0.001 m/s^2: the latitude formula's typical error" in out, out
    d = json.loads(cal.read_text())
    md = d["metadata"]
    assert md["g_source"].startswith("latitude formula") and "45.5 deg, 120 m" in md["g_source"]
    assert md["sigma_g"] == 1e-3 and "latitude formula" in md["sigma_g_source"]
    rel = np.sqrt(np.diag(d["covariance"]))[:3] / np.array(d["vector"][:3])
    assert np.all(rel > 1e-4 / 1.01) and np.all(rel < 2e-4), rel
    # A given --sigma-g is kept; --g records "given" and sigma_g 0.
    code, out = run("calibrate", "static", str(rec), "--lat", "45.5", "--height", "120",
                    "--sigma-g", "2e-5", "--json")
    assert code == 0 and json.loads(out)["sigma_g"] == 2e-5, out
    cal_g = tmp_path / "g.json"
    assert run("calibrate", "static", str(rec), "--g", "9.81", "-o", str(cal_g))[0] == 0
    md = json.loads(cal_g.read_text())["metadata"]
    assert md["g_source"] == "given" and md["sigma_g"] == 0.0


def test_calibration_file_is_traceable(tmp_path: Path) -> None:
    """What an auditor asks of a calibration record: the accelcal version, the input's
    SHA-256 and absolute path, the detector settings, model and method, the command line, and
    the recording's date (--date), which TriadModel.find uses as the start of validity."""
    import hashlib

    rec = _recording(tmp_path)
    cal = tmp_path / "cals" / "cal.json"
    cal.parent.mkdir()
    code, out = run("calibrate", "static", str(rec), "--g", "9.81", "--window", "0.8",
                    "--sensor-id", "U1", "--date", "2026-11-20T08:30:00+01:00", "-o", str(cal),
                    "--quiet")
    assert code == 0, out
    d = json.loads(cal.read_text())
    md = d["metadata"]
    assert md["accelcal_version"] == ac.__version__
    assert md["input"] == {"path": str(rec.resolve()), "bytes": rec.stat().st_size,
                           "sha256": hashlib.sha256(rec.read_bytes()).hexdigest()}
    assert md["detector"] == {"window_s": 0.8, "k": 6.0, "min_dwell_s": 1.0, "trim_s": 0.1}
    assert md["model"] == d["model"] == "lower" and md["method"] == "lm"
    assert md["dwells_from"] == "detected"
    assert md["command"].startswith("accelcal calibrate static ") and "--window 0.8" in md[
        "command"] and "--date 2026-11-20T08:30:00+01:00" in md["command"]
    assert d["date"] == "2026-11-20T07:30:00Z"
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", md["written"])
    assert ac.TriadModel.find(cal.parent, "U1", at="2026-11-21").date == d["date"]
    with pytest.raises(ac.CalibrationError, match="no calibration of sensor"):
        ac.TriadModel.find(cal.parent, "U1", at="2026-11-20T07:00:00Z")
    for bad, want in (("yesterday", "--date: it must be an ISO 8601"),
                      ("2999-01-01", "--date 2999-01-01 is in the future")):
        code, out = run("calibrate", "static", str(rec), "--g", "9.81", "--date", bad,
                        "-o", str(tmp_path / "x.json"))
        assert code == 2 and want in out and not (tmp_path / "x.json").exists(), out


def test_o_refuses_to_replace_a_calibration_unless_told(tmp_path: Path) -> None:
    """`-o cal.json` replaced an existing calibration record without a word, even one made
    from another recording. Now it is refused (one line naming the file and --overwrite,
    before anything is read; the file keeps its bytes) unless --overwrite is given."""
    rec, other = _recording(tmp_path), _recording(tmp_path, "other.csv", rng=10)
    cal = tmp_path / "cal.json"
    assert run("calibrate", "static", str(rec), "--g", "9.81", "-o", str(cal))[0] == 0
    before = cal.read_bytes()
    r = CliRunner().invoke(main, ["calibrate", "static", str(other), "--g", "9.81", "-o",
                                  str(cal), "--json"])
    assert r.exit_code == 2 and cal.read_bytes() == before
    line = r.stderr.strip() if hasattr(r, "stderr") and r.stderr else r.output.splitlines()[0]
    assert line == (f"accelcal: error: -o {cal}: the file exists (a calibration is never "
                    "replaced silently); give --overwrite to replace it, or choose another "
                    "path; nothing was written"), line
    assert json.loads(r.output.splitlines()[-1])["exit_code"] == 2
    code, out = run("calibrate", "static", str(other), "--g", "9.81", "-o", str(cal),
                    "--overwrite")
    assert code == 0, out
    assert json.loads(cal.read_text())["metadata"]["input"]["path"] == str(other.resolve())
    assert not list(tmp_path.glob("*.tmp*")) and not list(tmp_path.glob(".*"))


def test_compare_command_prints_the_summary_and_json(tmp_path: Path) -> None:
    rec, other = _recording(tmp_path), _recording(tmp_path, "other.csv", rng=10)
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    for f, c, date in ((rec, a, "2026-11-01"), (other, b, "2026-11-20")):
        assert run("calibrate", "static", str(f), "--lat", "45.5", "--sensor-id", "U1",
                   "--date", date, "-o", str(c))[0] == 0
    code, out = run("compare", str(a), str(b))
    assert code == 0, out
    assert out.startswith("calibrations compared: U1 2026-11-01T00:00:00Z -> U1 "
                          "2026-11-20T00:00:00Z") and "Wald test" in out and "moved beyond" in out
    assert "drops out of the difference" in out
    code, out = run("compare", str(a), str(b), "--json")
    d = json.loads(out)
    assert code == 0 and d["dof"] == 9 and d["shared_g"] and len(d["difference"]) == 9
    assert 0 <= d["p_value"] <= 1 and d["old_file"] == str(a)
    c = tmp_path / "c.json"
    assert run("calibrate", "static", str(other), "--g", "9.81", "--sensor-id", "U2",
               "-o", str(c))[0] == 0
    code, out = run("compare", str(a), str(c))
    assert code == 2 and "different sensor ids ('U1' and 'U2')" in out \
        and "--no-check-sensor" in out and "check_sensor=False" not in out, out
    code, out = run("compare", str(a), str(c), "--no-check-sensor", "--independent-g")
    assert code == 0 and "drops out" not in out, out


def _mg_recording(tmp_path: Path, name: str, header: str, rng: int = 9) -> Path:
    """A simulated session written in mg with the header ``header``."""
    from accelcal.sim.field import field_session

    s = field_session(fs=100.0, n_dwells=16, dwell_s=4.0, move_s=1.0, max_tilt_deg=85.0,
                      sigma=1e-3, rng=rng)
    rec = tmp_path / name
    np.savetxt(rec, np.column_stack([s.t, s.samples * 1000.0 / 9.80665]), delimiter=",",
               header=header, comments="")
    return rec


def test_calibration_records_the_input_unit_the_header_declares(tmp_path: Path) -> None:
    """'ax [mg]' in the header was read (a note used it) but the calibration file said
    units.input "": its K and bias in mg were unlabelled, and a model labelled by the Python
    API (input_units="mg") could not be compared with it. Now recorded; --input-units sets it
    where the header says nothing and is refused, naming both, where it disagrees."""
    rec = _mg_recording(tmp_path, "rec_mg.csv", "t,ax [mg],ay [mg],az [mg]")
    cal = tmp_path / "cal.json"
    code, out = run("calibrate", "static", str(rec), "--g", "9.80665", "-o", str(cal))
    assert code == 0, out
    d = json.loads(cal.read_text())
    assert d["units"]["input"] == "mg", d["units"]
    m = ac.TriadModel.load(cal)
    # K and bias in mg: the simulator's truth (m/s^2 per m/s^2, m/s^2) times 1000 / 9.80665.
    from accelcal.sim.field import field_session

    truth = field_session(fs=100.0, n_dwells=16, dwell_s=4.0, move_s=1.0, max_tilt_deg=85.0,
                          sigma=1e-3, rng=9).truth
    np.testing.assert_allclose(m.vector[:6], truth[:6] * 1000 / 9.80665, rtol=2e-3, atol=0.5)
    assert "K in mg per m/s^2" in out
    # The same unit given again (another spelling of the case) is accepted.
    code, out = run("calibrate", "static", str(rec), "--g", "9.80665", "--input-units", "MG",
                    "-o", str(tmp_path / "cal2.json"))
    assert code == 0, out
    assert json.loads((tmp_path / "cal2.json").read_text())["units"]["input"] == "mg"
    # A unit that contradicts the header: refused, both named, nothing written.
    bad = tmp_path / "bad.json"
    code, out = run("calibrate", "static", str(rec), "--g", "9.80665", "--input-units", "g",
                    "-o", str(bad))
    assert code != 0 and "--input-units g" in out and "ax [mg]" in out and "say mg" in out, out
    assert not bad.exists()
    # No unit in the header: --input-units labels it; without it, none is claimed.
    plain = _mg_recording(tmp_path, "rec.csv", "t,ax,ay,az")
    for extra, want in ((["--input-units", "mg"], "mg"), ([], "")):
        out_p = tmp_path / f"plain{want}.json"
        code, out = run("calibrate", "static", str(plain), "--g", "9.80665", *extra,
                        "-o", str(out_p))
        assert code == 0, out
        assert json.loads(out_p.read_text())["units"]["input"] == want


def test_fleet_calibrations_record_the_declared_input_unit(tmp_path: Path) -> None:
    """The fleet's calibration files record the unit the columns declare, as one file's
    does; --input-units is one recording's option."""
    recs = [_mg_recording(tmp_path, f"s{i}.csv", "t,ax [mg],ay [mg],az [mg]", rng=20 + i)
            for i in range(2)]
    out_dir = tmp_path / "cals"
    code, out = run("calibrate", "static", *map(str, recs), "--g", "9.80665", "--workers", "1",
                    "--out", str(out_dir))
    assert code == 0, out
    files = sorted(out_dir.glob("*.json"))
    assert len(files) == 2, (out, list(out_dir.iterdir()))
    for f in files:
        assert ac.TriadModel.load(f).input_units == "mg"
    code, out = run("calibrate", "static", *map(str, recs), "--g", "9.80665",
                    "--input-units", "mg", "--out", str(tmp_path / "c2"))
    assert code != 0 and "--input-units takes one recording" in out, out


def test_o_written_by_another_run_meanwhile_is_kept(tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """Two `-o cal.json` runs started together both passed the "file exists" check made at
    the start, and the second replaced the first's calibration. Now the file is linked to its
    name when written, which fails when it appeared meanwhile: kept byte for byte, exit 2."""
    from accelcal.cli import static as cli_static

    rec = _recording(tmp_path)
    cal = tmp_path / "cal.json"
    real = cli_static.stream_dwells

    def meanwhile(*a: object, **k: object) -> object:
        cal.write_text('{"the other run": 1}')  # written while this run reads
        return real(*a, **k)  # type: ignore[arg-type]

    monkeypatch.setattr(cli_static, "stream_dwells", meanwhile)
    code, out = run("calibrate", "static", str(rec), "--g", "9.81", "-o", str(cal))
    assert code == 2 and cal.read_text() == '{"the other run": 1}'
    assert (f"accelcal: error: -o {cal}: the file exists, written while this calibration ran "
            "(by another run?); it was kept (a calibration is never replaced silently): give "
            "--overwrite to replace it, or choose another path; the calibration was not "
            "written") in out, out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.json", "rec.csv"]
    code, out = run("calibrate", "static", str(rec), "--g", "9.81", "-o", str(cal),
                    "--overwrite")
    assert code == 0 and ac.TriadModel.load(cal).metadata["input"]["path"] == str(rec), out


def test_a_plot_that_cannot_be_written_leaves_no_calibration(tmp_path: Path) -> None:
    """`-o c.json --plot unwritable/p.png` wrote c.json, then failed (exit 2): the rerun was
    refused because c.json existed. Now the plot is written first."""
    rec = _recording(tmp_path)
    cal, blocker = tmp_path / "c.json", tmp_path / "afile"
    blocker.write_text("")  # a file, so afile/p.png cannot be made (root or not)
    code, out = run("calibrate", "static", str(rec), "--g", "9.81", "-o", str(cal),
                    "--plot", str(blocker / "p.png"))
    assert code == 2 and "Not a directory" in out and not cal.exists(), out
    code, out = run("calibrate", "static", str(rec), "--g", "9.81", "-o", str(cal),
                    "--plot", str(tmp_path / "p.png"))
    assert code == 0 and cal.is_file() and (tmp_path / "p.png").is_file(), out
