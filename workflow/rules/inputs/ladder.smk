# The input functions and helpers of ladder.smk (included at its top).


def ladder_library_runs(wc):
    """The library rollouts of chunk ``wc.chunk``, with the deformation gradients the video
    rungs render (a library written without them cannot be observed)."""
    if not LIBRARY_F:
        raise WorkflowError(f"config render.library_deformation_gradients is false (profile {PROFILE}), but the "
                            "observation ladder renders the library's rollouts: set it to true")
    return library_runs(wc.chunk, calibration_probe(wc.object), library_root(wc.object), export_F=True)


def ladder_target_runs(wc):
    """The split's targets as the ladder observes them: name, theta, Probe-A rollout and its
    deformation gradients (one run)."""
    need_eval_F("the observation ladder")
    probe = calibration_probe(wc.object)
    return [{"case_name": name, "theta": th, "rollout": eval_rollout(wc.object, probe, th, with_F=True),
             "F": eval_rollout(wc.object, probe, th, ".F.parquet")} for name, th in target_thetas(wc.split).items()]


def ladder_set_cases(obj, rung):
    """(probes, thetas) of a rung's diagnostics' set: its estimates under the first Probe B,
    each theta once, but those of a target (its evaluation rollout has it)."""
    targets = {theta_tag(th) for th in target_thetas(SPLIT).values()}
    thetas = {}
    for m in CONFIG_DEPLOYABLE:
        est = thetas_of(ladder_estimate_json(obj, rung, m))
        thetas.update({theta_tag(th): th for th in est.values() if theta_tag(th) not in targets})
    return [heldout_probes(obj)[0]], list(thetas.values())


def ladder_probe_b_rollouts(wc):
    """{"theta tag": rollout} under the first Probe B of every rung's estimates (the rungs'
    diagnostics' sets) and of the targets (their evaluation rollouts)."""
    probe = heldout_probes(wc.object)[0]
    out = {theta_tag(th): eval_rollout(wc.object, probe, th) for th in target_thetas(SPLIT).values()}
    for rung in LADDER_RUNGS:
        for (_, th), path in diag_set_paths(wc.object, f"ladder-{rung}").items():
            out.setdefault(theta_tag(th), path)
    return out


def ladder_table_inputs(wc):
    rollouts = ladder_probe_b_rollouts(wc)
    return {
        "estimates": [f"{P}/ladder/estimates/{wc.object}/{SPLIT}/{rung}/{m}.json" for rung in LADDER_RUNGS
                      for m in CONFIG_DEPLOYABLE],
        "observations": [f"{P}/ladder/observations/{wc.object}/lib/chunk{k}.csv" for k in range(len(LIBRARY_CHUNKS))]
        + [f"{P}/ladder/observations/{wc.object}/targets_{SPLIT}.csv"],
        "targets": "config/targets.csv",
        "rollouts": folders(rollouts.values()),
    }


def ladder_estimate_json(obj, rung, method):
    """A deployable method's estimate file of a rung, through the rung's checkpoint."""
    outputs = checkpoints.ladder_estimate.get(object=obj, split=SPLIT, rung=rung).output.json
    return outputs[CONFIG_DEPLOYABLE.index(method)]


def ladder_estimates(obj, rung):
    """Every deployable method's estimate file of a rung (through its checkpoint)."""
    return [ladder_estimate_json(obj, rung, m) for m in CONFIG_DEPLOYABLE]
