"""Sim-to-real gap diagnosis for the centrifuge and the gradiometer (effect dictionaries).

The same method as the static :func:`accelcal.diagnose` (GAP-DESIGN.md): fit the baseline
model, screen every candidate effect of the system's dictionary by principal angles
(identifiability: blind spots are reported, never "no effect") and a score test on its
projected Jacobian columns (chi2 when the noise model is known and the remainder is consistent
with it, sigma-free F otherwise), select forward-stepwise with a Bonferroni/Holm threshold (the
static diagnosis uses the exact min-p correction; these NumPy engines keep Bonferroni/Holm) and a
nonlinear re-fit after each step, and measure the leave-one-row-out held-out gap before and
after with the selection redone inside every fold; a selected effect that does not lower the
held-out gap is reported as "not_confirmed" (held-out gate, as in the static diagnosis).

Numerics: NumPy. The centrifuge baseline starts from the Rust :func:`accelcal.fit_centrifuge`
fit and the p-values come from the Rust special functions; Jacobian columns are central finite
differences of the residual function; the held-out folds use the model linearised at the
baseline fit (selection redone on the linear model in every fold).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from statistics import NormalDist
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._core import CalibrationError, DegenerateDataError
from .gap import GapReport

__all__ = [
    "CENTRIFUGE_EFFECTS",
    "GRADIOMETER_EFFECTS",
    "diagnose_centrifuge",
    "diagnose_gradiometer",
]

_F64 = NDArray[np.float64]

#: Centrifuge dictionary: effect -> (number of parameters, unit).
CENTRIFUGE_EFFECTS: dict[str, tuple[int, str]] = {
    "lever_along": (3, "mm"),
    "lever_across": (6, "mm"),
    "radius_error": (1, "mm"),
    "k3": (3, "ug/g^3"),
    "misalignment": (3, "mrad"),
    "cross_coupling": (6, "ug/g^2"),
    "rate_offset": (1, "urad/s"),
}

#: Gradiometer dictionary: effect -> unit (azimuth_error has one parameter per dwell).
GRADIOMETER_EFFECTS: dict[str, str] = {
    "drift": "E/h",
    "azimuth_error": "deg",
    "channel_scale": "%",
    "warmup": "E",
}

_CENTRIFUGE_FIX = {
    "lever_along": "add positions where each sensing axis is radial at several speeds "
    "(lever arms along an axis scale with omega^2 like the radial force)",
    "lever_across": "add positions with the spin axis inclined to the sensing axes "
    "(across-axis offsets enter through c3_i c3_j)",
    "radius_error": "add a speed where the radial force is small (or a 1 g reference): a "
    "radius error scales A^2 like a common scale error",
    "k3": "add speeds (at least three non-zero) and positions with both signs of each axis",
    "misalignment": "add positions between the axes (45 deg rotations of the fixture)",
    "cross_coupling": "add positions where two axes share the radial force (45 deg)",
    "rate_offset": "add speeds spanning a wider range (a rate offset changes A by 2 dw/w)",
}
_GRADIOMETER_FIX = {
    "drift": "record dwell times and use a time-symmetric (return-to-start) sequence",
    "azimuth_error": "use more azimuths than the minimum (each dwell's error needs redundancy)",
    "channel_scale": "use azimuths that rotate the gradient through both channels "
    "(a balanced set, e.g. 0/45/90/135 deg)",
    "warmup": "record from power-on over several warm-up time constants (a warm-up much longer "
    "than the session looks like a linear drift)",
}


def _chi2_sf(x: float, k: float) -> float:
    return float(_core.gap_chi2_sf(float(x), float(k)))


def _f_sf(f: float, d1: float, d2: float) -> float:
    return float(_core.gap_f_sf(float(f), float(d1), float(d2)))


# ----------------------------------------------------------------------------------------------
# Generic engine.


@dataclass
class _Problem:
    resid: Callable[[_F64], _F64]  # theta -> raw residual (N,), physical units
    sig: _F64  # (N,) noise std of each residual
    group: NDArray[np.int64]  # (N,) held-out group (row / dwell) of each residual
    n_base: int
    effects: dict[str, NDArray[np.int64]]  # parameter indices of each effect
    steps: _F64  # (P,) finite-difference steps
    noise_known: bool


def _jac(pb: _Problem, theta: _F64, idx: Sequence[int] | NDArray[np.int64]) -> _F64:
    n = pb.sig.size
    J = np.empty((n, len(idx)))
    for c, i in enumerate(idx):
        h = pb.steps[i]
        tp = theta.copy()
        tm = theta.copy()
        tp[i] += h
        tm[i] -= h
        J[:, c] = (pb.resid(tp) - pb.resid(tm)) / (2.0 * h) / pb.sig
    return J


def _whitened(pb: _Problem, theta: _F64) -> _F64:
    r = pb.resid(theta) / pb.sig
    return np.where(np.isfinite(r), r, 1e150)


def _fit(pb: _Problem, free: NDArray[np.int64], theta0: _F64) -> tuple[_F64, _F64, _F64, float]:
    """Gauss-Newton with step halving on the free parameters; returns theta, e, J(free), rss."""
    theta = theta0.copy()
    e = _whitened(pb, theta)
    rss = float(e @ e)
    for _ in range(30):
        J = _jac(pb, theta, free)
        dx = np.linalg.lstsq(J, -e, rcond=1e-12)[0]
        lam = 1.0
        ok = False
        while lam > 1e-4:
            tn = theta.copy()
            tn[free] += lam * dx
            en = _whitened(pb, tn)
            rn = float(en @ en)
            if rn <= rss:
                ok = True
                break
            lam *= 0.5
        if not ok:
            break
        done = rss - rn <= 1e-12 * (rss + 1e-300)
        theta, e, rss = tn, en, rn
        if done:
            break
    return theta, e, _jac(pb, theta, free), rss


def _orth(J: _F64) -> _F64:
    if J.shape[1] == 0:
        return np.zeros((J.shape[0], 0))
    d = np.linalg.norm(J, axis=0)
    d[~(d > 0)] = 1.0
    U, s, _ = np.linalg.svd(J / d, full_matrices=False)
    return U[:, s > 1e-9 * s.max()] if s.size and s.max() > 0 else np.zeros((J.shape[0], 0))


def _cov(J: _F64) -> _F64:
    """Unit covariance (J^T J)^+ with column scaling (scale-free rank decision)."""
    d = np.linalg.norm(J, axis=0)
    d[~(d > 0)] = 1.0
    Js = J / d
    return np.asarray(np.linalg.pinv(Js.T @ Js, rcond=1e-12, hermitian=True) / np.outer(d, d))


@dataclass
class _Screen:
    status: str
    sines: list[float]
    d: int = 0
    score: float = 0.0
    f: float = float("nan")
    p_f: float = float("nan")
    p_chi2: float = float("nan")
    p: float = float("nan")
    chi2_used: bool = False
    est: _F64 | None = None
    std: _F64 | None = None
    w: _F64 | None = None


def _screen(Q: _F64, e: _F64, rss: float, C: _F64, cfg: dict[str, Any], full: bool) -> _Screen:
    n = C.shape[0]
    norms = np.linalg.norm(C, axis=0)
    nmax = float(norms.max()) if norms.size else 0.0
    if not nmax > 0:
        return _Screen("blind", [])
    good = norms > 1e-12 * nmax
    Cn = C[:, good] / norms[good]
    Uc, sc, _ = np.linalg.svd(Cn, full_matrices=False)
    Uc = Uc[:, sc > 1e-8]
    if Uc.shape[1] == 0:
        return _Screen("blind", [])
    P = Uc - Q @ (Q.T @ Uc)
    Up, sp, _ = np.linalg.svd(P, full_matrices=False)
    kept = sp > cfg["sine_tol"]
    sines = sorted((float(x) for x in sp), reverse=True)
    if not kept.any():
        return _Screen("blind", sines)
    W = Up[:, kept]
    d = int(kept.sum())
    we = W.T @ e
    score = float(we @ we)
    dof2 = n - Q.shape[1] - d
    out = _Screen("testable", sines, d=d, score=score, w=W)
    if dof2 < 1:
        out.status = "too_few_rows"
        return out
    rem = max(rss - score, 1e-300)
    out.f = (score / d) / (rem / dof2)
    out.p_f = _f_sf(out.f, d, dof2)
    out.p_chi2 = _chi2_sf(score, d)
    mode = cfg["test"] if cfg["noise_known"] else "f"
    out.chi2_used = mode == "chi2" or (mode == "auto" and _chi2_sf(rem, dof2) > cfg["trust"])
    out.p = out.p_chi2 if out.chi2_used else out.p_f
    if full:
        Cp = C - Q @ (Q.T @ C)
        U2, s2v, Vt2 = np.linalg.svd(Cp, full_matrices=False)
        s2 = rem / dof2
        keep = s2v > cfg["sine_tol"] * nmax
        coef = (U2[:, keep].T @ e) / s2v[keep]
        out.est = -(Vt2[keep].T @ coef)  # the residual is reduced by e + C x -> x = -...
        out.std = np.sqrt(np.sum((Vt2[keep] / s2v[keep, None]) ** 2, axis=0) * s2)
    return out


def _stepwise(
    cands: list[str],
    cols: Callable[[Any, str], _F64],
    refit: Callable[[list[str], Any], Any],
    state0: Any,
    cfg: dict[str, Any],
    full: bool,
) -> dict[str, Any]:
    """Forward stepwise; state = (theta-like, e, Jfree, rss)."""
    active: list[str] = []
    step_p: list[float] = []
    history = [state0]
    first: dict[str, _Screen] = {}
    m_test = 0
    stop_p = float("nan")
    e_max = min(cfg["max_effects"], len(cands))
    cur = state0
    for step in range(e_max + 1):
        _, e, Jf, rss = cur
        Q = _orth(Jf)
        best: tuple[str, float] | None = None
        for c in cands:
            if c in active:
                continue
            sc = _screen(Q, e, rss, cols(cur, c), cfg, full and step == 0)
            if sc.status == "testable" and (best is None or sc.p < best[1]):
                best = (c, sc.p)
            if step == 0:
                m_test += sc.status == "testable"
                first[c] = sc
        if step == e_max:
            stop_p = best[1] if best else float("nan")
            break
        if best is None:
            break
        thr = cfg["alpha"] / max(m_test - step, 1)
        if not best[1] < thr:
            stop_p = best[1]
            break
        active.append(best[0])
        step_p.append(best[1])
        cur = refit(active, cur)
        history.append(cur)
    return {"effects": active, "step_p": step_p, "stop_p": stop_p, "history": history,
            "first": first}


def _run(pb: _Problem, theta0: _F64, cands: list[str], unavailable: dict[str, str],
         alpha: float, test: str, gate: str, loo: bool, max_effects: int,
         trust_level: float = 0.1) -> dict[str, Any]:
    if not 0 < alpha < 1:
        raise CalibrationError(f"alpha must be in (0, 1); got {alpha}")
    if test not in ("auto", "chi2", "f"):
        raise CalibrationError(f"test must be 'auto', 'chi2' or 'f'; got {test!r}")
    if gate not in ("auto", "strict", "off"):
        raise CalibrationError(f"gate must be 'auto', 'strict' or 'off'; got {gate!r}")
    base = np.arange(pb.n_base)
    theta_b, e_b, J_b, rss_b = _fit(pb, base, theta0)
    n = pb.sig.size
    rank0 = _orth(J_b).shape[1]
    dof = n - rank0
    if dof < 1:
        raise DegenerateDataError(f"{n} residuals cannot test a {rank0}-parameter baseline")
    if not pb.noise_known:
        pb.sig = pb.sig * math.sqrt(max(rss_b / dof, 1e-300))
        theta_b, e_b, J_b, rss_b = _fit(pb, base, theta_b)
    cfg = {"alpha": alpha, "test": test, "trust": trust_level, "sine_tol": 0.05,
           "noise_known": pb.noise_known, "max_effects": max_effects}

    def free_of(active: list[str]) -> NDArray[np.int64]:
        return np.concatenate([base] + [pb.effects[a] for a in active]).astype(np.int64)

    def cols_nl(state: Any, c: str) -> _F64:
        return _jac(pb, state[0], pb.effects[c])

    def refit_nl(active: list[str], state: Any) -> Any:
        return _fit(pb, free_of(active), state[0])

    sw = _stepwise(cands, cols_nl, refit_nl, (theta_b, e_b, J_b, rss_b), cfg, True)

    # Held-out gap: leave one group out, model linearised at the baseline fit, selection redone.
    groups = np.unique(pb.group)
    k_full = len(sw["effects"])
    g_steps: list[float] = []
    z_steps = np.full((k_full + 1, n), np.nan)
    r_steps = np.full((k_full + 1, n), np.nan)
    fold_counts = {c: 0 for c in cands}
    if loo and len(groups) > 2 and dof > int(np.bincount(pb.group).max()):
        Jall = _jac(pb, theta_b, np.arange(pb.steps.size))
        for gid in groups:
            out_m = pb.group == gid
            inn = ~out_m
            e0 = e_b[inn]
            Ji = Jall[inn]

            def lin(active: list[str], _s: Any = None, Ji: _F64 = Ji, e0: _F64 = e0) -> Any:
                fr = free_of(active)
                dx = np.linalg.lstsq(Ji[:, fr], -e0, rcond=1e-10)[0]
                e = e0 + Ji[:, fr] @ dx
                return (dx, e, Ji[:, fr], float(e @ e))

            def cols_lin(_s: Any, c: str, Ji: _F64 = Ji) -> _F64:
                return Ji[:, pb.effects[c]]

            swf = _stepwise(cands, cols_lin, lin, lin([]), cfg, False)
            for c in swf["effects"]:
                fold_counts[c] += 1
            for k in range(k_full + 1):
                kk = min(k, len(swf["effects"]))
                fr = free_of(swf["effects"][:kk])
                dx, _, Jf, _ = swf["history"][kk]
                Jo = Jall[out_m][:, fr]
                r = e_b[out_m] + Jo @ dx
                cov = _cov(Jf)
                qd = np.einsum("ij,jk,ik->i", Jo, cov, Jo)
                z_steps[k, out_m] = r / np.sqrt(1.0 + qd)
                r_steps[k, out_m] = r * pb.sig[out_m]
        g_steps = [float(np.sqrt(np.nanmean(z**2))) for z in z_steps]
    k_acc = k_full
    not_confirmed = None
    gate_note = None
    if gate != "off" and len(g_steps) == k_full + 1 and k_full:
        # Residual degrees of freedom a fold has left after the selected model: with fewer
        # than 2 the held-out prediction of a left-out group cannot judge the effect.
        n_max = int(np.bincount(pb.group).max())
        rank_k = _orth(sw["history"][k_full][2]).shape[1]
        fold_dof = n - n_max - rank_k
        if fold_dof < 2:
            gate_note = (
                f"leave-one-out with {len(groups)} groups is too small to judge "
                f"{', '.join(sw['effects'])} held out (a fold keeps {n - n_max} residuals for "
                f"{rank_k} parameters): the held-out gate was skipped, the in-sample test "
                "decides; record more dwells to confirm it held out")
    if gate != "off" and len(g_steps) == k_full + 1 and gate_note is None:
        for k in range(1, k_full + 1):
            adequate = False
            if gate == "auto" and pb.noise_known:
                _, _, Jk, rk = sw["history"][k]
                rank_k = _orth(Jk).shape[1]
                adequate = (n > rank_k and _chi2_sf(rk, n - rank_k) >= alpha
                            and g_steps[k] ** 2 <= 1.0 + 3.0 * math.sqrt(2.0 / n))
            if not g_steps[k] < g_steps[k - 1] and not adequate:
                k_acc = k - 1
                not_confirmed = (sw["effects"][k - 1], sw["step_p"][k - 1], g_steps[k - 1],
                                 g_steps[k])
                break
    return {"sw": sw, "k_acc": k_acc, "not_confirmed": not_confirmed, "g_steps": g_steps,
            "gate_note": gate_note,
            "z_steps": z_steps, "r_steps": r_steps, "fold_counts": fold_counts,
            "theta_b": theta_b, "e_b": e_b, "J_b": J_b, "rss_b": rss_b, "dof": dof,
            "rank0": rank0, "unavailable": unavailable, "cands": cands}


def _report(pb: _Problem, res: dict[str, Any], *, system: str, units: str,
            unit_of: dict[str, str], fixes: dict[str, str], alpha: float, g: float,
            noise_model: str, rows: dict[str, Any],
            where_extra: Callable[[_F64], dict[str, Any]], blind_fixed: list[dict[str, str]],
            names: list[str], statements: list[str], scale_out: float = 1.0) -> GapReport:
    sw = res["sw"]
    k_acc = res["k_acc"]
    n = pb.sig.size
    selected = list(sw["effects"][:k_acc])
    theta_f, e_f, J_f, rss_f = sw["history"][k_acc]
    e0 = res["e_b"]
    chi2 = float(res["rss_b"])
    dof = int(res["dof"])
    p_chi2 = _chi2_sf(chi2, dof) if pb.noise_known else float("nan")
    Q0 = _orth(res["J_b"])
    h = np.clip(np.sum(Q0**2, axis=1), 0.0, 0.999999)
    t_stud = e0 / np.sqrt(1.0 - h)
    thr = NormalDist().inv_cdf(1.0 - alpha / (2 * n))
    Qf = _orth(J_f)
    dof_after = n - Qf.shape[1]
    p_after = _chi2_sf(rss_f, dof_after) if pb.noise_known and dof_after > 0 else float("nan")
    # Parameter covariance after (scaled by the residual variance when above 1).
    cov = _cov(J_f)
    s2 = max(rss_f / dof_after, 1.0) if dof_after > 0 else 1.0
    free = np.concatenate([np.arange(pb.n_base)] + [pb.effects[a] for a in selected])
    std_all = np.full(pb.steps.size, np.nan)
    std_all[free] = np.sqrt(np.clip(np.diag(cov), 0, None) * s2)
    nf = float(n)

    def bic(rss: float, k: float) -> float:
        return nf * math.log(max(rss, 1e-300) / nf) + k * math.log(nf)

    bic_none = bic(chi2, res["rank0"])
    effects: list[dict[str, Any]] = []
    blind = list(blind_fixed)
    for c in names:
        if c in res["unavailable"]:
            effects.append({"effect": c, "unit": unit_of[c], "status": "not_testable",
                            "p_value": float("nan"), "test": "-", "p_f": float("nan"),
                            "p_chi2": float("nan"), "bic_weight": float("nan"),
                            "score": float("nan"), "d": 0, "estimate": np.array([np.nan]),
                            "std": np.array([np.nan]), "sines": []})
            blind.append({"effect": c, "reason": f"not testable: {res['unavailable'][c]} "
                          "(this is not 'no effect')"})
            continue
        sc = sw["first"][c]
        if c in selected:
            est = theta_f[pb.effects[c]].copy()
            sd = std_all[pb.effects[c]]
            status = "selected"
        else:
            est = sc.est if sc.est is not None else np.full(pb.effects[c].size, np.nan)
            sd = sc.std if sc.std is not None else np.full(pb.effects[c].size, np.nan)
            status = sc.status
        b_ = bic(chi2 - sc.score, res["rank0"] + sc.d) if sc.status == "testable" else np.nan
        effects.append({"effect": c, "unit": unit_of[c], "status": status, "p_value": sc.p,
                        "test": "chi2" if sc.chi2_used else "F", "p_f": sc.p_f,
                        "p_chi2": sc.p_chi2 if pb.noise_known else float("nan"),
                        "bic": b_, "bic_weight": float("nan"), "score": sc.score, "d": sc.d,
                        "estimate": np.asarray(est), "std": np.asarray(sd), "sines": sc.sines})
        if sc.status == "blind":
            blind.append({"effect": c, "reason": "every direction of it is absorbed by the "
                          "baseline parameters (principal-angle sines "
                          f"{', '.join(f'{s:.3f}' for s in sc.sines) or 'n/a'} < 0.05): not "
                          "testable with this design, NOT evidence of absence; to expose it: "
                          f"{fixes[c]}"})
        elif sc.status == "too_few_rows":
            blind.append({"effect": c, "reason": f"not testable: too few rows ({n}) for its "
                          f"{sc.d} direction(s); to expose it: {fixes[c]}"})
    bics = [e_["bic"] for e_ in effects if np.isfinite(e_.get("bic", np.nan))]
    bmin = min([bic_none] + bics)
    wsum = math.exp(-(bic_none - bmin) / 2) + sum(math.exp(-(b - bmin) / 2) for b in bics)
    for e_ in effects:
        if np.isfinite(e_.get("bic", np.nan)):
            e_["bic_weight"] = math.exp(-(e_["bic"] - bmin) / 2) / wsum
        e_.pop("bic", None)
    nc = res["not_confirmed"]
    if nc is not None:
        for e_ in effects:
            if e_["effect"] == nc[0]:
                e_["status"] = "not_confirmed"
        statements.append(
            f"{nc[0]} improves the in-sample fit (p = {nc[1]:.2g}) but does not reduce the "
            f"held-out gap (G {nc[2]:.2f} -> {nc[3]:.2f}): not an explanation")
    ambiguous: list[dict[str, Any]] = []
    if selected:
        wb = sw["first"][selected[0]].w
        rb = next(e_ for e_ in effects if e_["effect"] == selected[0])
        for e_ in effects:
            c = e_["effect"]
            if c == selected[0] or e_["status"] != "testable" or wb is None:
                continue
            wc = sw["first"][c].w
            if wc is None:
                continue
            cos = float(np.linalg.svd(wb.T @ wc, compute_uv=False).max())
            if cos > 0.9 and e_["bic_weight"] > 0.05 * rb["bic_weight"]:
                ambiguous.append({"effects": [selected[0], c], "cosine": cos,
                                  "experiment": f"{fixes[selected[0]]}; {fixes[c]}"})
    order = {"selected": 0, "not_confirmed": 1, "testable": 2}
    effects.sort(key=lambda x: (order.get(x["status"], 3),
                                x["p_value"] if math.isfinite(x["p_value"]) else 2.0))
    gs = res["g_steps"]
    g_b = gs[0] if gs else float("nan")
    g_a = gs[k_acc] if gs else float("nan")
    zb = res["z_steps"][0]
    za = res["z_steps"][k_acc]

    def rms(v: _F64) -> float:
        v = v[np.isfinite(v)]
        return float(np.sqrt(np.mean(v**2))) if v.size else float("nan")

    if not gs:
        statements.append("held-out gap not computed (too few rows)")
    if res["gate_note"]:
        statements.append(res["gate_note"])
    if pb.noise_known and p_chi2 < alpha:
        if not selected:
            statements.append("the gap is significant but no dictionary effect explains it: an "
                              "effect outside the dictionary or a mis-scaled noise model")
        elif p_after < alpha:
            statements.append(f"after {', '.join(selected)} a significant gap remains (chi2/dof "
                              f"{rss_f / max(dof_after, 1):.2f}): no dictionary effect fully "
                              "explains it")
    sig = pb.sig * scale_out
    dw = {"index": np.arange(n), "resid": pb.resid(res["theta_b"]) * scale_out, "e": e0,
          "t_stud": t_stud, "flag": np.abs(t_stud) > thr, "resid_after": e_f * sig,
          "e_after": e_f, "z_loo_before": zb, "z_loo_after": za, **rows}
    where = {"threshold": thr, "flagged": np.where(np.abs(t_stud) > thr)[0].tolist(),
             **where_extra(e0)}
    return GapReport(
        n=n, g=g, chi2=chi2, dof=dof, chi2_per_dof=chi2 / dof, p_value=p_chi2,
        noise_model=noise_model, held_out_gap=g_b, dwells=dw, where=where,
        best=selected[0] if selected else "none", selected=selected, effects=effects,
        ambiguous=ambiguous, blind_spots=blind,
        shrink=g_a / g_b if gs and g_b > 0 else float("nan"),
        held_out_gap_after=g_a,
        excess_remaining=(g_a - 1) / (g_b - 1) if gs and g_b > 1 else float("nan"),
        rms_before=rms(res["r_steps"][0]) * scale_out,
        rms_after=rms(res["r_steps"][k_acc]) * scale_out,
        remaining={"chi2": float(rss_f), "dof": float(dof_after), "p": p_after},
        statements=statements, params=res["theta_b"][: pb.n_base].copy(),
        params_after=theta_f.copy(), std_after=std_all, alpha=float(alpha), system=system,
        units=units,
        raw={"weight_none": math.exp(-(bic_none - bmin) / 2) / wsum, "step_p": sw["step_p"],
             "stop_p": sw["stop_p"], "fold_counts": res["fold_counts"], "g_steps": gs,
             "not_confirmed": nc},
    )


def _where_by(labels: NDArray[Any], name: str, key: str) -> Callable[[_F64], dict[str, Any]]:
    def f(e: _F64) -> dict[str, Any]:
        out = []
        for lab in np.unique(labels):
            sel = labels == lab
            out.append({name: f"{lab}", "segment": f"{lab}", "axis": f"{lab}",
                        "n": int(sel.sum()), "mean_e2": float(np.mean(e[sel] ** 2))})
        return {key: out}
    return f


# ----------------------------------------------------------------------------------------------
# Centrifuge.


def _centrifuge_layout(k: int) -> tuple[dict[str, NDArray[np.int64]], int]:
    idx: dict[str, NDArray[np.int64]] = {}
    p = 9
    for nm, (np_, _) in CENTRIFUGE_EFFECTS.items():
        idx[nm] = np.arange(p, p + np_)
        p += np_
    return idx, p


def _centrifuge_model(out: _F64, omega: _F64, radius: float, g: float, c3: _F64 | None,
                      idx: dict[str, NDArray[np.int64]]) -> Callable[[_F64], _F64]:
    w0 = np.abs(omega)
    c3z = np.zeros_like(out) if c3 is None else c3
    # Across-axis lever components, order (x:y, x:z, y:x, y:z, z:x, z:y).
    across = [(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)]

    def resid(th: _F64) -> _F64:
        S, b, k2 = th[0:3], th[3:6], th[6:9]
        k3 = 1e-6 * th[idx["k3"]]
        m = 1e-3 * th[idx["misalignment"]]
        cc = 1e-6 * th[idx["cross_coupling"]]
        u = (out - b) / S
        v = u.copy()
        v[:, 1] = u[:, 1] - m[0] * v[:, 0]
        v[:, 2] = u[:, 2] - m[1] * v[:, 0] - m[2] * v[:, 1]
        disc = np.maximum(1.0 + 4.0 * k2 * v, 1e-12)
        f = 2.0 * v / (1.0 + np.sqrt(disc))
        for _ in range(6):
            hc = np.zeros_like(f)
            dh = np.zeros_like(f)
            for j, (a, bb) in enumerate(across):
                hc[:, a] += cc[j] * f[:, a] * f[:, bb]
                dh[:, a] += cc[j] * f[:, bb]
            hres = f + k2 * f**2 + k3 * f**3 + hc - v
            f = f - hres / (1.0 + 2.0 * k2 * f + 3.0 * k3 * f**2 + dh)
        w = w0 + 1e-6 * th[idx["rate_offset"]][0]
        lev = np.zeros((3, 3))
        lev[np.arange(3), np.arange(3)] = 1e-3 * th[idx["lever_along"]]
        for j, (a, bb) in enumerate(across):
            lev[a, bb] = 1e-3 * th[idx["lever_across"]][j]
        proj = lev.diagonal()[None, :] - c3z * (c3z @ lev.T)
        fc = f + (w**2 / g)[:, None] * proj
        a_nom = w0**2 * radius / g
        a_true = w**2 * (radius + 1e-3 * th[idx["radius_error"]][0]) / g
        return np.asarray((np.sum(fc**2, axis=1) - a_true**2 - 1.0)
                          / (2.0 * np.sqrt(a_nom**2 + 1.0)))

    return resid


def diagnose_centrifuge(
    outputs: ArrayLike,
    omega: ArrayLike,
    radius: float,
    *,
    g: float = 9.80665,
    spin_axis: ArrayLike | None = None,
    sigma: float | ArrayLike | None = None,
    alpha: float = 0.05,
    effects: str | Sequence[str] = "all",
    loo: bool = True,
    max_effects: int = 3,
    test: str = "auto",
    gate: str = "auto",
) -> GapReport:
    """Diagnose the gap of a centrifuge session against the scale + bias + K2 norm model.

    Parameters
    ----------
    outputs : (k, 3) mean outputs per position and speed, g.
    omega : (k,) spin rate of each row, rad/s.
    radius : nominal radius, m.
    g : gravity used to express A = omega^2 R / g in g, m/s^2.
    spin_axis : (k, 3) spin-axis unit vector in the body frame per row; without it the lever
        arms are not testable (reported as such).
    sigma : noise std of each row's norm residual (scalar or (k,), g) or of each output
        ((k, 3), g, propagated to the norm); None: unit weights scaled to the baseline fit
        (F tests only, no absolute gap test).
    alpha : family-wise false-alarm level of the attribution.
    effects : "all" or names from :data:`CENTRIFUGE_EFFECTS`: ``lever_along`` (offset of each
        accelerometer along its own axis, mm), ``lever_across`` (the six across-axis offsets,
        mm), ``radius_error`` (mm), ``k3`` (ug/g^3), ``misalignment`` (the three observable
        small angles, mrad), ``cross_coupling`` (K_ij f_i f_j, i != j, ug/g^2) and
        ``rate_offset`` (spin-rate offset, e.g. the Earth rate Omega sin(latitude), urad/s).
    loo, max_effects, test, gate : as in :func:`accelcal.diagnose`.

    Returns
    -------
    GapReport (``system="centrifuge"``; residuals and RMS in g; estimates in the units above).
    """
    from .centrifuge import fit_centrifuge

    out = np.asarray(outputs, dtype=np.float64)
    if out.ndim != 2 or out.shape[1] != 3:
        raise CalibrationError(f"outputs must have shape (k, 3) in g; got {out.shape}")
    k = out.shape[0]
    om = np.asarray(omega, dtype=np.float64).reshape(-1)
    if om.shape != (k,):
        raise CalibrationError(f"omega must have {k} values (rad/s)")
    if not (np.all(np.isfinite(out)) and np.all(np.isfinite(om))):
        raise CalibrationError("outputs and omega must be finite")
    c3 = None
    if spin_axis is not None:
        c3 = np.asarray(spin_axis, dtype=np.float64)
        if c3.shape != out.shape:
            raise CalibrationError(f"spin_axis must have shape {out.shape}")
    names = _names(effects, list(CENTRIFUGE_EFFECTS))
    base = fit_centrifuge(out, om, radius, g=g, robust=False)
    idx, P = _centrifuge_layout(k)
    theta0 = np.zeros(P)
    theta0[:9] = base.params[:9]
    resid = _centrifuge_model(out, om, float(radius), float(g), c3, idx)
    noise_known = sigma is not None
    if sigma is None:
        sig = np.ones(k)
        noise_model = "unknown: unit weights scaled to the baseline fit (F tests only)"
    else:
        s_ = np.asarray(sigma, dtype=np.float64)
        if s_.ndim == 2:
            if s_.shape != out.shape:
                raise CalibrationError(f"sigma must be scalar, ({k},) or ({k}, 3)")
            # Propagate per-axis output noise to the norm: d r / d N_i = f_i / (S_i sqrt(A^2+1)).
            f = (out - base.bias) / base.scale
            a = om**2 * radius / g
            sig = np.sqrt(np.sum((f / base.scale * s_) ** 2, axis=1)) / np.sqrt(a**2 + 1.0)
        else:
            sig = np.broadcast_to(s_, (k,)).astype(np.float64).copy()
        if not np.all(sig > 0) or not np.all(np.isfinite(sig)):
            raise CalibrationError("sigma must be positive and finite")
        noise_model = "given noise std of each row"
    steps = np.ones(P)
    steps[:3] = 1e-6
    steps[3:6] = 1e-6
    steps[6:9] = 1e-7
    pb = _Problem(resid, sig, np.arange(k), 9, {n_: idx[n_] for n_ in names}, steps, noise_known)
    unavailable: dict[str, str] = {}
    if c3 is None:
        for nm in ("lever_along", "lever_across"):
            if nm in names:
                unavailable[nm] = "no spin_axis given (lever arms need the body-frame spin axis)"
    cands = [c for c in names if c not in unavailable]
    res = _run(pb, theta0, cands, unavailable, alpha, test, gate, loo, max_effects)
    speeds = np.round(om, 6)
    return _report(
        pb, res, system="centrifuge", units="g",
        unit_of={c: CENTRIFUGE_EFFECTS[c][1] for c in CENTRIFUGE_EFFECTS},
        fixes=_CENTRIFUGE_FIX, alpha=alpha, g=float(g), noise_model=noise_model,
        rows={"omega": om}, where_extra=_where_by(speeds, "omega", "segments"),
        blind_fixed=[{"effect": "common_scale_vs_radius", "reason": _radius_reason(om, radius,
                                                                                    g)}],
        names=names, statements=[])


def _radius_reason(om: _F64, radius: float, g: float) -> str:
    """Why a radius error and a common scale error are (nearly) aliased in this design."""
    sp = np.unique(np.round(np.abs(om), 6))
    sp = sp[sp > 0]
    a = sp**2 * radius / g
    if sp.size <= 1:
        return ("a radius error and a common scale error of A = omega^2 R / g are aliased: "
                "with a single speed they change every reading by the same factor; add speeds "
                "and an absolute radius measurement (or a 1 g reference)")
    return (f"a radius error changes A = omega^2 R / g by the same factor at all {sp.size} "
            f"speeds of this design (A = {', '.join(f'{x:.3g}' for x in a)} g), like a common "
            "scale error of the radial readings: more speeds do not separate them, only the "
            "1 g term differs and the per-axis scale factors absorb it (see the radius_error "
            "candidate's principal-angle sines); measure the radius independently or add a "
            "1 g reference")


def _names(effects: str | Sequence[str], known: list[str]) -> list[str]:
    if isinstance(effects, str):
        effects = known if effects == "all" else [effects]
    out = []
    for e in effects:
        if e not in known:
            raise CalibrationError(f"unknown effect {e!r}; known: {', '.join(known)}")
        if e not in out:
            out.append(e)
    return out


# ----------------------------------------------------------------------------------------------
# Gradiometer.


def diagnose_gradiometer(
    azimuth_deg: ArrayLike,
    outputs: ArrayLike,
    *,
    t: ArrayLike | None = None,
    sigma: float | ArrayLike | None = None,
    alpha: float = 0.05,
    effects: str | Sequence[str] = "all",
    warmup_tau_s: float = 600.0,
    loo: bool = True,
    max_effects: int = 3,
    test: str = "auto",
    gate: str = "auto",
) -> GapReport:
    """Diagnose the gap of a gradiometer start-up against ``y = bias + R(2 theta) gamma``.

    Parameters
    ----------
    azimuth_deg : (m,) commanded platform azimuths, deg.
    outputs : (m, 2) average inline and cross output per azimuth, E.
    t : (m,) dwell mid times, s (needed for drift and warm-up).
    sigma : noise std of an average (scalar or (m,), E); None: scaled to the baseline fit.
    alpha : family-wise false-alarm level of the attribution.
    effects : "all" or names from :data:`GRADIOMETER_EFFECTS`: ``drift`` (linear bias drift
        per channel, E/h), ``azimuth_error`` (one error per dwell, deg; a common offset is
        absorbed by the gradient and reported by the identifiability check), ``channel_scale``
        (inline/cross gain mismatch kappa and symmetric cross-talk mu, %) and ``warmup``
        (bias ``a exp(-(t - t0) / warmup_tau_s)`` per channel, E).
    warmup_tau_s : time constant of the warm-up term, s.
    loo, max_effects, test, gate : as in :func:`accelcal.diagnose`; held-out = leave one
        azimuth dwell (both channels) out.

    Returns
    -------
    GapReport (``system="gradiometer"``; residuals and RMS in E).
    """
    az = np.asarray(azimuth_deg, dtype=np.float64).reshape(-1)
    m = az.size
    y = np.asarray(outputs, dtype=np.float64)
    if y.shape != (m, 2):
        raise CalibrationError(f"outputs must have shape ({m}, 2) (inline, cross, E)")
    if not (np.all(np.isfinite(az)) and np.all(np.isfinite(y))):
        raise CalibrationError("azimuths and outputs must be finite")
    if m < 3:
        raise DegenerateDataError(f"{m} azimuths: the 4-parameter model needs at least 3")
    tt = None if t is None else np.asarray(t, dtype=np.float64).reshape(-1)
    if tt is not None and (tt.shape != (m,) or not np.all(np.isfinite(tt))):
        raise CalibrationError(f"t must have {m} finite values (s)")
    names = _names(effects, list(GRADIOMETER_EFFECTS))
    idx: dict[str, NDArray[np.int64]] = {}
    p = 4
    for nm, size in (("drift", 2), ("azimuth_error", m), ("channel_scale", 2), ("warmup", 2)):
        idx[nm] = np.arange(p, p + size)
        p += size
    th_h = np.zeros(m) if tt is None else (tt - tt.mean()) / 3600.0
    wu = np.zeros(m) if tt is None else np.exp(-(tt - tt.min()) / float(warmup_tau_s))
    azr = np.radians(az)

    def resid(th: _F64) -> _F64:
        ang = 2.0 * (azr + np.radians(th[idx["azimuth_error"]]))
        c, s = np.cos(ang), np.sin(ang)
        gi, gc = th[2], th[3]
        mi, mc = c * gi + s * gc, -s * gi + c * gc
        kap, mu = 1e-2 * th[idx["channel_scale"]]
        mi, mc = (1 + kap) * mi + mu * mc, mu * mi + (1 - kap) * mc
        dr, w = th[idx["drift"]], th[idx["warmup"]]
        yi = th[0] + mi + dr[0] * th_h + w[0] * wu
        yc = th[1] + mc + dr[1] * th_h + w[1] * wu
        return np.asarray(np.column_stack([y[:, 0] - yi, y[:, 1] - yc]).reshape(-1))

    noise_known = sigma is not None
    if sigma is None:
        sig = np.ones(2 * m)
        noise_model = "unknown: unit weights scaled to the baseline fit (F tests only)"
    else:
        s_ = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (m,))
        if not np.all(s_ > 0) or not np.all(np.isfinite(s_)):
            raise CalibrationError("sigma must be positive and finite (E)")
        sig = np.repeat(s_, 2).astype(np.float64)
        noise_model = "given noise std of each average"
    # Linear baseline start.
    c2, s2 = np.cos(2 * azr), np.sin(2 * azr)
    A = np.zeros((2 * m, 4))
    A[0::2, 0] = 1
    A[1::2, 1] = 1
    A[0::2, 2], A[0::2, 3] = c2, s2
    A[1::2, 2], A[1::2, 3] = -s2, c2
    if np.linalg.matrix_rank(A) < 4:
        raise DegenerateDataError("the azimuth set cannot separate bias and gradient "
                                  "(e.g. 0/180 deg): add an azimuth 45 or 90 deg away")
    theta0 = np.zeros(p)
    theta0[:4] = np.linalg.lstsq(A, y.reshape(-1), rcond=None)[0]
    steps = np.ones(p)
    steps[:4] = 1e-3
    steps[idx["azimuth_error"]] = 1e-3
    steps[idx["channel_scale"]] = 1e-3
    pb = _Problem(resid, sig, np.repeat(np.arange(m), 2), 4, {n_: idx[n_] for n_ in names},
                  steps, noise_known)
    unavailable: dict[str, str] = {}
    if tt is None:
        for nm in ("drift", "warmup"):
            if nm in names:
                unavailable[nm] = "no dwell times t given"
    cands = [c for c in names if c not in unavailable]
    res = _run(pb, theta0, cands, unavailable, alpha, test, gate, loo, max_effects)
    chan = np.tile(np.array(["inline", "cross"]), m)
    return _report(
        pb, res, system="gradiometer", units="E", unit_of=dict(GRADIOMETER_EFFECTS),
        fixes=_GRADIOMETER_FIX, alpha=alpha, g=float("nan"), noise_model=noise_model,
        rows={"azimuth_deg": np.repeat(az, 2), "channel": chan},
        where_extra=_where_by(chan, "channel", "axes"),
        blind_fixed=[{"effect": "common_azimuth_offset", "reason": "a common azimuth offset "
                      "rotates the estimated gradient and leaves the bias unchanged: no "
                      "start-up session can see it (it does not affect the bias)"}],
        names=names, statements=[])
