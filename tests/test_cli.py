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
from conftest import shared_data

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
    assert pngs == ["field_norm.png", "gap_drift.png", "planned_poses.png"]


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
    a = np.load(calibrated)
    assert a.shape == (51175, 3)
    norm = np.linalg.norm(a[:4000], axis=1)  # the initial 40 s of rest
    assert abs(np.mean(norm) - 9.81744) < 5e-3
    # CSV output carries time and the same numbers.
    csv = tmp_path / "cal.csv"
    code, _ = run("apply", str(cal), str(XSENS()), "-o", str(csv), "--quiet")
    assert code == 0
    tab = np.loadtxt(csv, delimiter=",", skiprows=2)
    np.testing.assert_allclose(tab[:, 1:], a, rtol=1e-8, atol=1e-8)


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
