"""Markdown report of a discrepancy run, with figures (private)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import atomic_write, write_json, write_npz, write_text
from ._loop import DiscrepancyResult
from ._resolution import calibration_bias_log
from ._views import VIEW_METRICS

__all__ = ["write_report", "write_result"]

_STAGE_LABEL = {"before": "before (base calibration)", "refit": "theta refit only", "after": "after (final model)"}


def write_result(result: DiscrepancyResult, out_dir) -> dict:
    """Write ``result.json`` (everything but arrays) and ``predictions.npz`` (predicted
    Gaussian-particle positions, keys ``{probe}/{stage}``) into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "result.json", result.to_dict())
    arrays = {f"{p}/{s}": a for p, stages in result.predictions.items() for s, a in stages.items()}
    write_npz(out / "predictions.npz", **arrays)
    return {"result": str(out / "result.json"), "predictions": str(out / "predictions.npz")}


def _figures(result: DiscrepancyResult, out: Path) -> list[tuple[str, str]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figs = []
    for probe, stages in result.views.items():
        fig, axes = plt.subplots(2, 3, figsize=(13, 7))
        t = stages["before"]["times"]
        ax = axes[0, 0]
        for s, st in stages.items():
            ax.plot(t, st["per_frame_rms"], label=_STAGE_LABEL[s])
        ax.axhline(result.noise["std"], color="k", ls=":", lw=1, label="noise std")
        ax.set_title("residual RMS per frame [m]")
        ax.set_xlabel("t [s]")
        ax.legend(fontsize=7)
        ax = axes[0, 1]
        ax.plot(t, stages["before"]["rms_curve_measured"], "k.", label="measured")
        for s, st in stages.items():
            ax.plot(t, st["rms_curve_simulated"], label=_STAGE_LABEL[s])
        ax.set_title("RMS displacement [m]")
        ax.set_xlabel("t [s]")
        ax.legend(fontsize=7)
        ax = axes[0, 2]
        for a, name in enumerate("xyz"):
            line, = ax.plot(t, stages["before"]["centroid_measured"][:, a], ".", label=f"measured {name}")
            ax.plot(t, stages["before"]["centroid_simulated"][:, a], "--", color=line.get_color(), lw=1)
            ax.plot(t, stages["after"]["centroid_simulated"][:, a], "-", color=line.get_color(), lw=1)
        ax.set_title("centroid displacement [m] (-- before, - after)")
        ax.set_xlabel("t [s]")
        ax.legend(fontsize=7)
        ax = axes[1, 0]
        f = stages["before"]["freq"][1:]
        ax.semilogy(f, np.linalg.norm(stages["before"]["spectrum_measured"][1:], axis=1) + 1e-30, "k.-", label="measured")
        for s, st in stages.items():
            ax.semilogy(f, np.linalg.norm(st["spectrum_simulated"][1:], axis=1) + 1e-30, label=_STAGE_LABEL[s])
        ax.set_title("centroid spectrum (norm over axes) [m]")
        ax.set_xlabel("f [Hz]")
        ax.legend(fontsize=7)
        ax = axes[1, 1]
        axis = "xyz"[stages["before"]["axis"]]
        ax.plot(t, stages["before"]["envelope_measured"], "k.", label="measured")
        for s, st in stages.items():
            ax.plot(t, st["envelope_simulated"], label=_STAGE_LABEL[s])
        ax.set_title(f"decay envelope of the {axis} centroid [m]")
        ax.set_xlabel("t [s]")
        ax.legend(fontsize=7)
        ax = axes[1, 2]
        for s in ("before", "after"):
            ax.hist(stages[s]["per_point_rms"], bins=40, alpha=0.6, label=_STAGE_LABEL[s])
        ax.set_title("per-point residual RMS [m]")
        ax.legend(fontsize=7)
        fig.suptitle(f"{result.object} / {probe}")
        fig.tight_layout()
        name = f"residuals_{probe}.png"
        with atomic_write(out / name, mode="wb") as fh:
            fig.savefig(fh, format="png", dpi=90)
        plt.close(fig)
        figs.append((probe, name))
    return figs


def _fmt(v, spec=".4g"):
    if isinstance(v, (float, np.floating)):
        return format(float(v), spec)
    return str(v)


def write_report(result: DiscrepancyResult, out_dir) -> str:
    """Write ``report.md`` with figures ``residuals_{probe}.png``, plus :func:`write_result`'s
    files, into ``out_dir``; returns the report path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_result(result, out)
    figs = _figures(result, out)
    L = (_calibration_lines(result) + _model_error_lines(result) + _error_lines(result) + _round_lines(result)
         + _figure_lines(figs))
    path = out / "report.md"
    write_text(path, "\n".join(L))
    return str(path)


def _calibration_lines(result: DiscrepancyResult) -> list[str]:
    """The verdict, the effects named and the calibration's summary."""
    L = [f"# Discrepancy report: {result.object} ({result.profile}), calibration probe {result.probe}", ""]
    L += [f"**Verdict:** {result.verdict}.", ""]
    if result.resolution:
        r = result.resolution
        levels = ", ".join(f"{n}: {e:.1f} %" for n, e in r["levels"])
        L += ["## Resolution", "", f"- {r['statement']}.",
              f"- the floor table's levels (n_grid: trajectory RMSE against the reference): {levels}"]
        w = r.get("theta_widening_log")
        if w and any(w):
            fit = r["theta_fit"]
            bias = calibration_bias_log(r)
            L.append(f"- the theta interval below is widened on both sides by what this level's floor can do to theta: "
                     f"{w[0]:.3g} and {w[1]:.3g} in log theta, the larger of its calibration bias, the theta it needs to "
                     f"reproduce the reference (s_E x {fit[0]:.3f}, s_rho x {fit[1]:.3f}: {bias[0]:.3g} and {bias[1]:.3g}), "
                     f"and the most a model error of the floor's size ({r['rmse_pct']:.1f} % of the response) could bias "
                     "this fit")
        elif w is not None:
            L.append("- the floor table has no theta fit at this level: the interval carries no calibration bias of it")
        L.append("")
    if result.effects:
        L += ["| effect | parameter | estimate | unit |", "|---|---|---|---|"]
        for e in result.effects:
            L.append(f"| {e['label']} (`{e['key']}`) | {e['parameter']} | {_fmt(e['value'])} | {e['unit']} |")
        L.append("")
    tb, tr, tf = result.theta_base, result.theta_refit, result.theta_final
    L += [
        "## Calibration",
        "",
        f"- base calibration ({result.base_method}): s_E = {tb[0]:.4f}, s_rho = {tb[1]:.4f}",
        f"- theta refit through the simulator: s_E = {tr[0]:.4f}, s_rho = {tr[1]:.4f}",
        f"- final model: s_E = {tf[0]:.4f}, s_rho = {tf[1]:.4f}"
        + (f", with {', '.join(result.identified)}" if result.identified else ""),
        f"- observation: {result.observation['points']} points x {result.observation['frames']} frames, "
        + ("with particle identity" if result.observation["identity"]
           else "no identity (matched at frame 0 to Gaussian particles)")
        + f"; fit window {result.observation['fit_frames']} frames, "
        f"validation window {result.observation['validation_frames']} frames",
        f"- noise std {result.noise['std']:.3g} m per coordinate ({result.noise['source']})",
        f"- residual at the end: RMS {result.residual['rms_per_point']:.3g} m per point, "
        f"{result.residual['excess_rms_per_point']:.3g} m above the noise "
        f"({100 * result.residual['excess_fraction_of_response']:.2f}% of the measured RMS displacement "
        f"{result.residual['measured_rms_displacement']:.3g} m)",
        f"- {result.n_simulations} simulations, {result.seconds:.1f} s",
    ]
    L += _interval_lines(result)
    return L


_NAMES = ("s_E", "s_rho")


def _bounds(lo: float, hi: float) -> str:
    left = "(0" if lo <= 0.0 else f"[{lo:.3f}"
    right = "inf)" if hi == float("inf") else f"{hi:.3f}]"
    return f"{left}, {right}"


def _interval_lines(result: DiscrepancyResult) -> list[str]:
    """The theta interval in words: its bounds, what they rest on (the fit's statistics, or the
    refinement and the floor's share), which sides are unbounded and why, and the continuum where the estimates allow
    one."""
    iv, u = result.theta_interval, result.theta_uncertainty
    if not iv:
        return []
    at = u.get("theta_at", {})
    fits = ", ".join(f"{k.replace('_', ' ')} ({v[0]:.3f}, {v[1]:.3f})" for k, v in at.items())
    L = [f"- theta interval (final model): s_E in {_bounds(*iv[0])}, s_rho in {_bounds(*iv[1])}; theta fitted by {fits}"]
    half = u["statistical_half_width_log"]
    if u["basis"] == "statistical":
        L.append(f"  - from the fit alone (2 sd and the step the fit still asks for: {half[0]:.3g} and {half[1]:.3g} in "
                 "log theta): the data show no discretization error of the model (its term's coefficient is at most "
                 "the ramp's start and no residual stays unexplained), so the refinement's change does not widen it")
    else:
        L.append(f"  - the data show the model's discretization error: the interval spans the refinement's change "
                 f"(its size on both sides) and the fit's statistics ({half[0]:.3g} and {half[1]:.3g} in log theta)")
        share = u.get("floor_share_log") or [0.0, 0.0]
        if any(share):
            L.append(f"  - and, on both sides, the floor's share ({share[0]:.3g} and {share[1]:.3g} in log theta): the "
                     "theta bias a model error of the kind the grid placements and the refinement make would hide "
                     "behind the residual left above the noise")
    cont = u.get("continuum") or [None, None]
    for k in range(2):
        if any(u["unbounded"][k]):
            side = "above" if u["unbounded"][k][1] else "below"
            L.append(f"  - {_NAMES[k]} is unbounded {side} (the refinement's side) and has no continuum value: "
                     f"{u['continuum_reason'][k]}")
        elif cont[k] is not None:
            L.append(f"  - {_NAMES[k]} extrapolated to the continuum: {cont[k]:.3f}"
                     + (f" (observed order {u['observed_order'][k]:.2f})" if u["observed_order"][k] is not None
                        else " (first order)"))
        elif u.get("asymptotic") is not None:
            L.append(f"  - {_NAMES[k]}: no continuum value: {u['continuum_reason'][k]}")
    return L


def _model_error_lines(result: DiscrepancyResult) -> list[str]:
    """The model's discretization term and floor (none without a refined model)."""
    L = []
    me = result.model_error
    if me:
        L += [
            "",
            "## The model's discretization error",
            "",
            f"Refined model: grid {me['refined_n_grid']}, fill {me['refined_fill_resolution']}, dt {me['refined_dt']:.3g} s, "
            f"{me['refined_particles']} particles (refinement ratio {me['refine_factor']:g}). Its change against the model, "
            f"less what theta absorbs, is the structured term: coefficient c = {me['coefficient']:.3f} "
            f"(0 <= c <= {me['coefficient_max']:g}; {me['richardson_coefficient']:g} is the continuum under first-order "
            f"convergence), RMS {me['term_rms_per_point']:.3g} m per point at c. The discretization floor of the validation "
            f"window is RMS {me['floor_rms_per_point']:.3g} m per point. Validation residual over the floors, minus 1: "
            f"{me['excess_without_term']:.3g} without the term (noise only), {me['excess_with_term']:.3g} with it "
            f"(noise + discretization floor).",
        ]
    return L


def _error_lines(result: DiscrepancyResult) -> list[str]:
    """The error before and after, per probe and stage."""
    L = []
    if result.approximation:
        L += ["", f"**Approximation, not added:** {result.approximation['note']}."]
    L += [
        "",
        "## Error before and after",
        "",
        "Against the measurement (noise included); held-out probes were never used in the loop.",
        "",
        "| probe | stage | " + " | ".join(VIEW_METRICS) + " |",
        "|---|---|" + "---|" * len(VIEW_METRICS),
    ]
    for probe, stages in result.metrics.items():
        role = "calibration" if probe == result.probe else "held-out"
        for s, m in stages.items():
            L.append(f"| {probe} ({role}) | {_STAGE_LABEL[s]} | " + " | ".join(_fmt(m[k], ".3g") for k in VIEW_METRICS) + " |")
    missing = [p for p in result.heldout_probes if p not in result.metrics]
    if missing:
        L += ["", f"Held-out probes predicted without a measurement to score against: {', '.join(missing)} "
              "(predictions in predictions.npz)."]
    return L


def _round_lines(result: DiscrepancyResult) -> list[str]:
    """Every attribution round: its decision and its ranked effects."""
    L = []
    L += ["", "## Attribution rounds", ""]
    for i, rd in enumerate(result.rounds, 1):
        L += [
            f"### Round {i}: model theta = ({rd['theta'][0]:.4f}, {rd['theta'][1]:.4f})"
            + (f", effects {', '.join(f'{k} = {u:.4g}' for k, u in rd['effects'])}" if rd["effects"] else ""),
            "",
            f"Residual energy on the validation window after re-tuning theta on the fit window: {rd['rss_theta_val']:.4g} m^2, "
            f"{1.0 + rd['excess_val']:.3g} x the floor (noise"
            + (f" + discretization {rd['model_floor_val']:.3g} m^2" if rd.get("model_floor_val") else "")
            + f"; {'significant' if rd['significant'] else 'not significant'}"
            + (f"; {1.0 + rd['excess_noise_val']:.3g} x the noise alone: {'visible' if rd['visible'] else 'not visible'}"
               if rd.get("model_floor_val") and "excess_noise_val" in rd else "")
            + "). "
            f"Decision: **{rd['decision']}**.",
            "",
            "| rank | effect | explained (validation) | explained (fit) | delta BIC (fit) | screen: explained (validation) "
            "| estimated parameter |",
            "|---|---|---|---|---|---|---|",
        ]
        for row in rd["table"]:
            if "error" in row:
                L.append(f"| {row['rank']} | {row['key']} | failed: {row['error']} | | | | |")
                continue
            refined = row["refined"]
            L.append(
                f"| {row['rank']} | {row['label']} (`{row['key']}`) | "
                + (f"{row['explained_val']:.3f}"
                   + (f" ({row['explained_excess']:.3f} beyond the floor)"
                      if rd.get("model_floor_val") and "explained_excess" in row else "")
                   + ("" if row.get("signature_ok", True) else f"; time signature off ({row['signature_share']:.2f})")
                   + ("; own term" if row.get("own_term") else "")
                   + f" | {row['explained_fit']:.3f} | {row['delta_bic']:.4g}" if refined
                   else "not refined | | ")
                + f" | {row['screen_explained_val']:.3f} | {row['parameter']} = {_fmt(row['value_estimate'])} {row['unit']} |"
            )
        if any(row.get("own_term") for row in rd["table"]):
            L.append("\n'own term': scored with the discretization term recomputed at the effect's fitted model "
                     "(a model with the effect moves under refinement in its own way).")
        for t in rd.get("tried") or []:
            if "error" in t:
                L.append(f"\nTried {t['key']}: joint recalibration failed ({t['error']}).")
            else:
                share = ("the residual lay within the noise and discretization floor" if t.get("within_floor")
                         else f"{100 * t['gain_over_excess']:.1f}% of the excess over the noise and discretization floor")
                L.append(f"\nTried {t['key']}: joint recalibration cut the residual energy from {t['rss_before']:.4g} to "
                         f"{t['rss_after']:.4g} m^2 ({share}).")
        L.append("")
    return L


def _figure_lines(figs) -> list[str]:
    L = []
    L += ["## Figures", ""]
    for probe, name in figs:
        L += [f"![residual views, {probe}]({name})", ""]
    L += [
        "Panels: residual RMS per frame; RMS-displacement curves; per-axis centroid curves; centroid spectrum; "
        "decay envelope (largest amplitude still to come) of the dominant centroid axis; "
        "per-point residual RMS (before vs after).",
        "",
    ]
    return L
