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


def gap_figure(rep: Any, fig: Any = None) -> Any:
    """The gap of a :class:`accelcal.GapReport`: residuals (sigma units) before and after
    against time, temperature and pose (static), or by row (centrifuge, gradiometer)."""
    plt = _plt()
    d = rep.dwells
    if rep.system != "static":
        if fig is None:
            fig = plt.figure(figsize=(7, 3.4))
        ax = fig.subplots(1, 1)
        x = np.arange(len(d["e"]))
        ax.plot(x, d["e"], "o", ms=4, label="baseline")
        ax.plot(x, d["e_after"], "x", ms=5, label=f"+ {', '.join(rep.selected) or 'none'}")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel("row")
        ax.set_ylabel("residual / sigma")
        ax.legend(fontsize=8)
        fig.suptitle(f"{rep.system} gap: chi2/dof {rep.chi2_per_dof:.2f}; best = {rep.best}")
        fig.tight_layout()
        return fig
    if fig is None:
        fig = plt.figure(figsize=(11, 3.4))
    axs = fig.subplots(1, 3, sharey=True)
    has_t = d["t"] is not None
    t = d["t"] if has_t else np.arange(rep.n, dtype=float)
    xs: list[tuple[Any, str]] = [(t / 60.0 if has_t else t, "time, min" if has_t else "dwell")]
    xs.append((d["temperature"], "temperature") if d["temperature"] is not None else (None, ""))
    xs.append((d["pose_angle_deg"], "angle of the z axis from vertical, deg"))
    for axis, (x, lab) in zip(axs, xs, strict=True):
        if x is None:
            axis.text(0.5, 0.5, "no temperature recorded", ha="center", transform=axis.transAxes)
            axis.set_axis_off()
            continue
        axis.plot(x, d["e"], "o", ms=4, label="baseline")
        axis.plot(x, d["e_after"], "x", ms=5, label=f"+ {', '.join(rep.selected) or 'none'}")
        axis.axhline(0, color="k", lw=0.5)
        axis.set_xlabel(lab)
    axs[0].set_ylabel("norm residual / sigma")
    axs[0].legend(fontsize=8)
    fig.suptitle(f"gap: chi2/dof {rep.chi2_per_dof:.2f}, held-out G {rep.held_out_gap:.2f} -> "
                 f"{rep.held_out_gap_after:.2f}; best = {rep.best}")
    fig.tight_layout()
    return fig
