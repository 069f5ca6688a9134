# The input functions and helpers of probe_shifts.smk (included at its top).


def passive_outputs(objects):
    return [
        path
        for o in objects
        for path in (f"{P}/tables/passive_active_{o}.csv", f"{P}/tables/passive_active_{o}.md",
                     f"{P}/tables/passive_active_targets_{o}.csv", f"{P}/figures/passive_active_{o}.png")
    ]


def shift_estimates(obj):
    """method -> frozen estimate file of the split, for every deployable method."""
    return {m: estimate_json(obj, SPLIT, m) for m in CONFIG_DEPLOYABLE}


def shift_cases(obj, probes, targets):
    """(probes, thetas): ``targets`` and every deployable estimate of them, each theta once."""
    truth = target_thetas()
    thetas = [truth[t] for t in targets]
    for m in shift_estimates(obj):
        est = estimated_thetas(obj, SPLIT, m)
        thetas += [est[t] for t in targets]
    return list(probes), list({theta_tag(th): th for th in thetas}.values())


def duration_inputs(wc):
    probe_a = [eval_rollout(wc.object, calibration_probe(wc.object), th) for th in target_thetas().values()]
    return {"estimates": list(shift_estimates(wc.object).values()), "targets": "config/targets.csv",
            "rollouts": diag_set_folder(wc.object, "duration"), "probe_a": folders(probe_a)}


def contact_inputs(wc):
    return {"estimates": list(shift_estimates(wc.object).values()), "targets": "config/targets.csv",
            "rollouts": diag_set_folder(wc.object, "contact")}


def passive_target_rollouts(obj, split):
    """target name -> its rollout under the passive protocol, in targets.csv order."""
    return {name: f"{P}/rollouts/{obj}/passive/targets_{split}/{theta_tag(th)}.parquet"
            for name, th in target_thetas(split).items()}
