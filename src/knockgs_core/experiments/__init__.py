"""The studies behind each table, one module per study.

Workflow scripts call one function here each. :mod:`._main` is the main benchmark
(descriptor tables, frozen estimates, Probe-A/B write-back evaluation, rendered frames);
:mod:`._convergence` the discretization study of the Probe-A response (time and space);
:mod:`._boundaries` the library's discretization and object boundaries (leave-one-object-out);
the paper's generalization diagnostics: :mod:`._splits` (alternative target splits, strict
gate), :mod:`._sensitivity` (library size, k x alpha) and :mod:`._identifiability`
(descriptor ambiguity, condition numbers); :mod:`._probe_shifts` (the frozen estimates under
another probe duration and contact) and :mod:`._passive` (passive versus active observation).
"""

from ._boundaries import (
    BOUNDARY_KINDS,
    BOUNDARY_LIBRARIES,
    BoundaryCondition,
    BoundarySettings,
    ConditionWorld,
    RESOLUTION_NEIGHBOURS,
    boundary_condition,
    boundary_conditions,
    boundary_note,
    boundary_table,
    condition_contract,
    condition_world,
    resolution_profile,
    loo_table,
    shared_library,
)
from ._identifiability import condition_table, identifiability_summary, pair_table, plot_identifiability
from ._sensitivity import (
    SensitivitySettings,
    k_alpha_grid,
    knn_reference,
    nested_subsets,
    plot_sensitivity,
    prediction_counts,
    size_sensitivity,
    size_summary,
)
from ._splits import plot_splits, split_row, splits_note, splits_table
from ._probe_shifts import (
    contact_table,
    duration_table,
    evaluate_shift,
    probe_impulse,
    probe_total_force,
    protocol_distance,
    shift_note,
)
from ._passive import (
    PASSIVE_PROBE,
    PassiveProtocol,
    error_directions,
    passive_active_note,
    passive_active_table,
    passive_protocol,
    passive_rollout,
    plot_passive_active,
    ratio_span_pct,
)
from ._convergence import NOT_ASYMPTOTIC, convergence_note, convergence_study, observed_order, plot_convergence
from ._main import (
    camera_from_contract,
    estimate_thetas,
    evaluate_method,
    file_sha256,
    frozen_estimate,
    library_table,
    oracle_estimate,
    query_table,
    render_metrics_rows,
    render_rollout,
    theta_tag,
    write_json,
)

__all__ = [
    "library_table",
    "query_table",
    "frozen_estimate",
    "oracle_estimate",
    "evaluate_method",
    "estimate_thetas",
    "file_sha256",
    "theta_tag",
    "write_json",
    "camera_from_contract",
    "render_rollout",
    "render_metrics_rows",
    "convergence_study",
    "convergence_note",
    "observed_order",
    "plot_convergence",
    "NOT_ASYMPTOTIC",
    "BOUNDARY_KINDS",
    "BOUNDARY_LIBRARIES",
    "BoundarySettings",
    "BoundaryCondition",
    "ConditionWorld",
    "RESOLUTION_NEIGHBOURS",
    "resolution_profile",
    "boundary_condition",
    "boundary_conditions",
    "condition_contract",
    "condition_world",
    "boundary_table",
    "boundary_note",
    "shared_library",
    "loo_table",
    "split_row",
    "splits_table",
    "splits_note",
    "plot_splits",
    "SensitivitySettings",
    "nested_subsets",
    "size_sensitivity",
    "size_summary",
    "knn_reference",
    "k_alpha_grid",
    "prediction_counts",
    "plot_sensitivity",
    "pair_table",
    "condition_table",
    "identifiability_summary",
    "plot_identifiability",
    "protocol_distance",
    "duration_table",
    "contact_table",
    "evaluate_shift",
    "shift_note",
    "probe_impulse",
    "probe_total_force",
    "PASSIVE_PROBE",
    "PassiveProtocol",
    "passive_protocol",
    "passive_rollout",
    "error_directions",
    "passive_active_table",
    "passive_active_note",
    "ratio_span_pct",
    "plot_passive_active",
]
