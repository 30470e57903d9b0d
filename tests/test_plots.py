"""Figures: made without pyplot's global state (no backend switched, no figure left open)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from typing import Any

import pytest

pytest.importorskip("matplotlib")


def test_figures_leave_the_users_backend_and_no_open_figure() -> None:
    """A user's backend (svg) was switched to Agg by the first plot, and every figure call
    left a pyplot figure open (ten after five gap and five norm figures): a service that
    plots leaked them. Run in a fresh interpreter, as the backend is process-wide."""
    code = textwrap.dedent("""
        import warnings
        import matplotlib
        matplotlib.use("svg")
        import matplotlib.pyplot as plt
        import accelcal as ac
        from accelcal.plots import static_norm_figure, save_figure
        from accelcal.sim.static import static_dwell_means
        warnings.simplefilter("ignore")
        s = static_dwell_means(24, sigma=1e-3, rng=1)
        fit = ac.fit_static(s.means, s.g_measured)
        rep = ac.diagnose(s.dwellset(), g=s.g_measured)
        for _ in range(5):
            fig, fig2 = rep.plot(), static_norm_figure(fit)
        import io
        buf = io.BytesIO()
        fig.savefig(buf, format="png")
        print(matplotlib.get_backend(), len(plt.get_fignums()), buf.tell() > 10000,
              len(fig.axes) >= 4)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["svg", "0", "True", "True"], out


@pytest.mark.parametrize("fmt", ["svg", "pdf"])
def test_the_same_figure_saved_twice_gives_the_same_bytes(fmt: str, tmp_path: Any,
                                                          monkeypatch: Any) -> None:
    """SVG ids were salted at random and SVG/PDF carried the time of writing (local time,
    no zone): the same --plot written twice differed. Now no date, and a fixed salt."""
    import warnings

    import accelcal as ac
    from accelcal.plots import save_figure
    from accelcal.sim.static import static_dwell_means

    warnings.simplefilter("ignore")
    s = static_dwell_means(24, sigma=1e-3, rng=1)
    fig = ac.diagnose(s.dwellset(), g=s.g_measured).plot()
    a, b = tmp_path / f"a.{fmt}", tmp_path / f"b.{fmt}"
    save_figure(fig, str(a))
    monkeypatch.setenv("TZ", "Asia/Tokyo")  # a date would be written in local time
    import time

    if hasattr(time, "tzset"):
        time.tzset()
    try:
        save_figure(fig, str(b))
    finally:
        monkeypatch.undo()
        if hasattr(time, "tzset"):
            time.tzset()
    data = a.read_bytes()
    assert len(data) > 10_000 and data == b.read_bytes()
    assert b"CreationDate" not in data and b"<dc:date>" not in data
