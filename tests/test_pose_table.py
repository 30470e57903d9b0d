"""Tables of dwell means (one pose per row, no sample rate): ``accelcal.io.read_means``, the
command line's ``--means`` and its recognition of such a file when the rate is unknown, and the
samples it must not take for one. Checked against the simulator's truth and against the fit
of the same means given as an array."""

from __future__ import annotations

import json
from pathlib import Path

import accelcal as ac
import numpy as np
import pytest
from accelcal import CalibrationError
from accelcal._pose_table import looks_like_poses
from accelcal.cli import main
from accelcal.io import read_means, stream_dwells
from accelcal.sim.field import field_session
from accelcal.sim.static import static_dwell_means
from click.testing import CliRunner

G = 9.80665
# Raw int16-like counts: 1670 counts per m/s^2, offsets of a few hundred counts.
TRUTH = [1670.0, 1668.0, 1675.0, 120.0, -340.0, 560.0, 3.0, -5.0, 8.0]


def run(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(main, list(args))
    assert "Traceback" not in r.output
    return r.exit_code, r.output


def session(n: int = 24, tilt: float | None = None, seed: int = 5) -> np.ndarray:
    return static_dwell_means(n, TRUTH, G, sigma=0.5, sigma_g=0.0, max_tilt_deg=tilt,
                              rng=seed).means


def test_headerless_table_is_read_as_poses_and_fits_like_the_array(tmp_path: Path) -> None:
    m = session()
    p = tmp_path / "poses.txt"
    np.savetxt(p, m, fmt="%.4f", delimiter=",")
    d = read_means(p)
    assert len(d) == 24 and d.var is None and d.fs is None
    np.testing.assert_allclose(d.mean, np.round(m, 4), rtol=0, atol=1e-9)
    fit = ac.fit_static(d, G, observability="ignore")
    ref = ac.fit_static(np.round(m, 4), G, observability="ignore")
    np.testing.assert_allclose(fit.vector, ref.vector, rtol=1e-12)
    # Within 5 std of the simulator's truth.
    assert np.all(np.abs(fit.vector - TRUTH) < 5 * fit.std + 1e-9)


@pytest.mark.parametrize("tilt", [None, 30.0])
def test_cli_takes_a_file_of_unknown_rate_whose_rows_are_poses(tmp_path: Path,
                                                               tilt: float | None) -> None:
    m = session(20, tilt, seed=7)
    p = tmp_path / "poses.csv"
    np.savetxt(p, m, fmt="%.4f", delimiter=",", header="ax,ay,az", comments="")
    code, out = run("calibrate", "static", str(p), "--g", str(G), "--json")
    assert code == 0, out
    res = json.loads(out[out.index("{"):])
    ref = ac.fit_static(np.round(m, 4), G, observability="ignore")
    np.testing.assert_allclose(res["vector"], ref.vector, rtol=1e-9)
    code, out = run("calibrate", "static", str(p), "--g", str(G))
    assert code == 0, out
    assert "read as a table of dwell means, one pose per row (20 rows" in out
    assert "table of dwell means, 20 poses" in out
    assert "sample rate is not in the file" not in out  # no rate is needed


def test_named_mean_std_and_count_columns_give_each_mean_its_noise(tmp_path: Path) -> None:
    m = session(18, seed=9)
    rng = np.random.default_rng(0)
    std = rng.uniform(2.0, 4.0, size=m.shape)
    n = rng.integers(200, 600, size=len(m))
    truth_dir = np.round(m / np.linalg.norm(m, axis=1)[:, None], 1)
    cols = {"x_true (g)": truth_dir[:, 0], "x_mean": m[:, 0], "x_std": std[:, 0],
            "y_true (g)": truth_dir[:, 1], "y_mean": m[:, 1], "y_std": std[:, 1],
            "z_true (g)": truth_dir[:, 2], "z_mean": m[:, 2], "z_std": std[:, 2], "n": n}
    p = tmp_path / "poses.csv"
    p.write_text(",".join(cols) + "\n" + "\n".join(
        ",".join(repr(float(cols[c][i])) for c in cols) for i in range(len(m))) + "\n")
    d = read_means(p)
    np.testing.assert_array_equal(d.mean, m)  # the mean columns, not the reference ones
    np.testing.assert_allclose(d.var, std**2, rtol=1e-15)
    np.testing.assert_array_equal(d.count, n)
    np.testing.assert_allclose(d.sem, std / np.sqrt(n)[:, None], rtol=1e-14)
    # Without the count the std columns are left out, with a note saying why.
    p2 = tmp_path / "no_count.csv"
    p2.write_text("\n".join(",".join(ln.split(",")[:-1])
                            for ln in p.read_text().splitlines()) + "\n")
    code, out = run("calibrate", "static", str(p2), "--g", str(G))
    assert code == 0, out
    assert "per-pose std columns (x_std, y_std, z_std) are not used" in out
    assert "or --count for all poses" in out
    # A logger that averages a fixed number of samples per pose: count= / --count gives
    # each mean its noise, std / sqrt(count), and the fit then knows the noise.
    d2 = read_means(p2, count=400)
    np.testing.assert_array_equal(d2.count, np.full(len(m), 400))
    np.testing.assert_allclose(d2.sem, std / 20.0, rtol=1e-14)
    ref = ac.fit_static(m, G, sigma=std / 20.0)
    np.testing.assert_allclose(ac.fit_static(d2, G).vector, ref.vector, rtol=1e-12)
    code, out = run("calibrate", "static", str(p2), "--g", str(G), "--count", "400",
                    "--json")
    assert code == 0, out
    res = json.loads(out)
    np.testing.assert_allclose(res["vector"], ref.vector, rtol=1e-10)
    assert any("the 400 samples per pose given by --count" in x for x in res["notes"])
    code, out = run("calibrate", "static", str(p2), "--g", str(G), "--count", "400")
    assert code == 0 and "the 400 samples per pose given by --count: std / sqrt" in out
    # ... but not with the table's own count column, without std columns, or for samples.
    with pytest.raises(CalibrationError, match=r"count= conflicts with the table's own count "
                       r"column 'n'"):
        read_means(p, count=400)
    plain = tmp_path / "plain.csv"
    np.savetxt(plain, m, delimiter=",", header="ax,ay,az", comments="")
    with pytest.raises(CalibrationError, match=r"has no per-pose std columns"):
        read_means(plain, count=10)
    with pytest.raises(CalibrationError, match=r"give means=True too"):
        stream_dwells(plain, fs=100.0, count=10)
    code, out = run("dwells", str(p2), "--count", "0")
    assert code == 2 and "--count" in out


def test_samples_of_unknown_rate_are_not_taken_for_poses(tmp_path: Path) -> None:
    # One pose at rest: rows that differ by the noise only.
    rng = np.random.default_rng(3)
    rest = np.array([120.0, -340.0, 16900.0]) + 3.0 * rng.standard_normal((500, 3))
    p = tmp_path / "rest.csv"
    np.savetxt(p, rest, fmt="%.3f", delimiter=",", header="ax,ay,az", comments="")
    assert not looks_like_poses(rest)
    with pytest.raises(CalibrationError, match=r"sample rate is unknown.*means=True"):
        stream_dwells(p, means=None)
    code, out = run("calibrate", "static", str(p), "--g", str(G))
    assert code != 0 and "give --fs (Hz)" in out and "read it with --means" in out
    # A real session's stream (poses held for seconds, moves between them), decimated to
    # 2000 rows: consecutive rows are mostly the same pose.
    s = field_session(fs=100.0, n_dwells=12, dwell_s=12.0, move_s=3.0, rng=1).samples
    assert not looks_like_poses(s[:2000])
    # Poses in one plane only (turned about one axis): not a calibration table.
    ang = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    planar = G * np.column_stack([np.cos(ang), np.zeros(12), np.sin(ang)])
    assert not looks_like_poses(planar)
    assert looks_like_poses(session(12))


def test_bad_tables_and_conflicting_options_are_refused(tmp_path: Path) -> None:
    m = session(12)
    p = tmp_path / "nan.csv"
    text = "\n".join(",".join(f"{v:.3f}" for v in r) for r in m).splitlines()
    text[4] = "1.0,nan,2.0"
    p.write_text("ax,ay,az\n" + "\n".join(text) + "\n")
    with pytest.raises(CalibrationError, match=r"data row\(s\) 5 \(1-based\) hold NaN"):
        read_means(p)
    good = tmp_path / "good.csv"
    np.savetxt(good, m, fmt="%.3f", delimiter=",")
    bounds = tmp_path / "b.json"
    bounds.write_text("[[0, 3]]")
    code, out = run("calibrate", "static", str(good), "--g", str(G), "--means",
                    "--bounds", str(bounds))
    assert code != 0 and "not both" in out
    code, out = run("dwells", str(good), "--means", "--plot", str(tmp_path / "x.png"))
    assert code != 0 and "--plot draws the stream" in out
    # A table given as one asked for (--means) even with a rate: one dwell per row.
    code, out = run("dwells", str(good), "--means", "--fs", "100")
    assert code == 0, out
    assert "table of dwell means, 12 poses" in out and "as asked" in out


def test_a_fleet_of_pose_tables_is_calibrated_as_the_single_file_command_does(
        tmp_path: Path) -> None:
    paths, means = [], []
    for i in range(3):
        m = session(20, seed=20 + i)
        p = tmp_path / f"board{i}.txt"
        np.savetxt(p, m, fmt="%.4f", delimiter=",")
        paths.append(str(p))
        means.append(np.round(m, 4))
    rest = tmp_path / "rest.txt"  # samples of one pose, rate unknown: refused, as before
    np.savetxt(rest, [120.0, -340.0, 16900.0] + np.random.default_rng(2).normal(
        0, 3, (400, 3)), fmt="%.3f", delimiter=",")
    df = ac.calibrate_many([*paths, str(rest)], g=G, workers=1, progress=False)
    rows = df.set_index("path")
    for p, m in zip(paths, means, strict=True):
        r = rows.loc[p]
        assert r["status"] in ("ok", "weak") and r["n_dwells"] == 20
        assert "read as a table of dwell means" in r["message"]
        ref = ac.fit_static(m, G, observability="ignore")
        names = ("sx", "sy", "sz", "bx", "by", "bz", "m1", "m2", "m3")
        np.testing.assert_allclose([r[n] for n in names], ref.vector, rtol=1e-10)
    bad = rows.loc[str(rest)]
    assert bad["status"] == "error" and "sample rate is not in the file" in bad["message"]
    # A g given in g: the columns named for m/s^2 are in g in that row, and it says so.
    in_g = ac.calibrate_many([paths[0]], g=1.0, workers=1, progress=False).iloc[0]
    assert "g = 1 is in g: g_mps2, rms_mps2 and gap_rms_after_mps2 are in those units" in (
        in_g["message"])
    assert "is in g" not in rows.loc[paths[0]]["message"]


def test_a_table_with_a_time_per_pose_is_read_as_poses_with_their_times(tmp_path: Path) -> None:
    """One row per pose with the time of each (every 30 s): a rate of 1/30 Hz is far too low
    for the detector's window, so the rows are taken for dwell means, and their times reach
    the gap diagnosis (drift becomes testable)."""
    m = session(20, seed=11)
    t = 30.0 * np.arange(20)
    p = tmp_path / "poses_t.csv"
    np.savetxt(p, np.column_stack([t, m]), fmt="%.6f", delimiter=",", header="t,ax,ay,az",
               comments="")
    d = stream_dwells(p, means=None)
    np.testing.assert_array_equal(d.t, t)
    np.testing.assert_allclose(d.mean, np.round(m, 6), atol=1e-9)
    code, out = run("calibrate", "static", str(p), "--g", str(G))
    assert code == 0, out
    assert "its rate, 0.03333 Hz, is too low for a stream of samples" in out
    r = ac.diagnose(d, g=G)
    assert next(e for e in r.effects if e["effect"] == "drift")["status"] in (
        "testable", "selected", "not_confirmed")
    # Asked for plainly (stream_dwells' default), the detector's own error stands.
    with pytest.raises(CalibrationError, match="samples per window"):
        stream_dwells(p)


def test_a_label_column_names_the_poses(tmp_path: Path) -> None:
    """A lab's table of pose means with a text label per row (``position, ax, ay, az`` with
    ``+X up`` ...): the labels become the dwells' names instead of making the file look like
    a long-format log; labels that name sensors still make it one (and are refused)."""
    m = session(12, seed=13)
    labels = [f"{s}{a} {w}" for s, a, w in zip("+-" * 6, "XXYYZZXXYYZZ", ["up", "down"] * 6,
                                                strict=True)]
    labels = [f"{lab} #{i}" for i, lab in enumerate(labels)]
    p = tmp_path / "lab.csv"
    p.write_text("position,ax,ay,az\n" + "".join(
        f"{lab},{r[0]:.5f},{r[1]:.5f},{r[2]:.5f}\n" for lab, r in zip(labels, m, strict=True)))
    d = read_means(p)
    assert d.names == labels
    np.testing.assert_allclose(d.mean, np.round(m, 5), atol=1e-9)
    code, out = run("dwells", str(p))
    assert code == 0, out
    assert "column 'position' holds a text label per row" in out and "+X up #0" in out
    bad = tmp_path / "sensors.csv"
    bad.write_text("t,sensor,x,y,z\n" + "".join(
        f"{i * 0.01:.2f},{'GYR' if i % 2 else 'MAG'},0.1,0.2,0.3\n" for i in range(20)))
    with pytest.raises(CalibrationError, match="no label that names an accelerometer"):
        read_means(bad)


@pytest.mark.parametrize("layout", ["fortran", "strided", "column_view", "float32", "int16",
                                    "uint16_stored", "dataframe"])
def test_pose_means_in_any_memory_layout_fit_as_the_c_array(layout: str) -> None:
    """The same means as Fortran-ordered, strided, a column view, float32, int16 counts, int16
    stored as uint16 (65404 for -132) or a DataFrame: the same fit as the C-ordered float64
    array (to float32 rounding for float32), through read_means and stream_dwells."""
    import pandas as pd

    counts = np.round(session(n=30))
    ref = ac.fit_static(counts, G)
    arr: object = {
        "fortran": lambda: np.asfortranarray(counts),
        "strided": lambda: np.repeat(counts, 2, axis=0)[::2],
        "column_view": lambda: np.column_stack([counts, counts])[:, 3:],
        "float32": lambda: counts.astype(np.float32),
        "int16": lambda: counts.astype(np.int16),
        "uint16_stored": lambda: (counts.astype(np.int64) & 0xFFFF).astype(np.uint16),
        "dataframe": lambda: pd.DataFrame(counts, columns=["ax", "ay", "az"]),
    }[layout]()
    for d in (read_means(arr), stream_dwells(arr, means=True)):
        np.testing.assert_array_equal(d.mean, counts)
        fit = ac.fit_static(d, G)
        np.testing.assert_array_equal(fit.vector, ref.vector)
        assert np.all(np.abs(fit.vector - TRUTH) < 5 * fit.std)


def test_the_fleet_row_carries_the_readers_notes(tmp_path: Path) -> None:
    """What the reader decided reaches the fleet's message, as the single-file commands
    print it: a pose table's std columns left out (no count), and int16 values stored as
    uint16 read as signed; the fits equal the single-file ones."""
    m = session(20, seed=31)
    std = np.full_like(m, 3.0)
    p1 = tmp_path / "poses.csv"
    cols = {"x_mean": m[:, 0], "x_std": std[:, 0], "y_mean": m[:, 1], "y_std": std[:, 1],
            "z_mean": m[:, 2], "z_std": std[:, 2]}
    p1.write_text(",".join(cols) + "\n" + "\n".join(
        ",".join(repr(float(cols[c][i])) for c in cols) for i in range(len(m))) + "\n")
    counts = np.round(m).astype(np.int64)
    p2 = tmp_path / "stored_unsigned.txt"
    np.savetxt(p2, counts & 0xFFFF, fmt="%d")
    df = ac.calibrate_many([str(p1), str(p2)], g=G, workers=1, progress=False)
    rows = df.set_index("path")
    r1, r2 = rows.loc[str(p1)], rows.loc[str(p2)]
    assert "per-pose std columns (x_std, y_std, z_std) are not used" in r1["message"]
    assert "hold signed 16-bit values stored as unsigned" in r2["message"]
    names = ("sx", "sy", "sz", "bx", "by", "bz", "m1", "m2", "m3")
    np.testing.assert_allclose([r2[n] for n in names],
                               ac.fit_static(counts.astype(float), G,
                                             observability="ignore").vector, rtol=1e-10)


def test_a_table_of_means_gets_no_note_on_its_time_column_resolution(tmp_path: Path) -> None:
    """A table of means whose time column repeats (dwells split in halves share a time):
    read as samples its stamps would be coarser than the sample interval, and the note said
    so; poses have no sample interval, so a table read as poses does not get it."""
    s = static_dwell_means(14, max_tilt_deg=None, rng=3)
    t = np.repeat(np.arange(7) * 16.1, 2)
    p = tmp_path / "halves.csv"
    p.write_text("t_s,ax,ay,az\n" + "".join(f"{a:.1f},{m[0]:.6f},{m[1]:.6f},{m[2]:.6f}\n"
                                            for a, m in zip(t, s.means, strict=True)))
    code, out = run("calibrate", "static", str(p), "--g", "9.80665", "--means")
    assert code == 0, out
    assert "read as a table of dwell means" in out and "resolution" not in out, out


def test_columns_a_table_of_means_does_not_read_are_named(tmp_path: Path) -> None:
    """A real lab's table of face means with std columns named sx, sy, sz (accelcal's own
    names for the scale factors): they were dropped without a word, and the noise estimated."""
    s = static_dwell_means(8, max_tilt_deg=None, sigma=1e-3, rng=3)
    p = tmp_path / "means.csv"
    rows = "".join(f"{x},{y},{z},0.01,0.01,0.02,1800,26.1,ok\n" for x, y, z in s.means)
    p.write_text("ax,ay,az,sx,sy,sz,n,temp,flag\n" + rows)
    d, rec = ac.io._stream_dwells(p, means=True)
    note = [n for n in rec.notes() if "of the table are not used" in n]
    assert note and note[0].startswith("column(s) 'sx', 'sy', 'sz' of the table are not used: "
                                       "a per-pose std is read from columns named like "
                                       "x_std"), rec.notes()  # ('flag' has its own note)
    assert d.temperature is not None and d.var is None
    # Named as it reads them: no such note, and the noise comes from std / sqrt(n).
    q = tmp_path / "named.csv"
    q.write_text("ax,ay,az,x_std,y_std,z_std,n,temp\n" + "".join(
        f"{x},{y},{z},0.01,0.01,0.02,1800,26.1\n" for x, y, z in s.means))
    d2, rec2 = ac.io._stream_dwells(q, means=True)
    assert not any("not used" in n for n in rec2.notes()) and d2.var is not None
