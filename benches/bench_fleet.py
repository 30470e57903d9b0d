"""Fleet calibration throughput: recordings per second, and the scaling from 1 to 2 workers.

Workload: ``accelcal.sim.fleet.fleet_recordings`` writes N text recordings (default 2 000 as a
script, 200 under ``make bench``; 24 dwells of 3 s at 50 Hz with 1 s moves, about 4 750 rows
and 190 kB each, a random calibration per sensor), 2 % of them corrupted in the four ways the
simulator knows (truncated mid-line, NaN rows, a row with an extra field, too few poses).

Four ways over the same files, in one process:

- ``loop``: the baseline a user writes: a plain Python loop of ``read_stream``,
  ``detect_dwells`` and ``fit_static`` with try/except, in this process;
- ``pool``: ``calibrate_many(paths, g=...)`` on the local process pool (all cores, one rayon
  thread per worker; the pool's start-up is included);
- ``dask-1``, ``dask-2``: ``calibrate_many(paths, g=..., client=...)`` on a Dask
  ``LocalCluster(processes=True, threads_per_worker=1)`` with 1 and 2 worker processes
  (cluster start-up and the workers' first import excluded).

Each run must report every corrupted file (status not ok; for NaN rows, which are dropouts
left out of the dwell statistics, status ok with a note) and lose none (one row per path).
The script prints recordings/s, CPU time per recording, the cores used (CPU time of this
process, the pool's workers and the Dask workers over the wall time: about 1 or 2 on an idle
machine, less when other jobs take the cores), the 1 -> 2 worker scaling of the pool and of
Dask (target >= 1.8x) and the machine load before and after.
``python benches/bench_fleet.py --n 2000`` for the full run, ``--n 200`` for a quick check.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import accelcal as ac
import numpy as np
import pytest
from accelcal.sim.fleet import FleetRecording, fleet_recordings
from accelcal.sim.static import G0

N_BENCH = int(os.environ.get("ACCELCAL_BENCH_FLEET_N", "200"))
_RESULTS: dict[str, tuple[float, float]] = {}


def make_fleet(folder: Path, n: int, seed: int = 0) -> list[FleetRecording]:
    return fleet_recordings(folder, n, corrupt=0.02, seed=seed)


def plain_loop(paths: list[str]) -> list[str]:
    """The baseline: one recording after another in this process."""
    status = []
    for p in paths:
        try:
            st = ac.io.read_stream(p)
            d = ac.detect_dwells(st.samples, st.fs, t=st.t)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ac.WeakDesignWarning)
                ac.fit_static(d, G0)
            status.append("ok")
        except ac.CalibrationError:
            status.append("error")
    return status


# Corruptions that still give a calibration: dropout rows are left out, with a note.
CALIBRATED = {"nan_rows"}


def _missed(recs: list[FleetRecording], status: list[str]) -> int:
    """Corrupted recordings the plain loop calibrated without complaint (dropouts aside)."""
    return sum(bool(r.corruption) and r.corruption not in CALIBRATED and s == "ok"
               for r, s in zip(recs, status, strict=True))


def check(recs: list[FleetRecording], df: Any) -> None:
    """Every corrupted file reported, none lost, every good one (and every one with dropout
    rows) calibrated."""
    assert list(df["path"]) == [r.path for r in recs], "rows lost or out of order"
    bad = {r.path for r in recs if r.corruption}
    reported = set(df.loc[(df["status"] != "ok") | (df["message"] != ""), "path"])
    assert reported == bad, (sorted(bad - reported), sorted(reported - bad))
    assert (df.loc[df["status"] != "ok", "message"] != "").all()
    ok = set(df.loc[df["status"] == "ok", "path"])
    assert {r.path for r in recs if r.corruption in CALIBRATED} <= ok


def _cpu_s() -> float:
    """CPU seconds of this process and of its reaped children (the pool's workers)."""
    a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


def _worker_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _timed(fn: Callable[[], Any], client: Any = None) -> tuple[float, float, Any]:
    """Wall time, CPU time (here, the pool's workers and the Dask workers) and the result."""
    w0 = sum(client.run(_worker_cpu_s).values()) if client is not None else 0.0
    c0, t0 = _cpu_s(), time.perf_counter()
    out = fn()
    wall = time.perf_counter() - t0
    cpu = _cpu_s() - c0
    if client is not None:
        cpu += sum(client.run(_worker_cpu_s).values()) - w0
    return wall, cpu, out


def _cluster(n_workers: int) -> Any:
    import distributed

    cluster = distributed.LocalCluster(n_workers=n_workers, threads_per_worker=1,
                                       processes=True, dashboard_address=":0")
    client = distributed.Client(cluster)
    client.run(lambda: __import__("accelcal.fleet"))  # workers' first import, not timed
    return cluster, client


def run_all(recs: list[FleetRecording], *, loop: bool = True) -> dict[str, tuple[float, float]]:
    """recordings/s and CPU seconds per recording of each method."""
    paths = [r.path for r in recs]
    n = len(paths)
    out: dict[str, tuple[float, float]] = {}
    if loop:
        dt, cpu, st = _timed(lambda: plain_loop(paths))
        out["loop"] = (n / dt, cpu / n)
        out["loop-missed"] = (float(_missed(recs, st)), 0.0)
    dt, cpu, df = _timed(lambda: ac.calibrate_many(paths, g=G0, workers=1, progress=False))
    check(recs, df)
    out["pool-1"] = (n / dt, cpu / n)
    dt, cpu, df = _timed(lambda: ac.calibrate_many(paths, g=G0, progress=False))
    check(recs, df)
    out["pool"] = (n / dt, cpu / n)
    for w in (1, 2):
        cluster, client = _cluster(w)
        try:
            dt, cpu, df = _timed(lambda c=client: ac.calibrate_many(paths, g=G0, client=c,
                                                                    progress=False), client)
        finally:
            client.close()
            cluster.close()
        check(recs, df)
        assert df["worker"].nunique() == w
        out[f"dask-{w}"] = (n / dt, cpu / n)
    return out


def table(res: dict[str, tuple[float, float]], n: int, loads: tuple[Any, Any]) -> str:
    lines = [
        f"fleet of {n} recordings, {os.cpu_count()} cores; load average before "
        f"{loads[0][0]:.2f} {loads[0][1]:.2f} {loads[0][2]:.2f}, after {loads[1][0]:.2f} "
        f"{loads[1][1]:.2f} {loads[1][2]:.2f}",
        "| method | recordings/s | CPU ms per recording | cores used (CPU / wall) |",
        "|---|---:|---:|---:|",
    ]
    names = {
        "loop": "plain loop (read_stream, detect_dwells, fit_static)",
        "pool-1": "calibrate_many, workers=1 (in process)",
        "pool": f"calibrate_many, local pool ({os.cpu_count()} processes)",
        "dask-1": "calibrate_many on Dask, 1 worker",
        "dask-2": "calibrate_many on Dask, 2 workers",
    }
    for k, (rate, cpu) in res.items():
        if k == "loop-missed":
            continue
        cpu_txt = f"{cpu * 1e3:.1f}" if cpu > 0 else "-"
        used = f"{rate * cpu:.2f}" if cpu > 0 else "-"
        lines.append(f"| {names[k]} | {rate:.1f} | {cpu_txt} | {used} |")
    r = {k: v[0] for k, v in res.items()}
    if "loop-missed" in r:
        lines.append(f"the plain loop calibrated {int(r['loop-missed'])} corrupted recordings "
                     "without complaint (calibrate_many reported all of them)")
    if {"dask-1", "dask-2"} <= r.keys():
        lines.append(f"Dask scaling 1 -> 2 workers: {r['dask-2'] / r['dask-1']:.2f}x "
                     "(target >= 1.8x)")
    if {"pool-1", "pool"} <= r.keys():
        lines.append(f"local scaling 1 -> {os.cpu_count()} processes: "
                     f"{r['pool'] / r['pool-1']:.2f}x")
    if {"loop", "pool"} <= r.keys():
        lines.append(f"local pool vs plain loop: {r['pool'] / r['loop']:.2f}x")
    return "\n".join(lines)


# ---- pytest-benchmark (make bench): one timed round per method -------------------------------
@pytest.fixture(scope="module")
def fleet() -> Iterator[list[FleetRecording]]:
    d = Path(tempfile.mkdtemp(prefix="accelcal-bench-fleet-"))
    try:
        yield make_fleet(d, N_BENCH)
    finally:
        shutil.rmtree(d, ignore_errors=True)


@pytest.fixture(scope="module", autouse=True)
def report() -> Iterator[None]:
    l0 = os.getloadavg()
    yield
    if _RESULTS:
        print("\n[bench_fleet] " + table(_RESULTS, N_BENCH, (l0, os.getloadavg())))


def test_plain_loop(benchmark: Any, fleet: list[FleetRecording]) -> None:
    paths = [r.path for r in fleet]
    st = benchmark.pedantic(plain_loop, args=(paths,), rounds=1, iterations=1)
    assert len(st) == len(paths)
    _RESULTS["loop"] = (len(paths) / benchmark.stats.stats.median, 0.0)
    _RESULTS["loop-missed"] = (float(_missed(fleet, st)), 0.0)


@pytest.mark.parametrize("workers", [1, None])
def test_local_pool(benchmark: Any, fleet: list[FleetRecording], workers: int | None) -> None:
    paths = [r.path for r in fleet]
    df = benchmark.pedantic(ac.calibrate_many, args=(paths,),
                            kwargs={"g": G0, "workers": workers, "progress": False},
                            rounds=1, iterations=1)
    check(fleet, df)
    _RESULTS["pool-1" if workers == 1 else "pool"] = (
        len(paths) / benchmark.stats.stats.median, 0.0)


@pytest.mark.parametrize("n_workers", [1, 2])
def test_dask_cluster(benchmark: Any, fleet: list[FleetRecording], n_workers: int) -> None:
    paths = [r.path for r in fleet]
    cluster, client = _cluster(n_workers)
    try:
        df = benchmark.pedantic(ac.calibrate_many, args=(paths,),
                                kwargs={"g": G0, "client": client, "progress": False},
                                rounds=1, iterations=1)
    finally:
        client.close()
        cluster.close()
    check(fleet, df)
    _RESULTS[f"dask-{n_workers}"] = (len(paths) / benchmark.stats.stats.median, 0.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=2000, help="recordings (default 2000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dir", default=None, help="folder for the recordings (default: temp)")
    ap.add_argument("--no-loop", action="store_true", help="skip the plain-loop baseline")
    a = ap.parse_args()
    d = Path(a.dir) if a.dir else Path(tempfile.mkdtemp(prefix="accelcal-bench-fleet-"))
    try:
        t0 = time.perf_counter()
        recs = make_fleet(d, a.n, a.seed)
        size = sum(os.path.getsize(r.path) for r in recs) / 1e6
        bad = sum(bool(r.corruption) for r in recs)
        print(f"wrote {a.n} recordings ({size:.0f} MB, {bad} corrupted) in "
              f"{time.perf_counter() - t0:.0f} s")
        l0 = os.getloadavg()
        res = run_all(recs, loop=not a.no_loop)
        print(table(res, a.n, (l0, os.getloadavg())))
        print(f"every corrupted file reported and none lost in every run ({bad} of {a.n}); "
              f"median recording {np.median([os.path.getsize(r.path) for r in recs]) / 1e3:.0f}"
              " kB")
    finally:
        if not a.dir:
            shutil.rmtree(d, ignore_errors=True)


if __name__ == "__main__":
    main()
