"""Figures people would rather look at (matplotlib, the optional ``plot`` extra)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ._core import CalibrationError
from ._files import atomic_write

#: SVG element ids are hashed with this salt (matplotlib's ``svg.hashsalt``) instead of a
#: random one, so that the same figure gives the same bytes.
SVG_HASHSALT = "accelcal"

#: The metadata entry that dates a file, per format (left out: the same figure gives the
#: same bytes, whenever and in whatever time zone it is saved).
_UNDATED = {"svg": {"Date": None}, "pdf": {"CreationDate": None},
            "eps": {"CreationDate": None}, "ps": {"CreationDate": None}}


def save_figure(fig: Any, path: str) -> None:
    """Save a figure atomically; the format follows the suffix (png, pdf, svg).

    The output is reproducible: the same figure gives the same bytes (PDF and SVG are
    written without a creation date, SVG element ids with a fixed salt)."""
    import io
    from pathlib import Path

    import matplotlib

    buf = io.BytesIO()
    suffix = Path(path).suffix.lstrip(".").lower() or "png"
    kw: dict[str, Any] = {}
    if suffix in _UNDATED:
        kw["metadata"] = dict(_UNDATED[suffix])
    with matplotlib.rc_context({"svg.hashsalt": SVG_HASHSALT}):
        fig.savefig(buf, format=suffix, dpi=120, bbox_inches="tight", **kw)
    atomic_write(path, buf.getvalue())


class _Figures:
    """``subplots`` and ``figure`` as pyplot spells them, making standalone figures
    (``matplotlib.figure.Figure``): no backend is chosen or switched, and no figure is left
    registered with pyplot, so a long-running service that plots does not accumulate them.
    Notebooks still show a returned figure; ``fig.savefig`` or :func:`save_figure` writes it."""

    def __init__(self) -> None:
        try:
            from matplotlib.figure import Figure
        except ImportError:  # pragma: no cover - depends on the install
            raise CalibrationError("plots need matplotlib: pip install 'accelcal[plot]'") from None
        self._figure = Figure

    def figure(self, figsize: tuple[float, float] | None = None) -> Any:
        return self._figure(figsize=figsize)

    def subplots(self, nrows: int = 1, ncols: int = 1, *, figsize: tuple[float, float] | None
                 = None, **kw: Any) -> tuple[Any, Any]:
        fig = self._figure(figsize=figsize)
        return fig, fig.subplots(nrows, ncols, **kw)


def _plt() -> _Figures:
    return _Figures()


def static_norm_figure(fit: Any, dwells: Any = None) -> Any:
    """The norm per dwell before and after calibration (in units of g: raw counts are taken
    through the nominal model, or the fitted bias and one common scale), and the residuals
    ``|a| - g`` with error bars from the noise model the fit reports; integer dwell ticks.
    ``dwells`` is accepted for the caller's convenience (the fit carries its means)."""
    from matplotlib.ticker import MaxNLocator

    from .static import unit_label

    plt = _plt()
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    k = np.arange(len(fit.residuals))  # numbered from 0, as the tables and reports
    g = fit.g
    u = unit_label(g)
    nb = fit.norms_before()
    if nb is not None:
        ax1.plot(k, nb[0] / g, "o-", label=f"before ({nb[1]})")
    ax1.plot(k, (g + fit.residuals) / g, "s-", label="after calibration")
    ax1.axhline(1.0, color="k", lw=0.8)
    ax1.set_ylabel("|a| / g  [g]")
    ax1.legend(fontsize=8)
    ax1.set_title(f"Norm per dwell ({fit.model} model, {len(k)} dwells)")
    scale, unit = (1e3, f"m{u}") if u in ("m/s^2", "g") else (1.0, u)
    ax2.bar(k, scale * fit.residuals, color="C1", label="|a| - g")
    src = "noise model" if fit.noise_known else "noise estimated from the residuals"
    ax2.errorbar(k, scale * fit.residuals, yerr=scale * fit.sigma_residual, fmt="none",
                 ecolor="k", capsize=2, label=f"1 sigma ({src})")
    ax2.axhline(0.0, color="k", lw=0.8)
    ax2.set_ylabel(f"|a| - g  [{unit}]")
    ax2.set_xlabel("dwell (numbered from 0, as in the tables)")
    ax2.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax2.legend(fontsize=8)
    chi = f"chi2/dof {fit.chi2_dof:.3g}" if fit.noise_known else "noise estimated"
    ax2.set_title(f"residual RMS {fit.rms:.3g} {u} ({chi})")
    fig.tight_layout()
    return fig


def _equal_area(d: Any, up: float) -> tuple[Any, Any]:
    """Lambert azimuthal equal-area projection about the ``up`` (+1 or -1) z pole: the radius
    is ``2 sin(theta / 2)`` for the angle theta from that pole (sqrt(2) at the equator)."""
    d = np.asarray(d, dtype=np.float64)
    theta = np.arccos(np.clip(up * d[:, 2], -1.0, 1.0))
    r = 2.0 * np.sin(theta / 2.0)
    phi = np.arctan2(d[:, 1], d[:, 0])
    return r * np.cos(phi), r * np.sin(phi)


def poses_figure(plan: Any) -> Any:
    """The planned poses, numbered in the order of the checklist, as gravity directions in
    the sensor frame (x nose, y left side, z top) on an equal-area projection: one disc for
    the poses with the top up (and one for the top down when the plan uses them)."""
    plt = _plt()
    d = np.asarray(plan.directions, dtype=np.float64)
    lower = d[:, 2] < -1e-9
    panels = [(1.0, "top up (z > 0)")] + ([(-1.0, "top down (z < 0)")] if lower.any() else [])
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 5.5), squeeze=False)
    ring = np.linspace(0, 2 * np.pi, 200)
    for ax, (up, title) in zip(axes[0], panels, strict=True):
        for deg in (30, 60, 90):
            r = 2.0 * np.sin(np.radians(deg) / 2.0)
            ax.plot(r * np.cos(ring), r * np.sin(ring), color="0.8", lw=0.7)
            ax.annotate(f"{deg} deg", (r * 0.71, r * 0.71), color="0.5", fontsize=7)
        sel = ~lower if up > 0 else lower
        idx = np.nonzero(sel)[0]
        x, y = _equal_area(d[idx], up)
        ax.scatter(x, y, color="C3", s=30, zorder=3)
        for i, xi, yi in zip(idx, x, y, strict=True):
            ax.annotate(str(i + 1), (xi, yi), xytext=(4, 4), textcoords="offset points",
                        fontsize=8)
        ax.set_aspect("equal")
        lim = 1.5
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_xlabel("x (nose) component of the gravity direction, equal-area")
        ax.set_ylabel("y (left side) component, equal-area")
        ax.set_title(f"{title}: tilt from the vertical")
    fig.suptitle(f"{len(d)} planned poses, numbered as in the checklist")
    fig.tight_layout()
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
              label=(f"after + {', '.join(rep.selected)}" if rep.selected
                     else "whitened (no effect selected)"))
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
