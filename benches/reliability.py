"""Count what the library does with bad, corrupted, chunked, concurrent and interrupted input.

Writes docs/reliability.md (atomically). Run from the repository root:
``.venv/bin/python benches/reliability.py [--quick] [--out docs/reliability.md]``

The cases come from the test suite itself (tests/ is put on ``sys.path``); this script only
runs them at a fixed, larger size and counts the outcomes instead of stopping at the first
failure.

1. Bad input over the public API: the hypothesis tests of ``tests/test_properties.py`` and the
   ``*_any_array`` tests of ``tests/test_centrifuge_gradiometer_inputs.py``, derandomised, a
   fixed number of examples each. The tests' own ``_check`` / ``_clear`` helper is wrapped to
   classify every call: a valid result, a clean CalibrationError/DegenerateDataError naming
   the argument, our error not naming it, a result with NaN and no status (silent wrong),
   another exception type, a panic (pyo3's PanicException, a BaseException). Each test file
   runs in a worker subprocess with a timeout, streaming one line per case, so a hang is
   counted (and its case named) instead of hanging the script.
2. Calibration files: ``TriadModel.load`` on the corruptions listed in
   ``tests/test_triad_model.py`` plus generic mutations of every field of a valid file.
3. Streaming: ``DwellAccumulator`` over random chunkings (``tests/test_dwell.py``'s
   ``chunkings`` / ``_check_stream``) equals the one-shot ``detect_dwells`` / ``dwell_stats``,
   on a simulated field session and on the Xsens recording (when ../shared/data is present).
4. Threads: the GIL-releasing entry points called from several Python threads at once, the
   1-vs-2 rayon thread tests and the concurrent push/position/finish deadlock test.
5. Output paths and interruptions: the cases of ``tests/test_files.py``, collected and run.
6. Monte Carlo: the figures of docs/reliability-static.md and docs/centrifuge-reproduction.md,
   quoted with their source (not re-run here).
"""

from __future__ import annotations

import argparse
import collections
import datetime as dt
import importlib
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
TESTS = ROOT / "tests"
DOCS = ROOT / "docs"
XSENS = ROOT.parent / "shared" / "data" / "xsens-mti" / "xsens_acc.txt"

OUTCOMES = ["result", "clean", "unnamed", "silent", "other", "panic", "hang"]
# The property tests per worker: (module, helper wrapped, tests; None = every hypothesis test).
PROPERTY_MODULES: dict[str, tuple[str, list[str] | None]] = {
    "test_properties": ("_check", None),
    "test_centrifuge_gradiometer_inputs": (
        "_clear",
        ["test_fit_centrifuge_any_array", "test_startup_bias_any_array",
         "test_demodulate_any_array"],
    ),
}
# Tests that check two public functions per example: the label of each call.
SECOND_CALL = {"test_startup_bias_any_array": ["startup_bias", "predict_startup_accuracy"]}


def _tests_on_path() -> None:
    if str(TESTS) not in sys.path:
        sys.path.insert(0, str(TESTS))


def _hyp_settings(examples: int) -> Any:
    from hypothesis import HealthCheck, Phase, settings

    # Derandomised, no example database (nothing written into the checkout), no shrinking:
    # failures are counted by the wrapped helper, never raised to hypothesis.
    return settings(max_examples=examples, derandomize=True, database=None, deadline=None,
                    phases=[Phase.explicit, Phase.generate],
                    suppress_health_check=list(HealthCheck))


def _seed(test: Any, name: str) -> None:
    """A fixed seed per test, from its name: the same cases every run (hypothesis's own
    derandomisation hashes the wrapped function, whose repr holds a memory address here)."""
    import zlib

    from hypothesis import seed

    seed(zlib.crc32(name.encode()))(test)


def _describe(x: Any) -> str:
    """A short description of a drawn value: arrays with shape, dtype and layout."""
    import numpy as np

    if isinstance(x, np.ndarray):
        lay = "C" if x.flags.c_contiguous else "F" if x.flags.f_contiguous else "strided"
        with np.printoptions(threshold=6, edgeitems=2):
            body = " ".join(repr(x).split())
        return f"ndarray{x.shape} {x.dtype} {lay}: {body[:120]}"
    if type(x).__name__ in ("DataFrame", "Series"):
        return f"{type(x).__name__}{x.shape} {getattr(x, 'dtypes', '')}".split("\n")[0]
    if isinstance(x, list):
        return f"list of {len(x)}: {repr(x)[:80]}"
    return repr(x)[:120]


def _short(kw: dict[str, Any], n: int = 300) -> str:
    s = ", ".join(f"{k}={_describe(v)}" for k, v in kw.items())
    return s if len(s) <= n else s[: n - 3] + "..."


# ---- 1. bad input: worker ---------------------------------------------------------------------
def _classify(kind: str, value: Any, helper_exc: BaseException | None) -> tuple[str, str]:
    """Outcome of one call: ``kind`` is what the call did ("returned"/"raised"), ``helper_exc``
    what the test's own check of it raised."""
    from accelcal import CalibrationError

    if kind == "returned":
        if helper_exc is None:
            return "result", ""
        if isinstance(helper_exc, AssertionError):
            return "silent", str(helper_exc)
        return "other", f"result check raised {type(helper_exc).__name__}: {helper_exc}"
    exc = value
    if isinstance(exc, CalibrationError):
        if helper_exc is None:
            return "clean", ""
        return "unnamed", f"{type(exc).__name__}: {exc}"
    if isinstance(exc, AssertionError):  # _clear's calls assert finite results themselves
        return "silent", str(exc)
    if not isinstance(exc, Exception):
        return "panic", f"{type(exc).__name__}: {exc}"
    return "other", f"{type(exc).__name__}: {exc}"


def _property_worker(module_name: str, examples: int) -> None:
    """Run one test file's property tests, one JSON line per case on stdout."""
    _tests_on_path()
    import conftest  # noqa: F401  (hypothesis profiles of the suite)

    mod = importlib.import_module(module_name)
    helper_name, names = PROPERTY_MODULES[module_name]
    original = getattr(mod, helper_name)
    state: dict[str, Any] = {"test": "", "args": "", "calls": 0}

    def emit(rec: dict[str, Any]) -> None:
        sys.stdout.write(json.dumps(rec) + "\n")
        sys.stdout.flush()

    def wrapped_helper(call: Callable[[], Any], *rest: Any, **kw: Any) -> None:
        seen: dict[str, Any] = {}

        def recorded() -> Any:
            try:
                res = call()
            except BaseException as e:
                seen["kind"], seen["value"] = "raised", e
                raise
            seen["kind"], seen["value"] = "returned", res
            return res

        helper_exc: BaseException | None = None
        try:
            original(recorded, *rest, **kw)
        except (KeyboardInterrupt, SystemExit):
            raise
        except BaseException as e:
            helper_exc = e
        if "kind" not in seen:
            outcome, detail = "other", f"helper raised {type(helper_exc).__name__}: {helper_exc}"
        elif seen["kind"] == "raised":
            # The helper re-raises what is not ours; for ours it raises only if unnamed.
            exc = seen["value"]
            outcome, detail = _classify("raised", exc, None if helper_exc is exc else helper_exc)
        else:
            outcome, detail = _classify("returned", seen["value"], helper_exc)
        labels = SECOND_CALL.get(state["test"])
        label = labels[state["calls"]] if labels and state["calls"] < len(labels) \
            else state["test"].removeprefix("test_")
        if state["test"].startswith("probe "):
            label = state["test"]
        state["calls"] += 1
        rec: dict[str, Any] = {"label": label, "outcome": outcome}
        if outcome not in ("result", "clean"):
            rec["detail"] = detail[:400]
            rec["args"] = state["args"]
        emit(rec)

    setattr(mod, helper_name, wrapped_helper)
    tests = [getattr(mod, n) for n in (names or sorted(dir(mod)))
             if n.startswith("test_") and hasattr(getattr(mod, n), "hypothesis")]
    for test in tests:
        inner = test.hypothesis.inner_test

        def counted(*args: Any, _inner: Any = inner, **kwargs: Any) -> None:
            state["args"] = _short(kwargs or {str(i): a for i, a in enumerate(args)})
            state["calls"] = 0
            emit({"case": state["test"], "args": state["args"]})
            try:
                _inner(*args, **kwargs)
            except (KeyboardInterrupt, SystemExit):
                raise
            except BaseException as e:  # outside the helper (e.g. a check after the call)
                if type(e).__module__.startswith("hypothesis"):
                    raise
                emit({"label": state["test"].removeprefix("test_"),
                      "outcome": "panic" if not isinstance(e, Exception) else "other",
                      "detail": f"{type(e).__name__}: {e}"[:400], "args": state["args"]})

        test.hypothesis.inner_test = counted
        test._hypothesis_internal_use_settings = _hyp_settings(examples)
        _seed(test, test.__name__)
        state["test"] = test.__name__
        emit({"begin": test.__name__})
        test()
        emit({"end": test.__name__})
    for label, args, call, words, ok in _probes(mod) if module_name == "test_properties" else []:
        state["test"], state["args"], state["calls"] = f"probe {label}", args, 0
        emit({"begin": state["test"]})
        emit({"case": state["test"], "args": args})
        wrapped_helper(call, words, ok)


def _probes(mod: Any) -> list[tuple[str, str, Callable[[], Any], list[str], Callable[[Any], bool]]]:
    """Fixed cases that seeded runs of the property tests once drew, run every time (with the
    words and result check of the corresponding test)."""
    import accelcal as ac
    import numpy as np

    x = np.arange(6.0)
    return [("allan_deviation, fs subnormal", "x=np.arange(6.0), fs=5e-324",
             lambda: ac.allan_deviation(x, 5e-324), ["x", "fs", "sample"],
             lambda r: mod._finite(r[0]) and bool(np.all(np.asarray(r[0]) > 0)))]


def bad_input(examples: int, timeout_s: float) -> dict[str, Any]:
    """Category 1: run each property test file in a worker, count outcomes per function."""
    counts: dict[str, collections.Counter[str]] = {}
    examples_bad: list[str] = []
    sources: dict[str, str] = {}
    for module in PROPERTY_MODULES:
        cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", module,
               "--examples", str(examples)]
        lines: list[str] = []
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s,
                               cwd=ROOT)
            lines = r.stdout.splitlines()
            failed = r.returncode != 0
            err = r.stderr
        except subprocess.TimeoutExpired as e:
            out = e.stdout or b""
            lines = (out.decode() if isinstance(out, bytes) else out).splitlines()
            failed, err = False, ""
            last = next((json.loads(x) for x in reversed(lines) if '"case"' in x), None)
            if last:
                label = last["case"].removeprefix("test_")
                counts.setdefault(label, collections.Counter())["hang"] += 1
                examples_bad.append(f"hang in {last['case']} ({timeout_s:.0f} s): {last['args']}")
        current = ""
        for line in lines:
            rec = json.loads(line)
            if "begin" in rec:
                current = rec["begin"]
            elif "outcome" in rec:
                counts.setdefault(rec["label"], collections.Counter())[rec["outcome"]] += 1
                sources[rec["label"]] = f"tests/{module}.py::{current}"
                if "detail" in rec and len(examples_bad) < 20:
                    examples_bad.append(f"{rec['label']} ({rec['outcome']}): {rec['detail']} "
                                        f"- input {rec['args']}")
        if failed:
            examples_bad.append(f"worker {module} exited with an error: {err.strip()[-600:]}")
    return {"counts": counts, "bad": examples_bad, "sources": sources}


# ---- 2. calibration files ---------------------------------------------------------------------
def _generic_mutations(good: dict[str, Any]) -> Iterator[tuple[str, Callable[[dict], None],
                                                               str]]:
    """Every field dropped or given a wrong value; one element of every array replaced."""
    values: list[tuple[str, Any]] = [("null", None), ("text", "text"), ("NaN", float("nan")),
                                     ("true", True), ("empty list", []), ("empty object", {})]
    for key in good:
        def drop(d: dict, k: str = key) -> None:
            del d[k]
        yield f"{key} missing", drop, key
        for vname, v in values:
            if v == good[key] or type(v) is type(good[key]) and v in ([], {}):
                continue

            def put(d: dict, k: str = key, v: Any = v) -> None:
                d[k] = v
            yield f"{key} {vname}", put, key
        if isinstance(good[key], list) and good[key] and not isinstance(good[key][0], str):
            elems: list[tuple[str, Any]] = [("NaN", float("nan")), ("inf", float("inf")),
                                            ("text", "1"), ("null", None), ("1e308", 1e308)]
            for vname, v in elems:
                def elem(d: dict, k: str = key, v: Any = v) -> None:
                    obj = d[k]
                    while isinstance(obj[0], list):
                        obj = obj[-1]
                    obj[-1] = v
                yield f"{key} last element {vname}", elem, key
        if key.startswith("covariance") and isinstance(good[key], list):
            def scale(d: dict, k: str = key) -> None:
                d[k][0][0] *= 100.0
            yield f"{key} first variance x100", scale, key


def _apply(change: Callable[[dict, Any], None], value: Any, d: dict) -> None:
    change(d, value)


# The numbers of a calibration a corruption must never change silently.
NUMBERS = ("K", "bias", "covariance", "covariance_noise_model", "covariance_scaled", "g")


def calibration_files() -> dict[str, Any]:
    """Category 2: TriadModel.load on corrupted copies of a valid file."""
    import copy

    import accelcal as ac
    import numpy as np
    from accelcal import CalibrationError
    from accelcal.sim.static import static_dwell_means

    _tests_on_path()
    from test_triad_model import CORRUPTIONS

    # The valid file of test_triad_model's fixtures (sigma given: the noise-model covariance is
    # the realistic one), and the same fit with the noise estimated (the scaled one is).
    s = static_dwell_means(20, max_tilt_deg=None, rng=14)
    models = {
        "sigma given": ac.fit_static(s.means, s.g_measured, sigma=1e-3).to_model(
            sensor_id="unit-7", temperature=21.5),
        "noise estimated": ac.fit_static(s.means, s.g_measured).to_model(
            sensor_id="unit-7", temperature=21.5),
    }
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bad.json"
        goods = {}
        for key, model in models.items():
            model.save(path)
            goods[key] = json.loads(path.read_text())
            assert ac.TriadModel.load(path) == model
        Case = tuple[str, Callable[[dict], None], str]
        listed: list[Case] = [(n, partial(_apply, c, v), w) for n, c, v, w in CORRUPTIONS]
        suites: list[tuple[str, str, list[Case]]] = [
            ("corruptions listed in tests/test_triad_model.py (file of a fit with sigma given)",
             "sigma given", listed),
        ] + [
            (f"generic mutations, file of a fit with {key} (realistic covariance: "
             f"{goods[key]['covariance_realistic']}): every field dropped / null / text / NaN / "
             "true / empty; last element of every array NaN / inf / text / null / 1e308; "
             "first variance of every covariance x100", key, list(_generic_mutations(goods[key])))
            for key in models
        ]
        for title, key, cases in suites:
            good, model = goods[key], models[key]
            c: collections.Counter[str] = collections.Counter()
            notes: list[str] = []
            for name, change, words in cases:
                d = copy.deepcopy(good)
                change(d)
                path.write_text(json.dumps(d))
                try:
                    m = ac.TriadModel.load(path)
                except CalibrationError as e:
                    msg = str(e).replace(str(path), "bad.json")
                    if words in msg and "bad.json" in msg and "\n" not in msg:
                        c["clean"] += 1
                    else:
                        c["unnamed"] += 1
                        notes.append(f"[{key}] {name}: error does not name '{words}': {msg[:200]}")
                    continue
                except Exception as e:
                    c["other"] += 1
                    notes.append(f"[{key}] {name}: {type(e).__name__}: {e}")
                    continue
                except BaseException as e:
                    c["panic"] += 1
                    notes.append(f"[{key}] {name}: {type(e).__name__}: {e}")
                    continue
                if m == model:
                    c["harmless"] += 1
                    notes.append(f"[{key}] {name}: accepted (loads identical: a derived or "
                                 "defaulted field)")
                    continue
                dropped, changed = [], []
                for a in NUMBERS:
                    a0, a1 = getattr(model, a), getattr(m, a)
                    if a1 is None and a0 is not None:
                        dropped.append(a)
                    elif not np.array_equal(np.asarray(a0, dtype=float),
                                            np.asarray(a1, dtype=float)):
                        changed.append(a)
                if changed:
                    c["silent"] += 1
                    notes.append(f"[{key}] {name}: LOADS SILENTLY with "
                                 f"{', '.join(changed)} changed")
                else:
                    c["harmless"] += 1
                    what = "an optional number absent" if dropped else \
                        "a descriptive field changed"
                    notes.append(f"[{key}] {name}: accepted ({what})")
            out[title] = {"tried": len(cases), "counts": c, "notes": notes}
    return out


# ---- 3. streaming -----------------------------------------------------------------------------
def streaming(examples: int, xsens_examples: int) -> dict[str, Any]:
    """Category 3: DwellAccumulator over random chunkings equals the one-shot call."""
    import numpy as np
    from hypothesis import given
    from hypothesis import strategies as st

    _tests_on_path()
    import test_dwell
    from accelcal.io import read_stream
    from accelcal.sim import field_session

    rows: list[dict[str, Any]] = []

    def run(name: str, x: np.ndarray, fs: float, t: np.ndarray, n: int) -> None:
        c: collections.Counter[str] = collections.Counter()
        notes: list[str] = []
        cuts_seen: list[int] = []
        orig_push = test_dwell.push_in_chunks

        def push(acc: Any, cuts: list[int], *a: Any, **k: Any) -> None:
            cuts_seen.append(len(cuts))
            orig_push(acc, cuts, *a, **k)

        @given(data=st.data())
        def one(data: st.DataObject) -> None:
            try:
                test_dwell._check_stream(x, fs, t, data)
                c["identical"] += 1
            except AssertionError as e:
                c["different"] += 1
                notes.append(str(e)[:300])
            except Exception as e:
                if type(e).__module__.startswith("hypothesis"):
                    raise
                c["other"] += 1
                notes.append(f"{type(e).__name__}: {e}"[:300])

        one._hypothesis_internal_use_settings = _hyp_settings(n)  # type: ignore[attr-defined]
        _seed(one, name)
        test_dwell.push_in_chunks = push
        try:
            one()
        finally:
            test_dwell.push_in_chunks = orig_push
        rows.append({"stream": name, "samples": x.shape[0], "tried": sum(c.values()),
                     "counts": c, "notes": notes,
                     "chunks": (min(cuts_seen) + 1, max(cuts_seen) + 1) if cuts_seen else None})

    sim = field_session(fs=200.0, n_dwells=8, dwell_s=8.0, move_s=3.0, rng=1)
    run("simulated field session (accelcal.sim.field_session, 200 Hz, 8 dwells, seed 1)",
        np.asarray(sim.samples), sim.fs, np.asarray(sim.t, dtype=np.float64), examples)
    skipped = None
    if XSENS.exists():
        s = read_stream(XSENS)
        assert s.fs is not None and s.t is not None
        run("Xsens MTi recording (xsens-mti/xsens_acc.txt, the field guide's public data)",
            np.asarray(s.samples), s.fs, np.asarray(s.t, dtype=np.float64), xsens_examples)
    else:
        skipped = "The recording xsens-mti/xsens_acc.txt is absent: its row was skipped"
    return {"rows": rows, "skipped": skipped}


# ---- 4. threads -------------------------------------------------------------------------------
def threads(calls: int, deadlock_runs: int) -> dict[str, Any]:
    """Category 4: identical results from several threads; no deadlock; 1 vs 2 rayon threads."""
    import accelcal as ac
    import numpy as np
    from accelcal.sim import gradiometer_session
    from accelcal.sim.static import static_dwell_means

    _tests_on_path()
    import test_centrifuge_gradiometer_inputs as tcg
    import test_dwell
    import test_static

    rng = np.random.default_rng(41)
    means = np.stack([static_dwell_means(20, max_tilt_deg=45, rng=rng).means for _ in range(400)])
    x = np.round(test_dwell.piecewise_static(21, fs=500.0) * 3000).astype(np.int16)
    b = np.array([[0, 1000], [1000, 2500], [3000, 4000]])
    g = gradiometer_session([0.0, 90.0], radius_m=0.1, spin_hz=0.5, fs=400.0, dwell_s=20.0,
                            slew_s=2.0, noise_mps2=1e-8, seed=1)
    big, ph = np.tile(g.accel, (10, 1)), np.tile(g.phase, 10)
    gb = [[0, big.shape[0] // 2], [big.shape[0] // 2, big.shape[0]]]
    entry: dict[str, Callable[[], Any]] = {
        "fit_static_batch (400 sessions x 20 dwells)": lambda: ac.fit_static_batch(
            means, 9.80665, sigma=1e-3),
        "dwell_stats (int16 stream, 3 dwells)": lambda: ac.dwell_stats(x, b),
        "detect_dwells (int16 stream)": lambda: ac.detect_dwells(x, 500.0),
        "demodulate (gradiometer stream, 2 dwells)": lambda: ac.demodulate(
            big, ph, gb, radius_m=g.radius_m),
    }
    rows = []
    for name, f in entry.items():
        ref = f()
        c: collections.Counter[str] = collections.Counter()
        notes: list[str] = []
        with ThreadPoolExecutor(4) as ex:
            for r in ex.map(lambda _, f=f: f(), range(calls)):
                try:
                    tcg._same(r, ref)
                    c["identical"] += 1
                except AssertionError as e:
                    c["different"] += 1
                    notes.append(str(e)[:200])
        rows.append({"what": name, "tried": calls, "counts": c, "notes": notes})

    subs: list[tuple[str, Callable[[], None], int]] = [
        ("DwellAccumulator push / position / finish from two threads "
         "(tests/test_dwell.py::test_concurrent_push_position_finish_do_not_deadlock, "
         "subprocess, 300 s timeout)",
         test_dwell.test_concurrent_push_position_finish_do_not_deadlock, deadlock_runs),
        ("dwell_stats / detect_dwells bit-identical with RAYON_NUM_THREADS=1 and 2",
         test_dwell.test_bit_identical_with_one_and_two_rayon_threads, 1),
        ("fit_static_batch bit-identical with RAYON_NUM_THREADS=1 and 2",
         lambda: _with_tmp(test_static.test_batch_is_bit_identical_with_one_and_two_rayon_threads),
         1),
        ("demodulate bit-identical with RAYON_NUM_THREADS=1 and 2",
         tcg.test_demodulate_bit_identical_with_one_and_two_rayon_threads, 1),
    ]
    runs = []
    for name, f, n in subs:
        c = collections.Counter()
        notes = []
        for _ in range(n):
            try:
                f()
                c["ok"] += 1
            except subprocess.TimeoutExpired as e:
                c["hang"] += 1
                notes.append(f"timed out after {e.timeout} s")
            except (AssertionError, subprocess.CalledProcessError) as e:
                c["fail"] += 1
                notes.append(str(e)[:300])
        runs.append({"what": name, "tried": n, "counts": c, "notes": notes})
    return {"rows": rows, "runs": runs}


def _with_tmp(f: Callable[[Path], None]) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        f(Path(tmp))


# ---- 5. output paths and interruptions --------------------------------------------------------
FILE_GROUPS = [
    ("regular file replaced atomically, mode kept, temp removed on error", "regular_file"),
    ("/dev/null (character device) written through, not replaced", "dev_null"),
    ("FIFO written through", "fifo"),
    ("symlink (and dangling symlink) refused, both ends untouched", "symlink"),
    ("stale temp files of dead processes cleaned", "stale_temps"),
    ("SIGTERM / SIGHUP / SIGINT during a long write: temp removed, old file kept",
     "signal_during"),
    ("nohup (SIGHUP ignored) keeps writing", "nohup"),
    ("CLI -o /dev/null and -o symlink", "cli_output"),
]


def output_files() -> dict[str, Any]:
    """Category 5: the cases of tests/test_files.py, collected and run under pytest."""
    py = sys.executable
    col = subprocess.run([py, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
                          "tests/test_files.py"], capture_output=True, text=True, cwd=ROOT,
                         timeout=300)
    ids = [ln.strip() for ln in col.stdout.splitlines() if "::" in ln]
    with tempfile.TemporaryDirectory() as tmp:
        xml = Path(tmp) / "r.xml"
        t0 = time.monotonic()
        run = subprocess.run([py, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                              f"--junitxml={xml}", "tests/test_files.py"], capture_output=True,
                             text=True, cwd=ROOT, timeout=900)
        elapsed = time.monotonic() - t0
        status: dict[str, str] = {}
        if xml.exists():
            for case in ET.parse(xml).iter("testcase"):
                kids = {k.tag for k in case}
                st = "failed" if kids & {"failure", "error"} else \
                    "skipped" if "skipped" in kids else "passed"
                status[case.get("name", "")] = st
    rows = []
    for title, key in FILE_GROUPS:
        names = [i.split("::", 1)[1] for i in ids if key in i]
        rows.append({"what": title, "cases": len(names),
                     "passed": sum(status.get(n) == "passed" for n in names),
                     "failed": sum(status.get(n) == "failed" for n in names),
                     "skipped": sum(status.get(n) == "skipped" for n in names)})
    other = [i for i in ids if not any(k in i for _, k in FILE_GROUPS)]
    if other:
        rows.append({"what": "other cases", "cases": len(other),
                     "passed": sum(status.get(i.split("::", 1)[1]) == "passed" for i in other),
                     "failed": sum(status.get(i.split("::", 1)[1]) == "failed" for i in other),
                     "skipped": sum(status.get(i.split("::", 1)[1]) == "skipped"
                                    for i in other)})
    summary = run.stdout.strip().splitlines()[-1] if run.stdout.strip() else run.stderr[-300:]
    return {"collected": len(ids), "rows": rows, "summary": summary, "rc": run.returncode,
            "seconds": elapsed}


# ---- 6. Monte Carlo figures (quoted) ----------------------------------------------------------
def _table_after(text: str, heading: str) -> list[str]:
    """The first markdown table after ``heading`` in ``text``."""
    i = text.find(heading)
    if i < 0:
        return []
    out: list[str] = []
    for line in text[i:].splitlines()[1:]:
        if line.startswith("|"):
            out.append(line)
        elif out:
            break
    return out


def monte_carlo() -> dict[str, Any]:
    static = (DOCS / "reliability-static.md").read_text()
    centri = (DOCS / "centrifuge-reproduction.md").read_text()
    return {"static": _table_after(static, "# Static fit: Monte Carlo reliability"),
            "centrifuge": _table_after(centri, "## False exclusions of the outlier screen")}


# ---- report -----------------------------------------------------------------------------------
def _n(c: collections.Counter[str], *keys: str) -> int:
    return sum(c.get(k, 0) for k in keys)


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def render(res: dict[str, Any], args: argparse.Namespace, seconds: float) -> str:
    import accelcal as ac

    L: list[str] = []
    now = dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    cmd = ".venv/bin/python benches/reliability.py" + (" --quick" if args.quick else "")
    L += ["# Reliability: what bad, corrupted, chunked, concurrent and interrupted input gives",
          "",
          f"Generated by `benches/reliability.py` ({'quick' if args.quick else 'default'} run, "
          f"{now}, {seconds:.0f} s). Regenerate with `{cmd}` from the repository root "
          "(`--quick` for a CI-sized run). The cases are the test suite's own (tests/), run at a "
          "fixed size with every outcome counted instead of stopping at the first failure.",
          "",
          f"Machine: {platform.system()} {platform.machine()} ({_cpu()}), {os.cpu_count()} cores "
          "shared "
          f"with other jobs (load average {res['load']:.1f} at start), Python "
          f"{platform.python_version()}, accelcal {getattr(ac, '__version__', '?')}.",
          "",
          "Targets: silent wrong answers 0, panics 0, hangs 0, other exception types 0.", ""]

    # 1
    b = res["bad"]
    tot: collections.Counter[str] = collections.Counter()
    L += ["## 1. Bad input over the public API", "",
          f"Hypothesis, {args.examples} examples per test (a fixed seed per test, the CRC-32 of "
          "its name: the same cases every run), then fixed probes (cases an earlier, "
          "differently seeded run drew): any array (random shape, "
          "dtype incl. bool/complex/datetime/big-endian, layout C/F/strided/reversed/list/"
          "DataFrame, content NaN/inf/huge/constant/empty) or any value of a numeric option "
          "(NaN, inf, None, text, 2^70, complex, lists). Sources: "
          "`tests/test_properties.py` and the `*_any_array` tests of "
          "`tests/test_centrifuge_gradiometer_inputs.py`; the tests' `_check` / `_clear` helper "
          "classifies each call. *Clean error*: CalibrationError / DegenerateDataError naming "
          "the argument; *unnamed*: our error not naming it; *silent wrong*: a result with NaN "
          "(or out of range) and no status; *other*: another exception type; *panic*: pyo3 "
          "PanicException.", "",
          "| function (test) | cases | results | clean errors | unnamed errors | silent wrong "
          "| other exceptions | panics | hangs |",
          "|---|---|---|---|---|---|---|---|---|"]
    for label in sorted(b["counts"]):
        c = b["counts"][label]
        tot.update(c)
        L.append(f"| `{label}` | {sum(c.values())} | " + " | ".join(
            str(c.get(k, 0)) for k in OUTCOMES) + " |")
    L.append(f"| **total** | **{sum(tot.values())}** | " + " | ".join(
        f"**{tot.get(k, 0)}**" for k in OUTCOMES) + " |")
    L.append("")
    bad1 = _n(tot, "unnamed", "silent", "other", "panic", "hang")
    if bad1:
        L += [f"Not 0: {bad1} case(s). The first ones:", ""]
        L += [f"- {x}" for x in b["bad"][:12]]
    else:
        L.append("Every case gave a valid result or a clean error naming the argument.")
    L.append("")

    # 2
    L += ["## 2. Calibration files", "",
          "`TriadModel.load` on mutated copies of a valid file (a 20-dwell fit saved with "
          "`TriadModel.save`). *Clean error*: one CalibrationError, on one line, naming the file "
          "and the changed field; *names another field*: our error, naming a field the changed "
          "one must agree with instead. *Accepted*: loads with K, bias, g and the three "
          "covariances unchanged (a derived field such as `vector` dropped, an optional field "
          "absent, a descriptive field such as `sensor_id` changed). *Silent wrong*: loads with "
          "one of those numbers changed.",
          "",
          "| mutations | tried | clean errors | error names another field | accepted "
          "| silent wrong | other exceptions | panics |",
          "|---|---|---|---|---|---|---|---|"]
    for title, r in res["files"].items():
        c = r["counts"]
        L.append(f"| {title} | {r['tried']} | {c.get('clean', 0)} | {c.get('unnamed', 0)} | "
                 f"{c.get('harmless', 0)} | {c.get('silent', 0)} | {c.get('other', 0)} | "
                 f"{c.get('panic', 0)} |")
    L.append("")
    groups: dict[str, set[str]] = {}
    for r in res["files"].values():
        for n in r["notes"]:
            hit = re.match(r"\[[^]]*\] (.*): accepted \((.*)\)$", n)
            if hit:
                groups.setdefault(hit.group(2), set()).add(hit.group(1))
    if groups:
        L += ["Accepted: " + "; ".join(f"{why}: {', '.join(sorted(names))}"
                                      for why, names in sorted(groups.items())) + ".", ""]
    bad2 = [n for r in res["files"].values() for n in r["notes"] if ": accepted" not in n]
    if bad2:
        L += [f"Not 0: {len(bad2)} case(s):", ""] + [f"- {n}" for n in bad2[:12]] + [""]
        if any("SILENTLY with covariance_" in n for n in bad2):
            L += ["The covariance that is not the realistic one is checked for shape, symmetry "
                  "and finiteness but not against the realistic one, although the file holds "
                  "what relates them (`covariance_scaled` = `metadata.chi2_dof` x "
                  "`covariance_noise_model` when sigma was given; the two are equal when the "
                  "noise was estimated).", ""]

    # 3
    s = res["stream"]
    L += ["## 3. Streaming", "",
          "`DwellAccumulator` pushed in random chunks (cuts at and next to every dwell boundary, "
          "anywhere, and runs of up to 300 one-sample chunks; `tests/test_dwell.py`'s "
          "`chunkings` and `_check_stream`) must give exactly the one-shot `detect_dwells` "
          "(detection mode) and `dwell_stats` (given bounds): both compared per chunking.", "",
          "| stream | samples | chunkings tried | chunks per chunking | identical | different "
          "| other exceptions |", "|---|---|---|---|---|---|---|"]
    for r in s["rows"]:
        c = r["counts"]
        ch = f"{r['chunks'][0]}-{r['chunks'][1]}" if r["chunks"] else "-"
        L.append(f"| {r['stream']} | {r['samples']} | {r['tried']} | {ch} | "
                 f"{c.get('identical', 0)} | {c.get('different', 0)} | {c.get('other', 0)} |")
    L.append("")
    if s["skipped"]:
        L += [s["skipped"] + ".", ""]
    for r in s["rows"]:
        for n in r["notes"][:3]:
            L.append(f"- Not identical ({r['stream']}): {n}")

    # 4
    t = res["threads"]
    L += ["## 4. Threads", "",
          "Each entry point called from 4 Python threads at once (a thread pool), every result "
          "compared bit for bit with a single-threaded call.", "",
          "| entry point | calls | identical | different |", "|---|---|---|---|"]
    for r in t["rows"]:
        c = r["counts"]
        L.append(f"| `{r['what']}` | {r['tried']} | {c.get('identical', 0)} | "
                 f"{c.get('different', 0)} |")
    L += ["", "| subprocess check | runs | passed | failed | hangs |", "|---|---|---|---|---|"]
    for r in t["runs"]:
        c = r["counts"]
        L.append(f"| {r['what']} | {r['tried']} | {c.get('ok', 0)} | {c.get('fail', 0)} | "
                 f"{c.get('hang', 0)} |")
    L.append("")
    for r in t["rows"] + t["runs"]:
        for n in r["notes"][:3]:
            L.append(f"- Not 0 ({r['what']}): {n}")

    # 5
    f = res["out"]
    L += ["## 5. Output paths and interruptions", "",
          f"The cases of `tests/test_files.py` ({f['collected']} collected with `pytest "
          f"--collect-only -q tests/test_files.py`), run with pytest: `{f['summary']}` "
          f"({f['seconds']:.0f} s).", "",
          "| case | cases | passed | failed | skipped |", "|---|---|---|---|---|"]
    for r in f["rows"]:
        L.append(f"| {r['what']} | {r['cases']} | {r['passed']} | {r['failed']} | "
                 f"{r['skipped']} |")
    L.append("")

    # 6
    m = res["mc"]
    L += ["## 6. Monte Carlo: maximum likelihood and error rates", "",
          "Quoted, not re-run here (they take tens of minutes). Static fit: from "
          "`docs/reliability-static.md`, generated by `benches/reproduce_static.py` "
          "(section 2 of `docs/static-reproduction.md`).", ""]
    L += m["static"] or ["(table not found in docs/reliability-static.md)"]
    L += ["", "Centrifuge outlier screen, false exclusions on clean sessions: from "
          "`docs/centrifuge-reproduction.md` (section \"False exclusions of the outlier screen "
          "on clean sessions\"), generated by `benches/validate_centrifuge_screen.py` (3000 "
          "clean sessions per row, the paper's 20 positions x 3 speeds, noise 1e-05 g, seeds "
          "0..2999). The default screen is outlier_k = 5.", ""]
    L += m["centrifuge"] or ["(table not found in docs/centrifuge-reproduction.md)"]
    L.append("")
    return "\n".join(L)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="CI-sized run (about a minute)")
    ap.add_argument("--examples", type=int, default=None,
                    help="hypothesis examples per property test (default 500, --quick 50)")
    ap.add_argument("--out", default=str(DOCS / "reliability.md"))
    ap.add_argument("--worker", choices=sorted(PROPERTY_MODULES), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.examples is None:
        args.examples = 50 if args.quick else 500
    if args.worker:
        _property_worker(args.worker, args.examples)
        return
    from accelcal._files import atomic_write

    t0 = time.monotonic()
    res: dict[str, Any] = {"load": os.getloadavg()[0]}
    steps: list[tuple[str, str, Callable[[], Any]]] = [
        ("bad", "1 bad input", lambda: bad_input(args.examples, 120 if args.quick else 600)),
        ("files", "2 calibration files", calibration_files),
        ("stream", "3 streaming", lambda: streaming(20 if args.quick else 1000,
                                                    3 if args.quick else 200)),
        ("threads", "4 threads", lambda: threads(8 if args.quick else 64,
                                                 1 if args.quick else 3)),
        ("out", "5 output files", output_files),
        ("mc", "6 Monte Carlo", monte_carlo),
    ]
    for key, title, f in steps:
        t1 = time.monotonic()
        res[key] = f()
        print(f"{title}: {time.monotonic() - t1:.1f} s", flush=True)
    seconds = time.monotonic() - t0
    text = render(res, args, seconds)
    atomic_write(args.out, text)
    print(f"wrote {args.out} ({seconds:.0f} s)")
    bad = re.findall(r"^(?:Not 0|- ).*$", text, flags=re.M)
    for line in bad:
        print(line)


if __name__ == "__main__":
    main()
