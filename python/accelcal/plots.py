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


def _flag_limits(axis: Any, thr: float) -> None:
    axis.axhline(0, color="k", lw=0.5)
    for v in (-thr, thr):
        axis.axhline(v, color="C3", lw=0.8, ls="--")


def _residual_panel(axis: Any, x: Any, rep: Any, label: str) -> None:
    """Studentised baseline residuals and whitened residuals after, flagged dwells ringed."""
    d = rep.dwells
    flag = np.asarray(d["flag"], dtype=bool)
    axis.plot(x, d["t_stud"], "o", ms=4, color="C0", label="baseline (studentised)")
    axis.plot(x, d["e_after"], "x", ms=5, color="C1",
              label=f"+ {', '.join(rep.selected) or 'none'}")
    if flag.any():
        axis.plot(np.asarray(x)[flag], np.asarray(d["t_stud"])[flag], "o", ms=10, mfc="none",
                  mec="C3", label="flagged")
    _flag_limits(axis, rep.where["threshold"])
    axis.set_xlabel(label)


def _sphere_panel(fig: Any, spec: Any, rep: Any) -> None:
    """Residual against pose: the gravity direction in the sensor frame on an equal-area
    (Mollweide) map, coloured by the studentised residual; flagged dwells ringed."""
    d = rep.dwells
    u = np.asarray(d["direction"], dtype=np.float64)
    lon = np.arctan2(u[:, 1], u[:, 0])
    lat = np.arcsin(np.clip(u[:, 2], -1.0, 1.0))
    ax = fig.add_subplot(spec, projection="mollweide")
    t = np.asarray(d["t_stud"])
    thr = rep.where["threshold"]
    lim = max(float(np.max(np.abs(t))), thr)
    sc = ax.scatter(lon, lat, c=t, cmap="coolwarm", vmin=-lim, vmax=lim, s=40, edgecolors="k",
                    linewidths=0.3)
    flag = np.asarray(d["flag"], dtype=bool)
    if flag.any():
        ax.scatter(lon[flag], lat[flag], s=160, facecolors="none", edgecolors="C3",
                   linewidths=1.5)
    cb = fig.colorbar(sc, ax=ax, orientation="horizontal", pad=0.08, fraction=0.05)
    for v in (-thr, thr):
        cb.ax.axvline(v, color="C3", lw=1.2, ls="--")
    cb.set_label(f"studentised residual (Bonferroni limit +-{thr:.2f} dashed)")
    ax.set_title("residual against pose (gravity direction, sensor frame)", fontsize=9)
    ax.grid(True, lw=0.3)
    ax.tick_params(labelsize=6)


def _allan_panel(axis: Any, rep: Any) -> None:
    """Allan deviation of the within-dwell samples with the dwell-mean noise of each model."""
    nc = rep.noise_curves
    axes = "xyz"
    if "tau" in nc and "adev" in nc:
        tau, ad = np.asarray(nc["tau"]), np.asarray(nc["adev"])
        for i in range(ad.shape[1]):
            axis.loglog(tau, ad[:, i], "-", color=f"C{i}", lw=1, label=f"ADEV {axes[i]}")
            axis.loglog(tau, ad[0, i] * np.sqrt(tau[0] / tau), ":", color=f"C{i}", lw=0.7)
    L = nc.get("dwell_s")
    if L:
        marks = (("std_used", "s", "noise model used"), ("std_white", "v", "white model"),
                 ("std_allan", "^", "Allan model"), ("std_empirical", "D",
                                                     "half-dwell differences"))
        for key, mk, lab in marks:
            if key in nc:
                v = np.asarray(nc[key])
                for i in range(3):
                    axis.loglog([L], [v[i]], mk, color=f"C{i}", mfc="none" if i else None,
                                ms=7, label=lab if i == 0 else None)
        axis.axvline(L, color="grey", lw=0.5)
    if not axis.lines:
        axis.text(0.5, 0.5, "no within-dwell noise information", ha="center",
                  transform=axis.transAxes)
        axis.set_axis_off()
        return
    axis.set_xlabel("tau, s (dwell length: grey line)")
    axis.set_ylabel("deviation, input units")
    axis.legend(fontsize=6, ncol=2)
    axis.set_title("noise: Allan deviation and dwell-mean noise", fontsize=9)


def gap_figure(rep: Any, fig: Any = None) -> Any:
    """The gap of a :class:`accelcal.GapReport`.

    Static sessions, four panels: residuals (studentised, sigma units) before and after
    against time; against temperature, or - when no temperature was recorded - against pose
    on an equal-area sphere map; against the tilt of the z axis; and the Allan deviation of
    the within-dwell samples with the dwell-mean noise of the model used (white, Allan and
    half-dwell empirical levels at the dwell length). Flagged dwells are ringed and the
    Bonferroni limit dashed. Centrifuge and gradiometer: residuals by row.
    """
    plt = _plt()
    d = rep.dwells
    if rep.system != "static":
        if fig is None:
            fig = plt.figure(figsize=(7, 3.4))
        ax = fig.subplots(1, 1)
        _residual_panel(ax, np.arange(len(d["e"])), rep, "row")
        ax.set_ylabel("residual / sigma")
        ax.legend(fontsize=8)
        fig.suptitle(f"{rep.system} gap: chi2/dof {rep.chi2_per_dof:.2f}; best = {rep.best}; "
                     f"structure: {rep.structure.verdict}")
        fig.tight_layout()
        return fig
    if fig is None:
        fig = plt.figure(figsize=(11, 7.5))
    gs = fig.add_gridspec(2, 2)
    has_t = d["t"] is not None
    t = np.asarray(d["t"]) / 60.0 if has_t else np.arange(rep.n, dtype=float)
    ax0 = fig.add_subplot(gs[0, 0])
    _residual_panel(ax0, t, rep, "time, min" if has_t else "dwell")
    ax0.set_ylabel("norm residual / sigma")
    ax0.legend(fontsize=7)
    if d["temperature"] is not None:
        ax1 = fig.add_subplot(gs[0, 1], sharey=ax0)
        _residual_panel(ax1, d["temperature"], rep, "temperature")
    else:
        _sphere_panel(fig, gs[0, 1], rep)
    ax2 = fig.add_subplot(gs[1, 0], sharey=ax0)
    _residual_panel(ax2, d["pose_angle_deg"], rep, "angle of the z axis from vertical, deg")
    ax2.set_ylabel("norm residual / sigma")
    _allan_panel(fig.add_subplot(gs[1, 1]), rep)
    fig.suptitle(f"gap: chi2/dof {rep.chi2_per_dof:.2f}, held-out G {rep.held_out_gap:.2f} -> "
                 f"{rep.held_out_gap_after:.2f}; best = {rep.best}; structure: "
                 f"{rep.structure.verdict}")
    fig.tight_layout()
    return fig
