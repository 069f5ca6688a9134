"""The studies behind each table, one module per study.

Workflow scripts call one function here each. :mod:`._main` is the main benchmark
(descriptor tables, frozen estimates, Probe-A/B write-back evaluation, rendered frames);
:mod:`._convergence` the discretization study of the Probe-A response (time and space);
:mod:`._floor` the MPM at several resolutions against the finite-element reference (the floor);
:mod:`._boundaries` the library's discretization and object boundaries (leave-one-object-out);
the paper's generalization diagnostics: :mod:`._splits` (alternative target splits, strict
gate), :mod:`._sensitivity` (library size, k x alpha) and :mod:`._identifiability`
(descriptor ambiguity, condition numbers); :mod:`._probe_shifts` (the frozen estimates under
another probe duration and contact) and :mod:`._passive` (passive versus active observation);
:mod:`._ladder` (the observation ladder, from simulator particles to ID-free video tracks) and
:mod:`._cmaes` (CMA-ES direct video optimization, the alternative inverse route);
:mod:`._own_object` (one's own object calibrated from a measured Probe-A observation, the
library observed the same way).
"""

# Each name is imported from its module on first use, so that a caller who needs one study's
# names (a workflow file at parse time, a script) pays for that module alone, not for every
# study's imports (Warp among them).
_LAZY = {
    "._boundaries": ("BOUNDARY_KINDS", "BOUNDARY_LIBRARIES", "BoundaryStudyCondition", "BoundarySettings",
        "ConditionWorld", "RESOLUTION_NEIGHBOURS", "boundary_condition", "boundary_conditions", "boundary_note",
        "boundary_table", "condition_contract", "condition_world", "resolution_profile", "loo_table",
        "shared_library"),
    "._identifiability": ("condition_table", "identifiability_summary", "pair_table", "plot_identifiability"),
    "._sensitivity": ("SensitivitySettings", "k_alpha_grid", "knn_reference", "nested_subsets", "plot_sensitivity",
        "prediction_counts", "size_sensitivity", "size_summary"),
    "._splits": ("plot_splits", "split_row", "splits_note", "splits_table"),
    "._probe_shifts": ("contact_table", "duration_table", "evaluate_shift", "probe_impulse", "probe_total_force",
        "protocol_distance", "shift_note"),
    "._cmaes": ("CMAES_METHOD", "DEPTH_WEIGHT", "VideoScene", "candidate_bounds", "cmaes_calibrate",
        "cmaes_estimate", "cmaes_note", "cmaes_rows", "cmaes_table", "rollout_video", "video_depth_scale",
        "video_loss", "video_simulator"),
    "._own_object": ("BASE_THETA", "OBSERVE_TRACKS_DEFAULTS", "ObservationSettings", "as_stored",
        "calibration_report", "camera_from_dict", "camera_to_dict", "calibration_rows", "estimate_summary",
        "measured_observation", "observe_frames", "observe_rollout", "plot_calibration"),
    "._ladder": ("LadderSettings", "ladder_note", "ladder_rungs", "ladder_table", "plot_ladder", "rung_descriptors"),
    "._passive": ("PASSIVE_PROBE", "PassiveProtocol", "error_directions", "passive_active_note",
        "passive_active_table", "passive_protocol", "passive_rollout", "plot_passive_active", "ratio_span_pct"),
    "._floor": ("FloorSettings", "at_resolution", "body_volume", "cells_through", "enclosed_empty_cells",
        "fit_theta", "floor_note", "floor_study", "kept_reference_files", "plot_floor", "probe_period"),
    "._convergence": ("NOT_ASYMPTOTIC", "convergence_note", "convergence_study", "observed_order", "plot_convergence"),
    "._main": ("camera_from_contract", "estimate_thetas", "evaluate_method", "evaluate_methods", "file_sha256",
        "frozen_estimate", "library_table", "oracle_estimate", "query_table", "render_metrics_rows",
        "render_rollout", "theta_tag"),
}
_MODULE_OF = {name: module for module, names in _LAZY.items() for name in names}


def __getattr__(name):
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_MODULE_OF))


__all__ = [
    "library_table",
    "query_table",
    "frozen_estimate",
    "oracle_estimate",
    "evaluate_method",
    "evaluate_methods",
    "estimate_thetas",
    "file_sha256",
    "theta_tag",
    "camera_from_contract",
    "render_rollout",
    "render_metrics_rows",
    "convergence_study",
    "convergence_note",
    "observed_order",
    "plot_convergence",
    "FloorSettings",
    "at_resolution",
    "cells_through",
    "enclosed_empty_cells",
    "body_volume",
    "probe_period",
    "fit_theta",
    "floor_study",
    "kept_reference_files",
    "floor_note",
    "plot_floor",
    "NOT_ASYMPTOTIC",
    "BOUNDARY_KINDS",
    "BOUNDARY_LIBRARIES",
    "BoundarySettings",
    "BoundaryStudyCondition",
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
    "LadderSettings",
    "ladder_rungs",
    "rung_descriptors",
    "ladder_table",
    "ladder_note",
    "plot_ladder",
    "BASE_THETA",
    "OBSERVE_TRACKS_DEFAULTS",
    "ObservationSettings",
    "as_stored",
    "camera_to_dict",
    "camera_from_dict",
    "observe_frames",
    "observe_rollout",
    "measured_observation",
    "estimate_summary",
    "calibration_rows",
    "calibration_report",
    "plot_calibration",
    "CMAES_METHOD",
    "DEPTH_WEIGHT",
    "VideoScene",
    "candidate_bounds",
    "cmaes_calibrate",
    "cmaes_estimate",
    "cmaes_note",
    "cmaes_rows",
    "cmaes_table",
    "rollout_video",
    "video_depth_scale",
    "video_loss",
    "video_simulator",
]
