"""Scoring a loop's run against the truth of its case, and the acceptance rule (private).

The truth side: only this module and :mod:`._cases` read a case's truth folder.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["evaluate_case", "interval_cells", "acceptance", "world_acceptance"]


def evaluate_case(result: dict, predictions: dict, truth_dir) -> dict:
    """One table row: the loop's ``result`` (its JSON dict) and ``predictions`` (arrays
    ``{probe}/{stage}`` [T, n_gs, 3]) scored against the truth in ``truth_dir``."""
    from ..metrics import joint_error_pct, trajectory_rmse

    truth_dir = Path(truth_dir)
    truth = json.loads((truth_dir / "truth.json").read_text())
    with np.load(truth_dir / "clean.npz") as z:
        clean = {"calib": z["calib"], "heldout": z["heldout"]}
    probes = {"calib": truth["calibration_probe"], "heldout": truth["heldout_probe"]}
    row = {"case": truth["case"], "planted_effect": truth["planted_effect"], "in_catalogue": truth["in_catalogue"]}
    rounds = result.get("rounds") or []
    table0 = rounds[0]["table"] if rounds else []
    row["identified_effect"] = result["identified_label"]
    row["first_ranked"] = table0[0]["key"] if table0 else "none"
    planted_rank = next((r["rank"] for r in table0 if r["key"] == truth["planted_effect"]), None)
    row["planted_rank"] = planted_rank if planted_rank is not None else ""
    row["unexplained"] = bool(result["unexplained"])
    for role in ("heldout", "calib"):
        for stage in ("before", "after", "refit"):
            P = predictions[f"{probes[role]}/{stage}"]
            row[f"{role}_traj_rmse_{stage}"] = trajectory_rmse(P, clean[role])
    th = tuple(truth["theta_true"])
    row["theta_true"] = f"({th[0]:.2f}, {th[1]:.2f})"
    row["theta_before"] = f"({result['theta_base'][0]:.3f}, {result['theta_base'][1]:.3f})"
    row["theta_after"] = f"({result['theta_final'][0]:.3f}, {result['theta_final'][1]:.3f})"
    row["theta_error_before_pct"] = joint_error_pct(result["theta_base"], th)
    row["theta_error_after_pct"] = joint_error_pct(result["theta_final"], th)
    pp = truth.get("planted_parameter") or {}
    row["planted_value"] = pp.get("value", "")
    est = {e["key"]: e for e in result.get("effects", [])}
    row["estimated_value"] = est[truth["planted_effect"]]["value"] if truth["planted_effect"] in est else ""
    row["parameter"] = pp.get("parameter", "")
    row["heldout_change"] = truth["heldout_change"]
    row["residual_excess_pct"] = 100.0 * result["residual"]["excess_fraction_of_response"]
    row["observation"] = truth["observation"]
    row["heldout_improvement"] = row["heldout_traj_rmse_before"] / max(row["heldout_traj_rmse_after"], 1e-30)
    row["n_simulations"] = result["n_simulations"]
    row["world"] = truth.get("world", "same")
    row["verdict_kind"] = result.get("verdict_kind", "")
    row["theta_interval"], row["theta_in_interval"] = interval_cells(result.get("theta_interval"), th)
    row["model_error_coefficient"] = (result.get("model_error") or {}).get("coefficient", "")
    row["approximation"] = (result.get("approximation") or {}).get("key", "")
    res = result.get("resolution") or {}     # the floor table's judgement of the loop's grid, where it had one
    row["floor_pct"] = res.get("rmse_pct", "")
    row["floor_within"] = res.get("within", "")
    return row


def interval_cells(interval, theta_true) -> tuple[str, bool]:
    """The table's two cells of a run's theta interval (``[[lo, hi] of s_E, [lo, hi] of s_rho]``
    as the result's JSON holds it: an unbounded side is ``"inf"``): its text and whether it
    holds ``theta_true`` (s_E, s_rho). Without an interval: ``("", False)``."""
    if not interval:
        return "", False
    iv = [[float(b) for b in pair] for pair in interval]
    text = f"[{iv[0][0]:.3f}, {iv[0][1]:.3f}] x [{iv[1][0]:.3f}, {iv[1][1]:.3f}]"
    return text, bool(all(iv[k][0] <= theta_true[k] <= iv[k][1] for k in range(2)))


def acceptance(row: dict) -> tuple[bool, str]:
    """The acceptance rule of one row: a planted catalogue effect is ranked first,
    identified, and the held-out RMSE drops at least 2x; the null case finds none; an
    effect outside the catalogue is not forced onto one and is reported unexplained."""
    planted = row["planted_effect"]
    if planted == "none":
        ok = row["identified_effect"] == "none" and not row["unexplained"]
        return ok, "none found" if ok else f"found {row['identified_effect']}"
    if not row["in_catalogue"]:
        ok = row["identified_effect"] == "none" and row["unexplained"]
        return ok, "unexplained, not forced" if ok else f"identified {row['identified_effect']}, unexplained={row['unexplained']}"
    ok1 = row["first_ranked"] == planted
    ok2 = row["identified_effect"].split("+")[0] == planted
    ok3 = row["heldout_improvement"] >= 2.0
    why = []
    if not ok1:
        why.append(f"ranked first: {row['first_ranked']}")
    if not ok2:
        why.append(f"identified {row['identified_effect']}")
    if not ok3:
        why.append(f"held-out drop {row['heldout_improvement']:.2f}x")
    return ok1 and ok2 and ok3, "; ".join(why) or "ranked first, identified, held-out drop >= 2x"


#: (world, planted effect) -> the catalogue terms that name it correctly, where the world's
#: effect is not one catalogue term: the FEM world's Rayleigh damping is mass-proportional
#: (the catalogue's velocity damping) plus stiffness-proportional (its material viscosity)
CORRECT_NAMES = {("fem", "damping"): ("damping", "viscosity")}


def world_acceptance(row: dict) -> tuple[bool, str]:
    """The acceptance rule of a case in a world the model cannot match (issue of worlds with a
    model-error floor): a planted catalogue effect is named (the first effect added) and the
    held-out RMSE drops at least 1.5x; with no effect planted, none is named and the theta
    interval holds the truth; an effect outside the catalogue is not named as a catalogue one
    (or is flagged an approximation) and the held-out prediction is not worse (2 % slack).
    A planted effect that two catalogue terms make up (:data:`CORRECT_NAMES`) is named by either.
    A run whose floor table put its grid's floor above half the smallest effect to name
    (``floor_within`` false: the run said that effects below about twice its floor cannot be named
    there, and qualified any it named) is judged by what it can show: its theta interval holds the
    truth."""
    planted = row["planted_effect"]
    named = row["identified_effect"].split("+")[0]
    if row.get("floor_within") is False:
        ok = bool(row["theta_in_interval"])
        return ok, (f"floor {row['floor_pct']:.1f} % above half the effect, said so; theta interval "
                    + ("holds the truth" if ok else "misses the truth"))
    if planted == "none":
        ok = named == "none" and bool(row["theta_in_interval"])
        return ok, "none named, theta interval holds the truth" if ok else (
            f"named {named}" if named != "none" else "theta interval misses the truth")
    if not row["in_catalogue"]:
        not_forced = named == "none" or bool(row.get("approximation"))
        not_worse = row["heldout_traj_rmse_after"] <= 1.02 * row["heldout_traj_rmse_before"]
        why = [] if not_forced else [f"named {named}"]
        if not not_worse:
            why.append("held-out prediction worse")
        return not_forced and not_worse, "; ".join(why) or "not forced onto the catalogue, held-out not worse"
    ok1 = named in CORRECT_NAMES.get((row.get("world", "same"), planted), (planted,))
    ok2 = row["heldout_improvement"] >= 1.5
    why = ([] if ok1 else [f"named {named}"]) + ([] if ok2 else [f"held-out drop {row['heldout_improvement']:.2f}x"])
    return ok1 and ok2, "; ".join(why) or "named, held-out drop >= 1.5x"
