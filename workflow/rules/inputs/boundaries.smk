# The input functions and helpers of boundaries.smk (included at its top).


def boundary_condition_names(obj):
    """The conditions that apply to the object, in table order."""
    return boundary_conditions(contract(obj), BOUNDARY_SETTINGS)


def boundary_libraries(obj, cond):
    """original, then rebuilt where the condition's kind is rebuilt."""
    return ["original"] + (["rebuilt"] if boundary_condition(contract(obj), cond, BOUNDARY_SETTINGS).rebuild else [])


def boundary_probe_b(obj):
    """The held-out probe the boundary tables report: the object's first Probe B."""
    return heldout_probes(obj)[0]


def boundary_library_root(obj, cond):
    return f"{BB}/{obj}/{cond}/lib"


def boundary_eval_rollout(obj, cond, probe, theta):
    return f"{BB}/{obj}/{cond}/eval/{theta_tag(theta)}/{probe}.parquet"


def boundary_eval_runs(wc):
    """A target's theta under Probe A (its query) and Probe B (its truth); an estimate's under Probe B."""
    theta = parse_theta(wc.theta)
    is_target = wc.theta in {theta_tag(th) for th in target_thetas().values()}
    probes = ([calibration_probe(wc.object)] if is_target else []) + [boundary_probe_b(wc.object)]
    return [{"theta": theta, "probe": pr, "rollout": boundary_eval_rollout(wc.object, wc.condition, pr, theta), "F": None}
            for pr in probes]


def boundary_query_rollouts(wc):
    return [boundary_eval_rollout(wc.object, wc.condition, calibration_probe(wc.object), th) for th in target_thetas().values()]


def boundary_library_csv(wc):
    if wc.library == "original":
        return f"{P}/descriptors/{wc.object}/library.csv"
    return f"{BB}/{wc.object}/{wc.condition}/descriptors/library.csv"


def boundary_writeback_rollouts(wc):
    """{"probe/theta": rollout}: Probe B of the frozen estimates and of the targets, under the condition."""
    est = checkpoints.boundary_estimate.get(object=wc.object, condition=wc.condition, library=wc.library).output.json[0]
    probe = boundary_probe_b(wc.object)
    ths = _estimate_thetas(est) + list(target_thetas().values())
    return {f"{probe}/{theta_tag(th)}": boundary_eval_rollout(wc.object, wc.condition, probe, th) for th in ths}


def boundary_metrics(obj):
    return [f"{BB}/{obj}/{c}/metrics/{lib}.csv" for c in boundary_condition_names(obj) for lib in boundary_libraries(obj, c)]


def loo_objects():
    """Objects of the leave-one-object-out table: all of them, given at least two."""
    return OBJECTS if BOUNDARIES["loo"] and len(OBJECTS) >= 2 else []


def loo_writeback_rollouts(wc):
    """{"probe/theta": rollout}: the main evaluation rollouts (Probe B) of the shared estimator's
    estimates and of the targets."""
    est = checkpoints.loo_estimate.get(object=wc.object).output.json[0]
    probe = boundary_probe_b(wc.object)
    ths = _estimate_thetas(est) + list(target_thetas().values())
    return {f"{probe}/{theta_tag(th)}": eval_rollout(wc.object, probe, th) for th in ths}
