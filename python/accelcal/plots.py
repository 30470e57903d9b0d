"""Figures people would rather look at (matplotlib, the optional ``plot`` extra)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ._core import CalibrationError
from ._files import atomic_write


def save_figure(fig: Any, path: str) -> None:
    """Save a figure atomically; the format follows the suffix (png, pdf, svg)."""
    import io
    from pathlib import Path

    buf = io.BytesIO()
    suffix = Path(path).suffix.lstrip(".") or "png"
    fig.savefig(buf, format=suffix, dpi=120, bbox_inches="tight")
    atomic_write(path, buf.getvalue())


def _plt() -> Any:
    try:
        import matplotlib

        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover - depends on the install
        raise CalibrationError("plots need matplotlib: pip install 'accelcal[plot]'") from None
    return plt


def static_norm_figure(fit: Any, dwells: Any = None) -> Any:
    """The paper's Fig. 5: |a| per dwell before and after calibration, and the residuals."""
    plt = _plt()
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    k = np.arange(len(fit.residuals))
    ns = fit.norm_stats
    g = fit.g
    if ns["before"] is not None:
        before = np.linalg.norm(fit._means, axis=1) if fit._nominal is None else np.linalg.norm(
            fit._nominal.apply(fit._means), axis=1)
        ax1.plot(k, before / g, "o-", label="before (nominal)")
    ax1.plot(k, (g + fit.residuals) / g, "s-", label="after calibration")
    ax1.axhline(1.0, color="k", lw=0.8)
    ax1.set_ylabel("|a| / g")
    ax1.legend()
    ax1.set_title(f"Norm per dwell ({fit.model} model, {len(k)} dwells)")
    ax2.bar(k, 1e3 * fit.residuals, color="C1")
    if np.all(np.isfinite(fit.sigma_residual)):
        ax2.errorbar(k, 1e3 * fit.residuals, yerr=1e3 * fit.sigma_residual, fmt="none",
                     ecolor="k", capsize=2)
    ax2.set_ylabel("|a| - g  [mm/s^2]")
    ax2.set_xlabel("dwell")
    ax2.set_title(f"residual RMS {fit.rms:.3g} m/s^2, chi2/dof {fit.chi2_dof:.3g}")
    fig.tight_layout()
    return fig


def poses_figure(plan: Any) -> Any:
    """Planned gravity directions on the unit sphere (sensor frame)."""
    plt = _plt()
    fig = plt.figure(figsize=(6, 6))
    ax = fig.add_subplot(111, projection="3d")
    u, v = np.mgrid[0 : 2 * np.pi : 30j, 0 : np.pi : 15j]
    ax.plot_wireframe(np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v), color="0.85",
                      lw=0.5)
    d = np.asarray(plan.directions)
    ax.scatter(d[:, 0], d[:, 1], d[:, 2], color="C3", s=40)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    ax.set_title(f"{len(d)} planned attitudes (gravity direction)")
    return fig


def allan_figure(taus: Any, adev: Any, labels: tuple[str, ...] = ("x", "y", "z")) -> Any:
    """Allan deviation against averaging time, with the white-noise slope for reference."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    a = np.asarray(adev)
    for i in range(a.shape[1] if a.ndim == 2 else 1):
        y = a[:, i] if a.ndim == 2 else a
        ax.loglog(taus, y, "o-", label=labels[i] if a.ndim == 2 else None)
        ax.loglog(taus, y[0] * np.sqrt(taus[0] / np.asarray(taus)), "k:", lw=0.7)
    ax.set_xlabel("tau [s]")
    ax.set_ylabel("Allan deviation")
    ax.legend()
    fig.tight_layout()
    return fig


def dwells_figure(
    t_s: Any, mean: Any, lo: Any, hi: Any, dwells: Any, *, units: str = "", title: str = ""
) -> Any:
    """The stream (x, y, z against time) with the detected dwells shaded and numbered.

    ``t_s`` (m,) bin times in s and ``mean``/``lo``/``hi`` (m, 3) the mean, minimum and
    maximum of each axis over a bin of samples (a decimated picture of a long stream).
    """
    plt = _plt()
    fig, axes = plt.subplots(3, 1, figsize=(10, 6.5), sharex=True)
    unit = units or "as recorded"
    fs = dwells.fs
    starts = None if dwells.start is None or fs is None else np.asarray(dwells.start) / fs
    stops = None if dwells.stop is None or fs is None else np.asarray(dwells.stop) / fs
    for a, ax in enumerate(axes):
        ax.fill_between(t_s, lo[:, a], hi[:, a], color="0.75", lw=0, label="min-max")
        ax.plot(t_s, mean[:, a], color="C0", lw=0.8, label="mean")
        ax.set_ylabel(f"{'xyz'[a]} [{unit}]")
        if starts is not None and stops is not None:
            for k, (s0, s1) in enumerate(zip(starts, stops, strict=True)):
                ax.axvspan(s0, s1, color="C2", alpha=0.25, lw=0,
                           label="dwell" if k == 0 else None)
                if a == 0:
                    ax.text(0.5 * (s0 + s1), 1.0, str(k), transform=ax.get_xaxis_transform(),
                            ha="center", va="bottom", fontsize=7)
    axes[0].legend(loc="upper right", fontsize=8, ncol=3)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"{title + ': ' if title else ''}{len(dwells)} static dwells (shaded)")
    fig.tight_layout()
    return fig
