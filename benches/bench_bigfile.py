"""Big recordings: accelcal's text reader and streaming commands against pandas.read_csv.

Generates a factory-style recording (5 kHz, static dwells in random attitudes joined by
smooth turns, columns ``t,ax,ay,az`` in s and m/s^2; 2e7 rows is about 0.9 GB), then in one
run:

* times ``pandas.read_csv(engine="c")``, ``accelcal.io.read_stream`` and the streaming dwell
  pass (``accelcal.io.stream_dwells``) in this process, best of ``--repeat`` runs each;
* runs ``calibrate static``, ``dwells``, ``diagnose`` (Allan and white noise models) and
  ``apply`` (csv and npy output) as
  child processes and reports each one's wall time and peak resident memory (``os.wait4``),
  plus pandas.read_csv in a child for its memory.

Targets (issue "large recordings"): read_stream and the dwell pass >= 2x faster than
pandas.read_csv; calibrate static end to end <= pandas.read_csv alone; peak RSS of
calibrate static / dwells / diagnose / apply <= 300 MB.

    python benches/bench_bigfile.py                 # 2e7 rows
    python benches/bench_bigfile.py --rows 1000000  # a quick check

Not a test: timings depend on the machine and its load (report both with the table). The
end-to-end target is for the big file: at 1e6 rows Python's start-up (about 0.4 s) dominates
every command.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

FS = 5000.0
G = 9.80665


def generate(path: Path, rows: int, seed: int = 0) -> None:
    """Dwells (20 s) in random attitudes, turns (5 s) between them, white noise 3 mm/s^2,
    a mildly distorted triad (scale, bias, misalignment); values to 1e-6 m/s^2."""
    from accelcal import _core

    rng = np.random.default_rng(seed)
    # 20 s dwells and 5 s turns (160 attitudes at 2e7 rows); shorter for small files, so that
    # a quick run still has about 24 attitudes to calibrate from.
    period_s = min(25.0, rows / FS / 24)
    dwell, turn = int(0.8 * period_s * FS), int(0.2 * period_s * FS)
    period = dwell + turn
    n_att = rows // period + 2
    u = rng.normal(size=(n_att, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    K = np.array([[1.002, 0.0, 0.0], [0.001, 0.997, 0.0], [-0.002, 0.0015, 1.004]])
    b = np.array([0.05, -0.03, 0.08])
    step = 1_000_000
    with open(path, "wb") as f:
        f.write(b"t,ax,ay,az\n")
        for a in range(0, rows, step):
            i = np.arange(a, min(a + step, rows))
            k, j = np.divmod(i, period)
            w = np.clip((j - dwell) / turn, 0.0, 1.0)[:, None]
            w = 0.5 - 0.5 * np.cos(np.pi * w)  # smooth turn from attitude k to k + 1
            g = (1 - w) * u[k] + w * u[k + 1]
            g *= G / np.linalg.norm(g, axis=1, keepdims=True)
            x = g @ K.T + b + rng.normal(0.0, 3e-3, (i.size, 3))
            t = np.round(i / FS, 4)
            f.write(_core.format_rows(np.round(x, 6), t))


#: Prepended to every child: report the peak resident memory of the child's own image at
#: exit (``VmHWM``; ``ru_maxrss`` would include this big parent's memory copied at fork).
_HWM = (
    "import atexit, os\n"
    "def _hwm():\n"
    "    for ln in open('/proc/self/status'):\n"
    "        if ln.startswith('VmHWM'):\n"
    "            os.write(2, ('\\nVmHWM_kB ' + ln.split()[1] + '\\n').encode())\n"
    "atexit.register(_hwm)\n"
)


def rss_child(code: str, args: list[str]) -> tuple[float, float, int, str]:
    """Run ``code`` in a child Python with ``sys.argv[1:] = args``; (wall s, peak RSS MB,
    exit code, stderr tail)."""
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", _HWM + code, *args], stdout=subprocess.DEVNULL,
                       stderr=subprocess.PIPE, check=False)
    dt = time.perf_counter() - t0
    err = p.stderr.decode(errors="replace")
    hwm = [ln.split()[1] for ln in err.splitlines() if ln.startswith("VmHWM_kB ")]
    mb = float(hwm[-1]) / 1024.0 if hwm else float("nan")
    return dt, mb, p.returncode, err[-400:]


def best(fn: Any, repeat: int) -> tuple[float, Any]:
    out = None
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", type=float, default=2e7, help="rows of the generated file")
    ap.add_argument("--repeat", type=int, default=2, help="in-process runs of each reader")
    ap.add_argument("--dir", default=None, help="folder for the files (default: a temp dir)")
    ap.add_argument("--json", default=None, help="also write the results as JSON here")
    ns = ap.parse_args()
    rows = int(ns.rows)
    import accelcal
    import pandas as pd
    from accelcal.io import read_stream, stream_dwells

    tmp = tempfile.TemporaryDirectory(dir=ns.dir)
    folder = Path(tmp.name)
    path = folder / "big.csv"
    t0 = time.perf_counter()
    generate(path, rows)
    size = path.stat().st_size
    print(f"generated {rows:.3g} rows, {size / 1e9:.3f} GB in {time.perf_counter() - t0:.1f} s",
          file=sys.stderr)
    load = os.getloadavg()
    res: dict[str, Any] = {
        "rows": rows, "bytes": size, "cpus": os.cpu_count(), "loadavg_start": load,
        "accelcal": getattr(accelcal, "__version__", "?"), "pandas": pd.__version__,
    }
    t_pd, df = best(lambda: pd.read_csv(path, engine="c"), ns.repeat)
    ref = df[["ax", "ay", "az"]].to_numpy()
    del df
    t_rs, st = best(lambda: read_stream(path), ns.repeat)
    assert np.array_equal(st.samples, ref), "read_stream differs from pandas.read_csv"
    del st, ref
    t_dw, d = best(lambda: stream_dwells(path), ns.repeat)
    res.update(pandas_s=t_pd, read_stream_s=t_rs, stream_dwells_s=t_dw, n_dwells=len(d))
    cli = "import sys; from accelcal.cli import main; main(sys.argv[1:])"
    cal = folder / "cal.json"
    children = {
        "pandas.read_csv (child, for memory)": (
            "import sys, pandas; pandas.read_csv(sys.argv[1], engine='c')", [str(path)]),
        "calibrate static": (cli, ["calibrate", "static", str(path), "--g", str(G), "--quiet",
                                   "-o", str(cal)]),
        "dwells": (cli, ["dwells", str(path), "--quiet"]),
        "diagnose": (cli, ["diagnose", str(path), "--g", str(G), "--quiet"]),
        "diagnose --noise white": (cli, ["diagnose", str(path), "--g", str(G), "--quiet",
                                         "--noise", "white"]),
        "apply -o csv": (cli, ["apply", str(cal), str(path), "-o", str(folder / "out.csv"),
                               "--quiet"]),
        "apply -o npy": (cli, ["apply", str(cal), str(path), "-o", str(folder / "out.npy"),
                               "--quiet"]),
    }
    res["children"] = {}
    for name, (code_, args) in children.items():
        dt, mb, code, err = rss_child(code_, args)
        res["children"][name] = {"s": dt, "peak_rss_mb": mb, "exit": code}
        if code != 0:
            print(f"{name}: exit {code}: {err}", file=sys.stderr)
    res["loadavg_end"] = os.getloadavg()
    tmp.cleanup()

    def line(name: str, s: float, mb: float | None, target: str, ok: bool | None) -> str:
        ratio = t_pd / s
        mem = "" if mb is None else f"{mb:.0f}"
        verdict = "" if ok is None else ("yes" if ok else "NO")
        return f"| {name} | {s:.2f} | {ratio:.2f}x | {mem} | {target} | {verdict} |"

    ch = res["children"]
    out = [
        f"{rows:.3g} rows, {size / 1e9:.2f} GB; {os.cpu_count()} cores; load average "
        f"{load[0]:.1f} at the start, {res['loadavg_end'][0]:.1f} at the end",
        "",
        "| step | time s | speed vs pandas | peak RSS MB | target | met |",
        "|---|---|---|---|---|---|",
        line("pandas.read_csv(engine='c')", t_pd, ch["pandas.read_csv (child, for memory)"]
             ["peak_rss_mb"], "baseline", None),
        line("accelcal.io.read_stream", t_rs, None, ">= 2x pandas", t_pd / t_rs >= 2),
        line("streaming dwell pass (stream_dwells)", t_dw, None, ">= 2x pandas",
             t_pd / t_dw >= 2),
    ]
    for name in ("calibrate static", "dwells", "diagnose", "diagnose --noise white",
                 "apply -o csv", "apply -o npy"):
        c = ch[name]
        ok = c["peak_rss_mb"] <= 300 and c["exit"] == 0
        target = "<= 300 MB"
        if name == "calibrate static":
            target = "<= pandas time, <= 300 MB"
            ok = ok and c["s"] <= t_pd
        out.append(line(f"accelcal {name}", c["s"], c["peak_rss_mb"], target, ok))
    print("\n".join(out))
    if ns.json:
        Path(ns.json).write_text(json.dumps(res, indent=2) + "\n")


if __name__ == "__main__":
    main()
