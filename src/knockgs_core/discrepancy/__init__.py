"""The discrepancy loop (SPEC §9): calibrate (s_E, s_rho) on measured trajectories, find the
residual, trace it to an effect the model lacks, add it, recalibrate, and report the error
before and after -- or say that no effect is missing, or that the residual stays
unexplained. See docs/discrepancy.md.

* :func:`read_measured` / :func:`write_measured`: measured point trajectories (Parquet,
  CSV, NPZ; with or without particle identity);
* :func:`run_discrepancy` -> :class:`DiscrepancyResult`; :class:`LoopSettings`,
  :class:`LibrarySource`;
* :func:`default_catalogue`: the candidate effects (:mod:`knockgs_core.sim` effects);
* :func:`write_report`: Markdown report with figures; :func:`run_files`: the loop from
  files to a report folder (the command line's and the workflow's entry point);
* :func:`make_case` / :func:`default_cases` (case definitions and generation, the truth
  side, never used by the loop), :func:`evaluate_case` / :func:`acceptance` (scoring
  against the truth), :func:`case_table` / :func:`write_case_table` / :func:`table_figure`
  (the table of cases); :func:`audit_truth_separation`: verdict that no run read the truth.
* :class:`AttributionRow` / :class:`AttributionRound`: one candidate's line and one round
  of the attribution (``DiscrepancyResult.rounds`` holds their dicts).
"""

from .._lazy import lazy_names

# Each name is imported from its module on first use, so that a caller who needs one study's
# names (a workflow file at parse time, a script) pays for that module alone, not for every
# study's imports (Warp among them).
_LAZY = {
    "._attribution": ("AttributionRound", "AttributionRow"),
    "._cases": ("default_cases", "make_case"),
    "._catalogue": ("CATALOGUE_KEYS", "Candidate", "CatalogueContext", "default_catalogue"),
    "._files": ("audit_truth_separation", "evaluate_files", "run_files"),
    "._loop": ("DiscrepancyResult", "LibrarySource", "LoopSettings", "run_discrepancy"),
    "._measured": ("Correspondence", "Measurement", "match_points", "read_measured", "write_measured"),
    "._planted": ("PLANTED_EFFECTS", "CaseSpec", "planted_change"),
    "._report": ("write_report", "write_result"),
    "._scoring": ("acceptance", "evaluate_case", "world_acceptance"),
    "._tables": ("case_table", "table_figure", "write_case_table"),
    "._views": ("residual_views", "view_summary"),
    "._worlds": ("FEM_EFFECTS", "FINER_EFFECTS", "finer_world_rollout", "make_world_case", "observe_world", "world_cases",
                 "world_contract"),
}
__getattr__, __dir__ = lazy_names(__name__, globals(), _LAZY)


__all__ = [
    "Measurement",
    "read_measured",
    "write_measured",
    "Correspondence",
    "match_points",
    "CATALOGUE_KEYS",
    "Candidate",
    "CatalogueContext",
    "default_catalogue",
    "LoopSettings",
    "LibrarySource",
    "AttributionRow",
    "AttributionRound",
    "DiscrepancyResult",
    "run_discrepancy",
    "residual_views",
    "view_summary",
    "write_report",
    "write_result",
    "PLANTED_EFFECTS",
    "CaseSpec",
    "default_cases",
    "make_case",
    "world_cases",
    "world_contract",
    "finer_world_rollout",
    "make_world_case",
    "observe_world",
    "planted_change",
    "FEM_EFFECTS",
    "FINER_EFFECTS",
    "world_acceptance",
    "evaluate_case",
    "case_table",
    "acceptance",
    "write_case_table",
    "table_figure",
    "run_files",
    "evaluate_files",
    "audit_truth_separation",
]
