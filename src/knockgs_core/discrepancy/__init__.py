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

from ._attribution import AttributionRound, AttributionRow
from ._cases import default_cases, make_case
from ._catalogue import CATALOGUE_KEYS, Candidate, CatalogueContext, default_catalogue
from ._files import audit_truth_separation, evaluate_files, run_files
from ._loop import DiscrepancyResult, LibrarySource, LoopSettings, run_discrepancy
from ._measured import Correspondence, Measurement, match_points, read_measured, write_measured
from ._planted import PLANTED_EFFECTS, CaseSpec
from ._report import write_report, write_result
from ._scoring import acceptance, evaluate_case, world_acceptance
from ._tables import case_table, table_figure, write_case_table
from ._views import residual_views, view_summary
from ._worlds import FEM_EFFECTS, FINER_EFFECTS, make_world_case, world_cases, world_contract

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
    "make_world_case",
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
