"""The loop's resolution from a measured floor (private): the coarsest grid whose distance to a
finite-element reference is below the effects the loop is asked to name.

A floor table is the floor study's CSV (:func:`knockgs_core.experiments.floor_study`, written
as ``results/{profile}/tables/floor_{object}.csv`` by the workflow or by
``benchmarks/floor_levels.py``): one row per MPM level (``model`` = ``mpm``; ``n_grid``;
``rmse_pct``, the Probe-A trajectory RMSE against the reference in % of the reference's RMS
displacement; ``period_error_pct``; ``particles``, the level's particle count; ``mass_kg``, its
body's mass at the base material), then the reference's check (``fem (check)``: how far the
reference itself still moves) and the reference.

The rule: a model whose floor is at least half the effect it must name cannot tell the effect
from its own error (the loop's attribution compares the effect with the residual the floor
leaves, and the two are of the same size), so the loop runs at the coarsest level whose RMSE is
at most half the smallest effect to name. Where no level is, it runs at the finest and says
plainly that effects below about twice that level's floor cannot be named there.

A level at or finer than the reference's own grid is never within: the MPM there and the voxel
reference share the voxelized body cell for cell, so their gap leaves out the body's
discretization (the ci Pillow at n_grid 32 is 11 % from a reference at 32 and 39 % from one at
48; the default Pillow at 64 is 8 % from a reference at 64 whose own check moves 16 %). The
reference must be finer than the model it judges.

The table also measures the level's calibration bias: ``s_E_fit``, ``s_rho_fit``, the theta the
model at that level needs to reproduce the reference made at theta (1, 1). A theta calibrated
at that level carries a bias of that size, which no statistic of the data shows; the loop's theta
interval is widened on both sides by it, or by the most a model error of the floor's size could
bias the run's own fit where that is larger (:func:`widen_by_floor_bias`).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import InputError

__all__ = ["read_floor_table", "choose_resolution", "check_floor_body", "calibration_bias_log", "widen_by_floor_bias",
           "qualify_verdict"]

#: the columns a floor table must have
FLOOR_COLUMNS = ("model", "n_grid", "rmse_pct", "period_error_pct", "particles", "mass_kg")
#: the effect must be at least this many times the floor
MARGIN = 2.0


def read_floor_table(path):
    """The floor table at ``path`` (CSV), checked: the columns of :data:`FLOOR_COLUMNS`, at least
    one MPM level, each MPM row's ``n_grid`` a positive integer and its ``rmse_pct``, ``particles``
    and ``mass_kg`` finite and positive. Returns a ``pandas.DataFrame``; a file that is not a
    floor table raises :class:`~knockgs_core.errors.InputError` naming the file and the field."""
    import pandas as pd

    path = Path(path)
    try:
        table = pd.read_csv(path)
    except (OSError, ValueError, pd.errors.ParserError) as exc:
        raise InputError(path, "floor table", f"is not a readable CSV ({str(exc).splitlines()[0][:120]})") from None
    missing = [c for c in FLOOR_COLUMNS if c not in table.columns]
    if missing:
        raise InputError(path, missing[0], "missing: not a floor table (`knockgs_core.experiments.floor_study`'s CSV)")
    mpm = table[table["model"] == "mpm"]
    if mpm.empty:
        raise InputError(path, "model", "has no 'mpm' row: the table holds no MPM level")
    for col in ("n_grid", "rmse_pct", "particles", "mass_kg"):
        v = pd.to_numeric(mpm[col], errors="coerce").to_numpy(dtype=np.float64)
        if not (np.all(np.isfinite(v)) and np.all(v > 0)):
            raise InputError(path, col, "must be finite and positive in every 'mpm' row")
    if not np.all(mpm["n_grid"].to_numpy(dtype=np.float64) % 1 == 0):
        raise InputError(path, "n_grid", "must be a whole number of cells in every 'mpm' row")
    return table


def choose_resolution(table, *, smallest_effect: float, n_grid: int | None = None, source="floor table") -> dict:
    """The loop's grid from ``table`` (:func:`read_floor_table`): the coarsest MPM level whose
    RMSE is at most ``smallest_effect`` (a fraction of the response, e.g. 0.2 for an effect that
    changes the held-out response by 20 %) divided by :data:`MARGIN`, else the finest. With
    ``n_grid`` (a grid the loop is told), that level of the table, judged by the same rule.

    Returns a dict: ``n_grid``; ``within`` (whether that level's floor allows the effect);
    ``rmse_pct``, ``period_error_pct``, ``particles``, ``mass_kg`` (its row); ``theta_fit`` (its
    ``s_E_fit``, ``s_rho_fit``: the level's calibration bias; NaN where the table has none); ``check_rmse_pct``
    (the reference's check, NaN without one); ``smallest_effect``; ``levels`` (every MPM
    level's ``n_grid`` and ``rmse_pct``); ``source`` (str); ``statement``, the choice in words."""
    if not (math.isfinite(smallest_effect) and 0.0 < smallest_effect <= 1.0):
        raise InputError(source, "smallest_effect", f"must be a fraction in (0, 1], got {smallest_effect}")
    mpm = table[table["model"] == "mpm"].sort_values("n_grid")
    limit = 100.0 * smallest_effect / MARGIN
    ref = table[table["model"] == "fem (reference)"]
    ref_grid = float(ref["n_grid"].iloc[0]) if len(ref) and np.isfinite(ref["n_grid"].iloc[0]) else math.inf
    judged = mpm["n_grid"] < ref_grid                   # a reference judges the levels coarser than its own grid
    allowed = mpm[(mpm["rmse_pct"] <= limit) & judged]
    if n_grid is None:
        within = not allowed.empty
        row = (allowed if within else mpm).iloc[0 if within else -1]
    else:
        at = mpm[mpm["n_grid"] == int(n_grid)]
        if at.empty:
            raise InputError(source, "n_grid", f"has no MPM level at n_grid {n_grid} (its levels: "
                             f"{', '.join(str(int(v)) for v in mpm['n_grid'])}): the floor of that grid is not measured")
        row = at.iloc[0]
        within = bool(row["rmse_pct"] <= limit and row["n_grid"] < ref_grid)
    check = table[table["model"] == "fem (check)"]
    check_pct = float(check["rmse_pct"].iloc[0]) if len(check) and np.isfinite(check["rmse_pct"].iloc[0]) else math.nan
    name = Path(str(source)).name
    n, rmse, period = int(row["n_grid"]), float(row["rmse_pct"]), float(row["period_error_pct"])
    moves = f"; the reference itself moves {check_pct:.1f} % on its check" if math.isfinite(check_pct) else ""
    if row["n_grid"] >= ref_grid:
        moves += (f"; the reference (n_grid {int(ref_grid)}) is not finer than this level, so it cannot show this level's "
                  "floor (the two share the voxelized body)")
    if n_grid is not None:
        verdict = (f"within half the smallest effect to name ({100 * smallest_effect:.0f} % of the response)" if within
                   else f"effects smaller than about {MARGIN * rmse:.0f} % of the response cannot be named at this resolution")
        statement = (f"n_grid {n}, as told: the model there is {rmse:.1f} % from the finite-element reference of {name} "
                     f"(first-mode period {period:+.1f} %){moves}; {verdict}")
    elif within:
        statement = (f"n_grid {n}, the coarsest level of {name} within half the smallest effect to name "
                     f"({100 * smallest_effect:.0f} % of the response): the model there is {rmse:.1f} % from the "
                     f"finite-element reference (first-mode period {period:+.1f} %){moves}")
    else:
        statement = (f"no level of {name} is within half the smallest effect to name ({100 * smallest_effect:.0f} % of the "
                     f"response): the model at its finest, n_grid {n}, is {rmse:.1f} % from the finite-element reference "
                     f"(first-mode period {period:+.1f} %){moves}; effects smaller than about {MARGIN * rmse:.0f} % of the "
                     "response cannot be named at this resolution")
    fit = [float(row[k]) if k in row.index and np.isfinite(row[k]) and row[k] > 0 else math.nan
           for k in ("s_E_fit", "s_rho_fit")]
    return {"n_grid": n, "within": within, "theta_fit": fit, "rmse_pct": rmse, "period_error_pct": period,
            "particles": int(row["particles"]),
            "mass_kg": float(row["mass_kg"]), "check_rmse_pct": check_pct, "smallest_effect": float(smallest_effect),
            "levels": [[int(a), float(b)] for a, b in zip(mpm["n_grid"], mpm["rmse_pct"])], "source": str(source),
            "statement": statement}


def check_floor_body(choice: dict, contract, particles) -> None:
    """Refuse a floor table made for another body: the chosen level's particle count and mass
    (``contract``'s base material, its particles' rest volumes or their cells' share) must be the
    table's, ``contract`` being at the chosen grid."""
    from ..sim import body_volume

    source = choice["source"]
    if len(particles.positions) != choice["particles"]:
        raise InputError(source, "particles", f"n_grid {choice['n_grid']} has {choice['particles']} particles in the table "
                         f"and {len(particles.positions)} in {contract.name} ({contract.profile}) at that grid: the table "
                         "was made for another body")
    if set(contract.region_names) != {"base"}:
        raise InputError(contract.source, "regions", "a floor table's reference has one material region (base)")
    mass = body_volume(particles, contract.sim.grid_lim / contract.sim.n_grid) * float(contract.materials["base"].rho)
    if abs(mass - choice["mass_kg"]) > 1e-6 * max(abs(mass), 1e-30):
        raise InputError(source, "mass_kg", f"n_grid {choice['n_grid']} weighs {choice['mass_kg']:.6g} kg in the table and "
                         f"{mass:.6g} kg in {contract.name} ({contract.profile}): the table was made for another body "
                         "(another particle-volume rule or fill)")


def calibration_bias_log(choice: dict) -> list[float]:
    """The chosen level's calibration bias in log theta, ``|log theta_fit|`` per coordinate (0
    where the table has no fit)."""
    return [abs(math.log(f)) if math.isfinite(f) else 0.0 for f in choice["theta_fit"]]


def widen_by_floor_bias(interval, choice: dict, per_response=None) -> tuple[list, list]:
    """``interval`` ([[lo, hi], [lo, hi]] in (s_E, s_rho)) widened on both sides by what the
    chosen level's floor can do to theta: each bound scaled by ``exp(-+w)``, per coordinate the
    larger of

    - the level's calibration bias, ``|log theta_fit|`` (0 where the table has no fit): what
      the floor did to theta at theta (1, 1);
    - ``rmse_pct / 100`` times ``per_response`` [2] (the run's
      ``theta_uncertainty["theta_per_response_log"]``: the most a model error as large as the
      measured response could bias log theta in the run's own fit; None: not used): what a
      model error of the floor's size could do to theta at the run's estimate, whatever its
      shape. A floor above the effects lets an effect of the model's own error be named, and
      the fit then follows it; the bias at (1, 1) does not bound that.

    Returns (the interval, w)."""
    w = calibration_bias_log(choice)
    if per_response is not None:
        w = [max(wk, float(choice["rmse_pct"]) / 100.0 * float(x)) for wk, x in zip(w, per_response)]
    return [[float(lo) * math.exp(-wk), float(hi) * math.exp(wk)] for (lo, hi), wk in zip(interval, w)], w


def qualify_verdict(verdict: str, identified, choice: dict) -> str:
    """``verdict`` as the floor table qualifies it: where the chosen level's floor is not within
    half the smallest effect to name (``choice["within"]`` false) and the loop named effects
    (``identified``: their keys), the verdict says that they lie below what the model at this
    resolution can tell from its own error; else unchanged."""
    if choice["within"] or not identified:
        return verdict
    return (f"{verdict}; but the model at n_grid {choice['n_grid']} is {choice['rmse_pct']:.1f} % from the finite-element "
            f"reference, so {', '.join(identified)} cannot be told from the model's own error at this resolution")
