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


def centrifuge_residual_figure(fit: Any, speed_index: Any = None, position: Any = None) -> Any:
    """Norm residual of every centrifuge row against position, one series per speed, the
    excluded rows marked (and the screening threshold drawn as a band), in g."""
    plt = _plt()
    r = np.asarray(fit.residuals, dtype=np.float64)
    k = r.size
    pos = np.arange(1, k + 1) if position is None else np.asarray(position)
    spd = np.ones(k, dtype=np.int64) if speed_index is None else np.asarray(speed_index)
    out = np.zeros(k, dtype=bool)
    out[np.asarray(fit.outliers, dtype=np.int64)] = True
    big = np.abs(r[~out]).max() if np.any(~out) else 0.0
    band_g = float(np.nanmax(fit.threshold * np.asarray(fit.residual_std, dtype=np.float64)))
    ref = max(big, band_g if np.isfinite(band_g) else 0.0, 1e-15)
    scale, unit = (1e6, "ug") if ref < 1e-5 else (1e3, "mg") if ref < 1e-2 else (1.0, "g")
    fig, ax = plt.subplots(figsize=(8, 4.5))
    # Excluded rows far beyond the others are drawn at the edge of the axis (clipped).
    lim = 3.0 * scale * ref
    clipped = False
    speeds = np.unique(spd)
    for j, s in enumerate(speeds):
        m = spd == s
        x = pos + 0.12 * (j - (len(speeds) - 1) / 2)  # side by side, one speed each
        ax.plot(x[m & ~out], scale * r[m & ~out], "o", color=f"C{j}", label=f"speed {s}")
        if np.any(m & out):
            v = scale * r[m & out]
            clipped |= bool(np.any(~(np.abs(v) <= lim)))
            ax.plot(x[m & out], np.clip(np.nan_to_num(v, posinf=lim, neginf=-lim), -lim, lim),
                    "x", color=f"C{j}", ms=9, mew=2)
    band = scale * fit.threshold * np.asarray(fit.residual_std, dtype=np.float64)
    if np.all(np.isfinite(band)) and band.size:
        ax.axhspan(-band.max(), band.max(), color="0.9", zorder=0,
                   label="screening threshold")
    if np.any(out):
        ax.plot([], [], "kx", ms=9, mew=2,
                label=f"excluded ({int(out.sum())}{', clipped' if clipped else ''})")
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_xlabel("position")
    ax.set_ylabel(f"norm residual |f| - sqrt(A^2 + 1)  [{unit}]")
    ax.set_title(f"Centrifuge fit ({fit.method}): {k} rows, {int(out.sum())} excluded, "
                 f"rms {fit.residual_rms:.3g}{'' if fit.noise_known else ' g'}")
    if np.issubdtype(pos.dtype, np.integer):
        ax.set_xticks(np.unique(pos))
    ax.legend(fontsize=8, ncol=2)
    fig.tight_layout()
    return fig


def gradiometer_figure(sb: Any) -> Any:
    """Inline and cross averages against azimuth (with their error bars) and the fitted
    ``bias + R(2 theta) gamma`` (at ``t_ref`` when a drift was fitted), in E."""
    plt = _plt()
    az = np.asarray(sb.azimuth_deg, dtype=np.float64)
    y = np.asarray(sb.residuals, dtype=np.float64)
    th = np.radians(az)
    c, s = np.cos(2 * th), np.sin(2 * th)
    b, gm = np.asarray(sb.bias), np.asarray(sb.gradient)
    model = np.column_stack([b[0] + c * gm[0] + s * gm[1], b[1] - s * gm[0] + c * gm[1]])
    drift = np.zeros_like(model)
    if sb.drift is not None and sb.t is not None:
        drift = np.outer(np.asarray(sb.t) - float(sb.t_ref or 0.0), np.asarray(sb.drift))
    data = model + drift + y  # the averages, drift removed to t_ref below
    shown = data - drift
    grid = np.linspace(0.0, 180.0, 361)
    tg = np.radians(grid)
    cg, sg = np.cos(2 * tg), np.sin(2 * tg)
    curves = (b[0] + cg * gm[0] + sg * gm[1], b[1] - sg * gm[0] + cg * gm[1])
    err = None if sb.sigma is None else np.asarray(sb.sigma, dtype=np.float64)
    fig, axes = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    for i, (ax, name) in enumerate(zip(axes, ("inline I", "cross C"), strict=True)):
        ax.errorbar(np.mod(az, 180.0), shown[:, i], yerr=err, fmt="o", capsize=3,
                    label="averages" + (" (drift removed)" if sb.drift is not None else ""))
        ax.plot(grid, curves[i], "-", label="fit: bias + R(2 theta) gamma")
        ax.axhline(b[i], color="k", ls=":", lw=1, label=f"bias {b[i]:.4g} E")
        ax.set_ylabel(f"{name}  [E]")
        ax.legend(fontsize=8)
    axes[1].set_xlabel("platform azimuth  [deg]")
    axes[1].set_xticks(np.arange(0, 181, 45))
    axes[0].set_title(f"Start-up bias from {az.size} azimuths (dof {sb.dof})")
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
