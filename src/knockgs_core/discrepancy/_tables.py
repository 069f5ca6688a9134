"""The table of planted-effect cases (CSV and Markdown) and its figure (private)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import atomic_write, write_text
from ._scoring import acceptance, world_acceptance

__all__ = ["TABLE_COLUMNS", "case_table", "write_case_table", "table_figure"]


TABLE_COLUMNS = [
    "case", "planted_effect", "identified_effect", "first_ranked", "heldout_traj_rmse_before", "heldout_traj_rmse_after",
    "calib_traj_rmse_before", "calib_traj_rmse_after", "theta_error_before_pct", "theta_error_after_pct",
    "heldout_traj_rmse_refit", "calib_traj_rmse_refit", "heldout_improvement", "planted_rank", "unexplained",
    "residual_excess_pct", "parameter", "planted_value", "estimated_value", "heldout_change", "theta_true", "theta_before",
    "theta_after", "observation", "n_simulations", "world", "verdict_kind", "theta_interval", "theta_in_interval",
    "model_error_coefficient", "approximation", "floor_pct", "floor_within", "accepted", "note",
]


def case_table(rows: list[dict]):
    """The table of cases (one row per case, :data:`TABLE_COLUMNS`), acceptance included: the
    standard rule (:func:`acceptance`) for cases of the loop's own world, the world rule
    (:func:`world_acceptance`) for the ``finer`` and ``fem`` worlds."""
    import pandas as pd

    out = []
    for row in rows:
        row = dict(row)
        row.setdefault("world", "same")
        rule = acceptance if row["world"] == "same" else world_acceptance
        row["accepted"], row["note"] = rule(row)
        out.append(row)
    return pd.DataFrame(out).reindex(columns=TABLE_COLUMNS)


#: columns of the Markdown table, and those shown with two decimals (percentages)
_MD_COLUMNS = [
    "case", "planted_effect", "identified_effect", "first_ranked", "heldout_traj_rmse_before", "heldout_traj_rmse_after",
    "calib_traj_rmse_before", "calib_traj_rmse_after", "theta_error_before_pct", "theta_error_after_pct",
    "planted_value", "estimated_value", "residual_excess_pct", "accepted",
]
_MD_PERCENT = ("theta_error_before_pct", "theta_error_after_pct", "residual_excess_pct")


def write_case_table(df, csv_path, md_path, *, title="Discrepancy loop: planted effects found and errors before/after") -> None:
    """Write the table as CSV (every column, ``%.6g``) and Markdown (a one-line acceptance
    summary and the main columns), each atomically.

    Not :func:`knockgs_core.reporting.write_table`: that one writes ``%.8g`` and every column
    with its own Markdown layout, which would change this table's bytes."""
    with atomic_write(csv_path, mode="w") as fh:
        df.to_csv(fh, index=False, float_format="%.6g")
    lines = [f"# {title}", "", f"{int(df['accepted'].sum())} of {len(df)} cases meet the acceptance rule.", ""]
    columns = list(_MD_COLUMNS)
    if "world" in df and (df["world"] != "same").any():
        columns[-1:-1] = ["world", "verdict_kind", "model_error_coefficient", "theta_interval", "theta_in_interval",
                          "approximation"]
        if "floor_within" in df and df["floor_within"].isin([True, False]).any():  # judged by a floor table
            columns[-1:-1] = ["floor_pct", "floor_within"]
    lines.append("| " + " | ".join(columns) + " |")
    lines.append("|" + "---|" * len(columns))
    for _, r in df.iterrows():
        cells = []
        for c in columns:
            v = r[c]
            if isinstance(v, float):
                cells.append(f"{v:.3g}" if c not in _MD_PERCENT else f"{v:.2f}")
            else:
                cells.append(str(v))
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "RMSE in normalized-domain metres over the Gaussian-associated particles and all frames, against the clean "
              "(noise-free) truth; theta error = 50 (|dsE|/sE + |dsR|/sR) %. 'before' = base calibration, "
              "'after' = the loop's final model.", ""]
    write_text(md_path, "\n".join(lines))


def table_figure(df, path) -> None:
    """Bar chart of the held-out and calibration trajectory RMSE before/after per case."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.arange(len(df))
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.5), sharey=True)
    panels = ((axes[0], "heldout", "held-out probe (never used in the loop)"), (axes[1], "calib", "calibration probe"))
    for ax, role, title in panels:
        ax.bar(x - 0.2, df[f"{role}_traj_rmse_before"], 0.4, label="before (base calibration)")
        ax.bar(x + 0.2, df[f"{role}_traj_rmse_after"], 0.4, label="after (loop)")
        ax.set_yscale("log")
        ax.set_xticks(x)
        ax.set_xticklabels([f"{c}\n-> {i}" for c, i in zip(df["case"], df["identified_effect"])], rotation=70, fontsize=7)
        ax.set_title(f"trajectory RMSE [m], {title}", fontsize=9)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    with atomic_write(path, mode="wb") as fh:
        fig.savefig(fh, format=Path(path).suffix.lstrip(".") or "png", dpi=100)
    plt.close(fig)
