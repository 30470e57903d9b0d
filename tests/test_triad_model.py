"""TriadModel: apply, the versioned JSON file validated against its published schema (every
corruption one clear error naming the field), dates, look-up by sensor and time, pickling."""

from __future__ import annotations

import copy
import datetime as dt
import json
import pickle

import accelcal as ac
import jsonschema
import numpy as np
import pytest
from accelcal import CalibrationError
from accelcal._triad_model import schema
from accelcal.sim.static import static_dwell_means


@pytest.fixture(scope="module")
def fitted() -> ac.StaticFit:
    s = static_dwell_means(20, max_tilt_deg=None, rng=14)
    return ac.fit_static(s.means, s.g_measured, sigma=1e-3)


@pytest.fixture()
def good(fitted, tmp_path) -> dict:
    path = tmp_path / "good.json"
    fitted.to_model(sensor_id="unit-7", temperature=21.5).save(path)
    return json.loads(path.read_text())


def test_apply_save_load_round_trip(fitted, tmp_path):
    tm = fitted.to_model(sensor_id="unit-7", temperature=21.5)
    means = fitted.means
    a = tm.apply(means)
    np.testing.assert_allclose(np.linalg.norm(a, axis=1) - fitted.g, fitted.residuals, atol=1e-12)
    np.testing.assert_allclose(a, fitted.calibrated_means(), atol=1e-12)
    # Streaming: chunks give the same as the whole; integer dtypes are read in place.
    np.testing.assert_allclose(np.vstack([tm.apply(means[:7]), tm.apply(means[7:])]), a)
    raw = np.array([[100, -200, 3000]], dtype=np.int16)
    ref = np.linalg.solve(tm.K, raw[0].astype(float) - tm.bias)
    np.testing.assert_allclose(tm.apply(raw, check_units=False)[0], ref, rtol=1e-13)
    path = tmp_path / "m.json"
    tm.save(path)
    back = ac.TriadModel.load(path)
    assert back == tm
    np.testing.assert_array_equal(back.K, tm.K)
    np.testing.assert_array_equal(back.covariance, tm.covariance)
    assert back.sensor_id == "unit-7" and back.g == fitted.g and back.temperature == 21.5
    d = json.loads(path.read_text())
    assert d["format"] == "accelcal.TriadModel" and d["version"] == 2
    jsonschema.validate(d, schema())  # the file the package writes meets its own schema
    assert pickle.loads(pickle.dumps(tm)) == tm
    with pytest.raises(CalibrationError, match="singular"):
        ac.TriadModel(np.zeros((3, 3)), [0, 0, 0])


def test_version_1_files_still_load(good, tmp_path):
    v1 = {k: v for k, v in good.items()
          if k not in ("covariance_noise_model", "covariance_scaled", "covariance_realistic")}
    v1["version"] = 1
    v1["date"] = "2026-11-23"
    v1["covariance"] = good["covariance_noise_model"]
    p = tmp_path / "v1.json"
    p.write_text(json.dumps(v1))
    m = ac.TriadModel.load(p)
    assert m.date == "2026-11-23T00:00:00Z" and m.realistic == "noise_model"
    np.testing.assert_array_equal(m.covariance, good["covariance_noise_model"])


def _set(path):
    def f(d, value):
        obj = d
        for k in path[:-1]:
            obj = obj[k]
        obj[path[-1]] = value
    return f


def _drop(key):
    def f(d, _):
        del d[key]
    return f


NAN = float("nan")

# (name, change, value, words the message must contain)
CORRUPTIONS = [
    ("covariance NaN", _set(["covariance_noise_model", 0, 0]), NAN, "covariance_noise_model"),
    ("covariance 8x8", lambda d, _: d.update(
        covariance_noise_model=[r[:8] for r in d["covariance_noise_model"][:8]]),
     None, "covariance_noise_model"),
    ("covariance ragged", lambda d, _: d["covariance_scaled"][2].pop(), None, "covariance"),
    ("covariance not symmetric", _set(["covariance_noise_model", 0, 1]), 1.0, "symmetric"),
    ("covariance negative variance", _set(["covariance_scaled", 4, 4]), -1.0, "negative"),
    ("realistic cov disagrees", _set(["covariance", 0, 0]), 123.0, "covariance"),
    ("scaled cov 100x", lambda d, _: d["covariance_scaled"][0].__setitem__(
        0, 100 * d["covariance_scaled"][0][0]), None, "covariance_scaled"),
    ("noise-model cov 0.5x", lambda d, _: d["covariance_noise_model"][3].__setitem__(
        3, 0.5 * d["covariance_noise_model"][3][3]), None, "covariance_noise_model"),
    ("chi2_dof negative", _set(["metadata", "chi2_dof"]), -2.0, "chi2_dof"),
    ("realistic covariance null", _set(["covariance_noise_model"]), None,
     "covariance_noise_model"),
    ("g NaN", _set(["g"]), NAN, "g"),
    ("g negative", _set(["g"]), -9.8, "g"),
    ("g text", _set(["g"]), "9.8", "g"),
    ("version 0", _set(["version"]), 0, "version"),
    ("version -7", _set(["version"]), -7, "version"),
    ("version true", _set(["version"]), True, "version"),
    ("version text", _set(["version"]), "1.0", "version"),
    ("version newer", _set(["version"]), 99, "newer"),
    ("K near singular", _set(["K", 2, 2]), 1e-12, "ill-conditioned"),
    ("K ill-conditioned", lambda d, _: d.update(K=[[1.0, 0, 0], [0.999999999, 1e-7, 0],
                                                   [0, 0, 1.0]]), None, "ill-conditioned"),
    ("K transposed", lambda d, _: d.update(K=np.array(d["K"]).T.tolist()), None, "K["),
    ("K boolean", lambda d, _: d.update(K=[[True, False, False], [False, True, False],
                                           [False, False, True]]), None, "K"),
    ("K NaN", _set(["K", 1, 1]), NAN, "K"),
    ("K 2x3", lambda d, _: d["K"].pop(), None, "K"),
    ("K disagrees with vector", _set(["vector", 0]), 2.0, "vector"),
    ("diag model, lower K", _set(["model"]), "diag", "K["),
    ("unknown model", _set(["model"]), "full", "model"),
    ("missing K", _drop("K"), None, "'K'"),
    ("missing bias", _drop("bias"), None, "'bias'"),
    ("bias of 2", lambda d, _: d["bias"].pop(), None, "bias"),
    ("bias infinite", _set(["bias", 0]), float("inf"), "bias"),
    ("units a string", _set(["units"]), "m/s^2", "units"),
    ("units output a number", _set(["units", "output"]), 9.8, "units"),
    ("metadata a list", _set(["metadata"]), [1, 2], "metadata"),
    ("sensor_id a number", _set(["sensor_id"]), 7, "sensor_id"),
    ("date not a date", _set(["date"]), "yesterday", "date"),
    ("temperature text", _set(["temperature"]), "hot", "temperature"),
    ("format wrong", _set(["format"]), "other", "format"),
]


@pytest.mark.parametrize("name,change,value,words", CORRUPTIONS, ids=[c[0] for c in CORRUPTIONS])
def test_each_corruption_is_one_clear_error_naming_the_field(good, tmp_path, name, change,
                                                              value, words):
    d = copy.deepcopy(good)
    change(d, value)
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(d))
    with pytest.raises(CalibrationError) as e:
        ac.TriadModel.load(p)
    msg = str(e.value)
    assert words in msg, msg
    assert "bad.json" in msg and "\n" not in msg


def test_not_json_and_missing_file(tmp_path):
    p = tmp_path / "x.json"
    p.write_text("{not json")
    with pytest.raises(CalibrationError, match="not JSON"):
        ac.TriadModel.load(p)
    with pytest.raises(CalibrationError, match="cannot read"):
        ac.TriadModel.load(tmp_path / "none.json")


def test_one_date_format():
    m = ac.TriadModel(np.eye(3), [0, 0, 0], date="2026-11-23T11:15:00+01:00")
    assert m.date == "2026-11-23T10:15:00Z"
    assert ac.TriadModel(np.eye(3), [0, 0, 0], date=dt.date(2026, 11, 23)).date == \
        "2026-11-23T00:00:00Z"
    now = ac.TriadModel(np.eye(3), [0, 0, 0]).datetime
    assert abs((now - dt.datetime.now(dt.timezone.utc)).total_seconds()) < 60
    with pytest.raises(CalibrationError, match="ISO 8601"):
        ac.TriadModel(np.eye(3), [0, 0, 0], date="23/11/2026")


def test_find_returns_the_calibration_valid_at_a_time(tmp_path):
    K = np.diag([1.01, 0.99, 1.0])
    for sid, day, b in [("A", 1, 0.1), ("A", 10, 0.2), ("A", 20, 0.3), ("B", 5, 0.9)]:
        m = ac.TriadModel(K, [b, 0, 0], sensor_id=sid, date=dt.datetime(2026, 3, day, 12))
        sub = tmp_path / ("2026" if day > 5 else "")
        sub.mkdir(exist_ok=True)
        m.save(sub / m.default_filename())
    (tmp_path / "notes.json").write_text('{"hello": 1}')  # not a calibration: skipped
    pick = ac.TriadModel.find(tmp_path, "A", at=dt.datetime(2026, 3, 15))
    assert pick.bias[0] == 0.2
    assert ac.TriadModel.find(tmp_path, "A", at="2026-03-20T12:00:00Z").bias[0] == 0.3
    assert ac.TriadModel.find(tmp_path, "A").bias[0] == 0.3  # now: the newest
    assert ac.TriadModel.find(tmp_path, "B", at=dt.date(2026, 3, 6)).bias[0] == 0.9
    with pytest.raises(CalibrationError, match="no calibration of sensor 'A'.*earliest"):
        ac.TriadModel.find(tmp_path, "A", at=dt.datetime(2026, 2, 1))
    with pytest.raises(CalibrationError, match="no calibration of sensor 'C'"):
        ac.TriadModel.find(tmp_path, "C")
    with pytest.raises(CalibrationError, match="does not exist"):
        ac.TriadModel.find(tmp_path / "nope", "A")
    # A corrupt calibration of the sensor is reported, not passed over.
    bad = json.loads((tmp_path / "2026" / "A_20260320T120000Z.json").read_text())
    bad["g"] = -1.0
    (tmp_path / "2026" / "A_20260320T120000Z.json").write_text(json.dumps(bad))
    with pytest.raises(CalibrationError, match="g"):
        ac.TriadModel.find(tmp_path, "A")


def test_find_neither_skips_a_cut_short_nor_a_bom_calibration(tmp_path):
    """The newest calibration cut short (a copy interrupted): find skipped it as 'not JSON'
    and returned the older one; saved with a BOM (Notepad), load read it and find skipped it
    and returned the older one. Now the cut one is named and the BOM one is found."""
    K = np.eye(3)
    old = ac.TriadModel(K, [0.1, 0, 0], sensor_id="S1", date=dt.datetime(2021, 1, 1))
    new = ac.TriadModel(K, [0.2, 0, 0], sensor_id="S1", date=dt.datetime(2022, 1, 1))
    old.save(tmp_path / old.default_filename())
    p = tmp_path / new.default_filename()
    new.save(p)
    text = p.read_text()
    p.write_text("\ufeff" + text, encoding="utf-8")
    assert ac.TriadModel.find(tmp_path, "S1", at="2022-06-01").bias[0] == 0.2
    p.write_text(text[: len(text) // 2])
    with pytest.raises(CalibrationError, match="not valid JSON.*cut short.*S1"):
        ac.TriadModel.find(tmp_path, "S1", at="2022-06-01")
    (tmp_path / "other.json").write_text('{"format": "something else", "x": [1, 2')
    p.write_text(text)
    assert ac.TriadModel.find(tmp_path, "S1", at="2022-06-01").bias[0] == 0.2


def test_schema_is_shipped_and_published():
    s = schema()
    assert s["properties"]["format"]["const"] == "accelcal.TriadModel"
    jsonschema.Draft202012Validator.check_schema(s)


def test_a_hand_edited_unit_and_a_bom_are_handled(tmp_path):
    """A calibration made with g = 9.81744 m/s^2 whose 'units.output' was edited to 'g': apply
    labelled m/s^2 values as g. Refused now, naming both fields; a file saved with a UTF-8
    BOM (Windows Notepad) reads."""
    import json

    from accelcal.sim.static import static_dwell_means

    s = static_dwell_means(20, max_tilt_deg=None, sigma=1e-4, rng=2, g=9.81744)
    m = ac.fit_static(s.means, 9.81744).to_model()
    p = tmp_path / "cal.json"
    m.save(p)
    d = json.loads(p.read_text())
    d["units"]["output"] = "g"
    bad = tmp_path / "edited.json"
    bad.write_text(json.dumps(d))
    with pytest.raises(ac.CalibrationError, match=r"'units.output' says 'g' but field 'g' is "
                                                  r"9.81744"):
        ac.TriadModel.load(bad)
    bom = tmp_path / "bom.json"
    bom.write_bytes(b"\xef\xbb\xbf" + p.read_bytes())
    np.testing.assert_array_equal(ac.TriadModel.load(bom).K, m.K)


def test_apply_an_empty_chunk_gives_an_empty_result(fitted):
    """Streaming code applies a calibration chunk by chunk and may read nothing: (0, 3) in
    gives (0, 3) float64 out (it raised "raw are empty"), and chunks with an empty one among
    them give the calibrated truth of the whole."""
    s = static_dwell_means(20, max_tilt_deg=None, rng=14)
    tm = fitted.to_model()
    for dtype in (np.float64, np.float32, np.int16):
        out = tm.apply(np.zeros((0, 3), dtype=dtype))
        assert out.shape == (0, 3) and out.dtype == np.float64
    parts = [tm.apply(s.means[:5]), tm.apply(s.means[5:5]), tm.apply(s.means[5:])]
    got = np.vstack(parts)
    np.testing.assert_array_equal(got, tm.apply(s.means))
    # The calibrated means are the simulated specific force, to a few noise std.
    assert np.max(np.abs(got - s.force)) < 6 * s.sigma
    with pytest.raises(CalibrationError, match="raw"):
        tm.apply(np.zeros((0, 3), dtype=bool))


def test_apply_takes_a_dataframes_columns_by_name_as_read_stream_does():
    """A model fitted through read_stream(df) of an ``az, ay, ax`` DataFrame and applied to
    that DataFrame gives |a| = g at every dwell (it took the columns in storage order:
    9.598 for 9.807)."""
    pd = pytest.importorskip("pandas")
    from accelcal.sim import field_session

    s = field_session(fs=500.0, n_dwells=12, dwell_s=4.0, move_s=2.0, rng=1,
                      max_tilt_deg=60)
    x = s.samples
    df = pd.DataFrame({"az": x[:, 2], "ay": x[:, 1], "ax": x[:, 0]})
    model = ac.fit_static(ac.detect_dwells(ac.io.read_stream(df, fs=s.fs)), s.g).to_model()
    out = model.apply(df)
    np.testing.assert_array_equal(out, model.apply(x))
    for b0, b1 in s.bounds:
        assert abs(np.linalg.norm(out[b0:b1], axis=1).mean() - s.g) < 1e-3
    np.testing.assert_array_equal(model.apply(pd.DataFrame(x)), model.apply(x))


def test_apply_reads_uint16_words_as_the_models_fit_read_them(tmp_path):
    """A calibration made from a file of uint16 words (int16 registers stored unsigned, read
    as signed by read_stream) and applied to live uint16 DAQ chunks of the same words gives
    |a| = g (it gave 35.3 m/s^2, silently), chunk by chunk as in one call. A model of an
    output that is unsigned by design (bias near mid-scale 32768) reads them as given."""
    import warnings

    from accelcal.sim import field_session

    mpu = np.array([1670., 1660., 1690., 300., -250., 500., 15., -20., 10.])
    for offset in (0.0, 32768.0):
        truth = mpu + np.r_[0, 0, 0, offset, offset, offset, 0, 0, 0]
        s = field_session(fs=500.0, n_dwells=16, dwell_s=4.0, move_s=2.0, rng=2,
                          max_tilt_deg=80, truth=truth, sigma=4.0)
        words = (np.round(s.samples).astype(np.int64) & 0xFFFF).astype(np.uint16)
        np.save(tmp_path / "u16.npy", words)
        model = ac.fit_static(ac.detect_dwells(ac.io.read_stream(tmp_path / "u16.npy",
                                                                 fs=s.fs)), s.g).to_model()
        with warnings.catch_warnings(record=True) as rec:
            warnings.simplefilter("always")
            whole = model.apply(words)
            parts = np.vstack([model.apply(words[a:a + 250])
                               for a in range(0, len(words), 250)])
        np.testing.assert_array_equal(parts, whole)
        for b0, b1 in s.bounds:
            assert abs(np.linalg.norm(whole[b0:b1], axis=1).mean() - s.g) < 0.01
        said = [str(w.message) for w in rec if "uint16" in str(w.message)]
        assert bool(said) == (offset == 0.0), said


def test_a_model_is_not_changed_in_place_nor_saved_unchecked(tmp_path):
    """K /= 9.80665 on a loaded model changed what apply did and what save wrote (a file
    load then refused, or worse accepted); an entry set off the model's triangle was saved
    as well. The arrays are read-only, and save checks the model as load checks a file;
    numpy scalars in the metadata are written as numbers (they raised a raw TypeError)."""
    m = ac.TriadModel(np.diag([1.01, 0.99, 1.0]), [0.1, 0, 0], sensor_id="S",
                      covariance_noise_model=np.eye(9) * 1e-8,
                      metadata={"n": np.int64(3), "x": np.float32(0.5)})
    for arr in (m.K, m.bias, m.covariance_noise_model):
        with pytest.raises(ValueError, match="read-only"):
            arr[0] = 2.0
    m.save(tmp_path / "m.json")
    back = ac.TriadModel.load(tmp_path / "m.json")
    assert back.metadata["n"] == 3 and back.metadata["x"] == 0.5
    m.K = np.array([[1.0, 5.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # off 'lower'
    with pytest.raises(CalibrationError, match="the model to write: K\\[0\\]\\[1\\]"):
        m.save(tmp_path / "bad.json")
    assert not (tmp_path / "bad.json").exists()


def test_a_hand_edited_g_or_output_unit_is_noticed(tmp_path):
    """'g' edited from 9.80665 to 9.0 loaded without a word (fit_static refuses 9.0 unless
    told), 'units.output' edited to 'mg' or 'ft/s^2' passed the unit check, which knew three
    units, and the bias edited with 'vector' loaded. A fit made with check_g=False records
    it, and its file loads quietly; a model without redundancy (9 dwells, the noise
    estimated) is saved without a covariance (to_model failed on its NaN one)."""
    import warnings

    from accelcal.sim.static import static_dwell_means

    s = static_dwell_means(20, max_tilt_deg=None, sigma=1e-4, rng=2)
    m = ac.fit_static(s.means, 9.80665).to_model()
    p = tmp_path / "m.json"
    m.save(p)
    d = json.loads(p.read_text())
    e = dict(d, g=9.0)
    p.write_text(json.dumps(e))
    with pytest.warns(UserWarning, match="not a plausible local gravity"), \
            pytest.raises(CalibrationError, match="do not reproduce the fit they record"):
        ac.TriadModel.load(p)
    # The bias and 'vector' edited together (consistent for the other checks): the session's
    # residual RMS gives it away; a file without a session is not checked so.
    e = json.loads(json.dumps(d))
    e["bias"][0] += 0.05
    e["vector"][3] += 0.05
    p.write_text(json.dumps(e))
    with pytest.raises(CalibrationError, match="residual RMS of .* the file says"):
        ac.TriadModel.load(p)
    del e["metadata"]["fit_session"]
    p.write_text(json.dumps(e))
    assert ac.TriadModel.load(p).bias[0] == pytest.approx(d["bias"][0] + 0.05)
    for unit in ("mg", "ft/s^2"):
        e = json.loads(json.dumps(d))
        e["units"]["output"] = unit
        p.write_text(json.dumps(e))
        with pytest.raises(CalibrationError, match="units.output' says"):
            ac.TriadModel.load(p)
    s9 = static_dwell_means(20, max_tilt_deg=None, sigma=1e-4, rng=2, g=9.0)
    m9 = ac.fit_static(s9.means, 9.0, check_g=False).to_model()
    m9.save(p)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert ac.TriadModel.load(p).g == 9.0
    s9 = static_dwell_means(9, max_tilt_deg=None, sigma=1e-4, rng=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bare = ac.fit_static(s9.means, 9.80665).to_model()
    bare.save(p)
    assert ac.TriadModel.load(p).covariance is None


def test_apply_warns_when_the_raw_data_are_in_other_units_than_the_model():
    """A model fitted in m/s^2 applied to the same sensor's data in g gave |a| = 0.67 with no
    word (the command line's apply checks the norms; the Python API did not)."""
    import warnings

    from accelcal.sim.static import static_dwell_means

    s = static_dwell_means(20, max_tilt_deg=None, sigma=1e-4, rng=2)
    m = ac.fit_static(s.means, 9.80665).to_model()
    with pytest.warns(UserWarning, match="calibrated norms are 0.1"):
        m.apply(s.means / 9.80665)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = m.apply(s.means)
    assert np.allclose(np.linalg.norm(out, axis=1), 9.80665, atol=1e-2)


# -- comparing two calibrations of one sensor -------------------------------------------------
_TRUTH = np.array([1.1, 0.95, 1.2, 0.3, -0.6, 0.3, 0.01, 0.02, 0.03])


def _pair(seed: int, drift_sz: float = 0.0, sigma_g: float = 1e-3) -> tuple:
    """Two simulated sessions of one sensor (24 poses on the sphere, dwell means at 1e-3),
    fitted with the same site g (one draw of a 1e-3 m/s^2 error, shared by both)."""
    g = 9.81
    gsite = g + np.random.default_rng(seed).normal(0.0, sigma_g)
    tb = _TRUTH.copy()
    tb[2] += drift_sz
    out = []
    for truth, rng in ((_TRUTH, 1000 + seed), (tb, 9000 + seed)):
        s = static_dwell_means(24, truth=truth, g=g, sigma=1e-3, sigma_g=0.0,
                               max_tilt_deg=None, rng=rng)
        fit = ac.fit_static(s.dwellset(), gsite, sigma_g=sigma_g or None)
        out.append(fit.to_model(sensor_id="S1"))
    return tuple(out)


def test_compare_has_its_nominal_size_and_finds_a_real_drift():
    """Wald test of two calibrations: under the null (the same sensor twice, the same site g
    with a 1e-3 m/s^2 error) it rejects at alpha 0.05 within the binomial band of 5 %; a real
    3e-4 drift of sz (3 std of the noise-only difference) is found. Counting the shared g's
    term twice (the files taken as independent) lost most of that power (20 % against 86 %
    for sz alone in the tester's 200 pairs)."""
    n = 400
    null = [a.compare(b) for a, b in (_pair(s) for s in range(n))]
    rate = np.mean([c.p_value < 0.05 for c in null])
    band = 3.0 * np.sqrt(0.05 * 0.95 / n)
    assert abs(rate - 0.05) < band, rate
    assert all(c.shared_g and c.dof == 9 for c in null)
    n = 100
    pairs = [_pair(s, drift_sz=3.04e-4) for s in range(n)]
    found = np.mean([a.compare(b).p_value < 0.05 for a, b in pairs])
    sz = np.mean([abs(a.compare(b).z[2]) > 1.96 for a, b in pairs])
    twice = np.mean([a.compare(b, shared_g=False).p_value < 0.05 for a, b in pairs])
    assert found > 0.6 and sz > 0.75 and twice < 0.4, (found, sz, twice)


def test_compare_realistic_covariance_is_conservative():
    """The Birge-scaled (realistic) covariance is inflated in every session whose chi2/dof
    exceeds 1 by chance, never shrunk: its Wald statistic is never above the noise model's,
    and the null rejects less than alpha (on these 200 pairs 0.5 % against 2 %; over 2000,
    2.7 % against 4.2 %). That is why compare uses the noise-model covariance by default."""
    pairs = [_pair(s, sigma_g=0.0) for s in range(200)]
    noise = [a.compare(b) for a, b in pairs]
    real = [a.compare(b, covariance="realistic") for a, b in pairs]
    assert all(r.chi2 <= n.chi2 * (1 + 1e-9) for r, n in zip(real, noise, strict=True))
    assert "realistic covariance" in real[0].summary()
    rate_n, rate_r = (np.mean([c.p_value < 0.05 for c in x]) for x in (noise, real))
    assert rate_r < rate_n, (rate_r, rate_n)


def test_compare_result_names_what_moved():
    a, b = _pair(3, drift_sz=2e-3)
    c = a.compare(b)
    assert c.moved() == ("sz",) and c.changed()
    assert c.difference[2] == pytest.approx(b.vector[2] - a.vector[2])
    np.testing.assert_allclose(c.z, c.difference / c.std)
    text = c.summary()
    assert "moved beyond 3 std: sz" in text and "chi2 = " in text and "on 9 dof" in text
    assert "noise-model covariance" in text and "drops out of the difference" in text
    d = c.to_dict()
    assert d["moved"] == ["sz"] and d["dof"] == 9 and json.dumps(d)
    with pytest.raises(AttributeError):
        c.chi2 = 0.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        c.difference[0] = 1.0
    same = a.compare(a)
    assert same.chi2 == 0.0 and same.moved() == () and not same.changed()


def test_compare_shared_g_only_when_both_used_the_same_g():
    a, b = _pair(5)
    # Independent: each file's own sigma_g^2 j j^T stays in; shared: it drops out.
    ind, sh = a.compare(b, shared_g=False), a.compare(b)
    ja = -a.vector / a.g
    ja[3:6] = 0.0
    assert ind.std[2] ** 2 - sh.std[2] ** 2 == pytest.approx(2e-6 * ja[2] ** 2, rel=0.01)
    s = static_dwell_means(24, truth=_TRUTH, g=9.81, sigma=1e-3, sigma_g=0.0,
                           max_tilt_deg=None, rng=77)
    other = ac.fit_static(s.dwellset(), 9.812, sigma_g=1e-3).to_model(sensor_id="S1")
    c = a.compare(other)
    assert not c.shared_g and "different g" in " ".join(c.notes)


def test_compare_refuses_other_sensors_unless_told(fitted):
    a = fitted.to_model(sensor_id="S1")
    for kw, what in ((dict(sensor_id="S2"), "sensor ids"), (dict(sensor_id="S1", units="m/s2"),
                                                            "output units")):
        b = fitted.to_model(**kw)
        with pytest.raises(CalibrationError, match=f"different {what}.*check_sensor=False"):
            a.compare(b)
        assert a.compare(b, check_sensor=False).chi2 == 0.0
    s = static_dwell_means(20, max_tilt_deg=None, rng=14)
    diag = ac.fit_static(s.means, s.g_measured, sigma=1e-3, model="diag").to_model(
        sensor_id="S1")
    with pytest.raises(CalibrationError, match="different models"):
        a.compare(diag)
    c = a.compare(diag, check_sensor=False)
    assert c.names == ("sx", "sy", "sz", "bx", "by", "bz") and c.dof == 6
    with pytest.raises(CalibrationError, match="no covariance"):
        a.compare(ac.TriadModel(fitted.K, fitted.bias, sensor_id="S1"))
    with pytest.raises(CalibrationError, match="covariance must be"):
        a.compare(a, covariance="scaled")


def test_compare_notes_a_noise_model_the_residuals_reject(fitted):
    s = static_dwell_means(20, max_tilt_deg=None, sigma=3e-3, rng=15)
    a = ac.fit_static(s.means, s.g_measured, sigma=1e-3).to_model()  # noise 3x the model
    c = a.compare(fitted.to_model())
    assert any("exceed its noise model" in n for n in c.notes), c.notes


def test_to_model_records_where_g_came_from_and_what_made_it(fitted):
    md = fitted.to_model().metadata
    assert md["sigma_g"] == 0.0 and md["g_source"] == "given"
    assert md["method"] == "lm" and md["accelcal_version"] == ac.__version__
    md = fitted.to_model(metadata={"g_source": "latitude formula"}).metadata
    assert md["g_source"] == "latitude formula"


def test_docstrings_say_the_bias_is_in_raw_units():
    """The docstring said "bias: (3,) output units": a tester importing an AN4508 calibration
    (a = W am + o, o in g) took the bias as -o and was 50 mg out. The model is
    a = K^-1 (am - b): K and b are in the raw (input) units, b = -K o with K = W^-1."""
    for doc in (ac.TriadModel.__doc__, ac.StaticFit.K.__doc__):
        assert "output units" not in doc and "raw (input) units" in doc, doc
    W = np.array([[1.02e-3, 0, 0], [5e-6, 0.98e-3, 0], [-4e-6, 3e-6, 1.01e-3]])  # g per mg
    o = np.array([-0.035, 0.020, -0.050])  # g
    rng = np.random.default_rng(2)
    a = rng.normal(size=(200, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    raw = np.linalg.solve(W, (a - o).T).T  # mg
    K = np.linalg.inv(W)
    m = ac.TriadModel(K, -K @ o, g=1.0, units="g", input_units="mg")
    np.testing.assert_allclose(m.apply(raw), a, atol=1e-12)


def _labelled(d: dict, **units) -> dict:
    e = json.loads(json.dumps(d))
    e["units"].update(units)
    return e


def test_a_file_in_another_convention_is_refused_naming_the_field(fitted):
    """A hand-written file stating imu_tk's convention (K in m/s^2 per count, a bias in
    m/s^2) or biases listed first in 'parameter_names' loaded silently, and to_dict then
    wrote accelcal's labels over it. Refused now, naming the field, what it says and what
    accelcal means; what accelcal writes (and spellings saying the same) still loads."""
    d = fitted.to_model(input_units="counts").to_dict()
    assert d["units"]["K"] == "input units per m/s^2" and d["units"]["bias"] == "input units"
    for e, words in (
        (_labelled(d, K="m/s^2 per count"), "field 'units.K' says 'm/s^2 per count'"),
        (_labelled(d, K="input units per g"), "field 'units.K' says 'input units per g'"),
        (_labelled(d, bias="m/s^2"), "field 'units.bias' says 'm/s^2'"),
        (_labelled(d, bias="mg"), "raw (input) units"),
        (dict(d, parameter_names=["bx", "by", "bz", "sx", "sy", "sz", "m1", "m2", "m3"]),
         "field 'parameter_names' says ['bx', 'by'"),
        (dict(d, parameter_names=["sx", "sy", "sz", "sx", "sy", "sz", "m1", "m2", "m3"]),
         "in the order ['sx', 'sy', 'sz', 'bx', 'by', 'bz', 'm1', 'm2', 'm3']"),
    ):
        with pytest.raises(CalibrationError) as err:
            ac.TriadModel.from_dict(e, "hand.json")
        assert "hand.json" in str(err.value) and words in str(err.value), str(err.value)
    assert "K maps the calibrated output to the raw output" in _refusal(
        _labelled(d, K="m/s^2 per count"))
    # What accelcal writes, and the same said otherwise, loads; absent labels too.
    ok = [d, _labelled(d, K="counts per m/s^2", bias="counts"),
          _labelled(d, K="raw (input) units per m/s^2", bias="raw units"),
          _labelled(d, K="input units  per m/s2")]
    bare = json.loads(json.dumps(d))
    del bare["units"]["K"], bare["units"]["bias"], bare["parameter_names"]
    for e in [*ok, bare]:
        m = ac.TriadModel.from_dict(e)
        np.testing.assert_array_equal(m.K, fitted.K)
        assert m.to_dict()["units"] == d["units"]


def _refusal(d: dict) -> str:
    with pytest.raises(CalibrationError) as err:
        ac.TriadModel.from_dict(d)
    return str(err.value)


def test_constructor_refuses_an_output_unit_that_contradicts_g():
    """units="g" with g = 9.81 was accepted by the constructor (only a file was checked):
    apply's output was labelled g while in m/s^2 until save refused it."""
    with pytest.raises(CalibrationError, match=r"units says 'g' but g is 9.81, not gravity in "
                                               r"g .*'m/s\^2' for g = 9.81"):
        ac.TriadModel(np.diag([400., 410., 405.]), [0, 0, 0], model="diag", g=9.81, units="g")
    for units, g in (("g", 1.0), ("mg", 1000.0), ("m/s^2", 9.81), ("counts", 9.81),
                     ("g", None)):
        assert ac.TriadModel(np.eye(3), [0, 0, 0], g=g, units=units).units == units


def test_fit_static_records_the_input_units(fitted):
    """fit_static had no input_units= (only to_model did): now the fit records them, its
    summary names them, and to_model writes them; a DwellSet in other units is refused."""
    s = static_dwell_means(20, max_tilt_deg=None, sigma=1e-4, rng=2)
    f = ac.fit_static(s.means, s.g_measured, input_units="counts")
    assert f.input_units == "counts" and "K in counts per m/s^2" in f.summary()
    assert f.to_model().to_dict()["units"]["input"] == "counts"
    np.testing.assert_array_equal(f.vector, ac.fit_static(s.means, s.g_measured).vector)
    d = ac.DwellSet(mean=s.means, units="mg")
    assert ac.fit_static(d, s.g_measured, input_units="mg").input_units == "mg"
    with pytest.raises(CalibrationError, match="input_units='counts' disagrees .*'mg'"):
        ac.fit_static(d, s.g_measured, input_units="counts")


def test_a_full_matrix_names_its_triangular_factor():
    """A full K (the inverse of a six-position calibration's W) was refused as "wrong
    triangle or wrong model" with no route. The message now gives one: the triangular
    factor of numpy.linalg.qr(K.T), which gives the same norm as W for every input."""
    W = np.array([[1.02e-3, 2e-6, -3e-6], [5e-6, 0.98e-3, 4e-6], [-4e-6, 3e-6, 1.01e-3]])
    o = np.array([-0.035, 0.020, -0.050])
    K = np.linalg.inv(W)
    msg = _ctor_refusal(K, -K @ o)
    assert "rotation" in msg and "numpy.linalg.qr(K.T)" in msg and "K_lower = r.T" in msg
    # The recipe of the message, checked: the same norm |W am + o| for every raw input.
    q, r = np.linalg.qr(K.T)
    r *= np.sign(np.diag(r))[:, None]
    cal = ac.TriadModel(r.T, -K @ o, model="lower", g=1.0, units="g", input_units="mg")
    assert np.all(np.diag(cal.K) > 0)
    raw = np.random.default_rng(0).normal(0, 2000, (500, 3))
    np.testing.assert_allclose(np.linalg.norm(cal.apply(raw, check_units=False), axis=1),
                               np.linalg.norm(raw @ W.T + o, axis=1), rtol=1e-12)
    # A triangle on the wrong side is not a full matrix: the old words only.
    low = np.tril(K)
    assert "rotation" not in _ctor_refusal(low.T, [0, 0, 0])


def _ctor_refusal(K, b) -> str:
    with pytest.raises(CalibrationError, match="wrong triangle or wrong model") as err:
        ac.TriadModel(K, b)
    return str(err.value)


def _history(folder) -> tuple:
    """Two calibrations of S1 (2021, 2022) in ``folder``: (old path, new path)."""
    K = np.eye(3)
    old = ac.TriadModel(K, [0.1, 0, 0], sensor_id="S1", date=dt.datetime(2021, 1, 1))
    new = ac.TriadModel(K, [0.2, 0, 0], sensor_id="S1", date=dt.datetime(2022, 1, 1))
    for m in (old, new):
        m.save(folder / m.default_filename())
    return folder / old.default_filename(), folder / new.default_filename()


def test_find_does_not_pass_over_a_calibration_it_cannot_read(tmp_path, monkeypatch):
    """The newest calibration unreadable (mode 000, as a user without the right): find
    skipped it in silence and returned the older one. Now it raises, naming the file. (The
    read is made to fail by hand: running as root bypasses file permissions.)"""
    import errno

    from accelcal import _triad_model

    _, new = _history(tmp_path)
    real = _triad_model.read_small_text

    def read(path, what, *a):
        if str(path) == str(new):
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real(path, what, *a)

    monkeypatch.setattr(_triad_model, "read_small_text", read)
    with pytest.raises(CalibrationError) as e:
        ac.TriadModel.find(tmp_path, "S1")
    assert str(e.value) == (f"cannot read {str(new)!r} (Permission denied), which may be a "
                            "calibration of sensor 'S1': make it readable, or move it out of "
                            "the folder")


def test_find_reads_only_regular_files(tmp_path):
    """A FIFO named *.json hung find for ever, and a *.json link to /dev/zero ate all memory
    (MemoryError with an empty message). Now only regular files are read; what was skipped is
    named when no calibration qualifies."""
    import os
    import signal

    old, new = _history(tmp_path)
    os.mkfifo(tmp_path / "zz.json")
    os.symlink("/dev/zero", tmp_path / "b.json")
    os.symlink(tmp_path / "gone", tmp_path / "c.json")
    def hung(signum, frame):
        raise TimeoutError("find hung")

    old_handler = signal.signal(signal.SIGALRM, hung)
    signal.alarm(20)  # a hang fails the test instead of blocking the run
    try:
        assert ac.TriadModel.find(tmp_path, "S1").bias[0] == 0.2
        with pytest.raises(CalibrationError) as e:
            ac.TriadModel.find(tmp_path, "S2")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old_handler)
    assert str(e.value).startswith("no calibration of sensor 'S2' dated at or before ")
    assert str(e.value).endswith(
        f" in {str(tmp_path)!r} (0 later; skipped, not read: {str(tmp_path / 'b.json')!r} (a "
        f"character device), {str(tmp_path / 'c.json')!r} (a broken link), "
        f"{str(tmp_path / 'zz.json')!r} (a FIFO (named pipe)))")


def test_load_refuses_a_device_and_a_file_too_large(tmp_path):
    """`accelcal apply /dev/zero ...` (TriadModel.load of a device) read without end."""
    with pytest.raises(CalibrationError) as e:
        ac.TriadModel.load("/dev/zero")
    assert str(e.value) == "calibration file '/dev/zero' is a character device, not a file"
    big = tmp_path / "big.json"
    with open(big, "wb") as fh:
        fh.truncate(100 << 20)  # sparse
    with pytest.raises(CalibrationError, match=r"holds 104857600 bytes, more than the 64 MB"):
        ac.TriadModel.load(big)


def test_save_without_overwrite_never_replaces_a_file(tmp_path):
    """save(path, overwrite=False) links the complete file to its name: a file there (one
    another run wrote meanwhile) is kept, byte for byte, and nothing else is left behind."""
    import errno
    import os

    m = ac.TriadModel(np.eye(3), [0.1, 0, 0], sensor_id="S1")
    p = tmp_path / "cal.json"
    p.write_text("theirs")
    with pytest.raises(FileExistsError) as e:
        m.save(p, overwrite=False)
    assert e.value.errno == errno.EEXIST and e.value.filename == str(p)
    assert p.read_text() == "theirs" and sorted(os.listdir(tmp_path)) == ["cal.json"]
    q = tmp_path / "new.json"
    m.save(q, overwrite=False)
    assert ac.TriadModel.load(q) == m
    m.save(p)  # the default replaces, as before
    assert ac.TriadModel.load(p) == m
