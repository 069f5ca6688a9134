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


def _simulated_before(obj, rung):
    """The tags of the thetas whose first Probe B is simulated outside ``rung``'s set: a target's
    and a main estimate's (their evaluation rollouts have it), and an earlier rung's estimates
    (that rung's set has it)."""
    done = {theta_tag(th) for th in target_thetas(SPLIT).values()}
    files = [estimate_json(obj, SPLIT, m) for m in CONFIG_DEPLOYABLE]
    files += [ladder_estimate_json(obj, r, m) for r in LADDER_RUNGS[: LADDER_RUNGS.index(rung)] for m in CONFIG_DEPLOYABLE]
    for path in files:
        done |= {theta_tag(th) for th in thetas_of(path).values()}
    return done


def ladder_set_cases(obj, rung):
    """(probes, thetas) of a rung's diagnostics' set: its estimates under the first Probe B,
    each theta once, but those simulated elsewhere (:func:`_simulated_before`): on the CPU the
    same theta's rollout is the same bytes wherever it is made."""
    done = _simulated_before(obj, rung)
    thetas = {}
    for m in CONFIG_DEPLOYABLE:
        est = thetas_of(ladder_estimate_json(obj, rung, m))
        thetas.update({theta_tag(th): th for th in est.values() if theta_tag(th) not in done})
    return [heldout_probes(obj)[0]], list(thetas.values())


def ladder_probe_b_rollouts(wc):
    """{"theta tag": rollout} under the first Probe B of every rung's estimates: the targets' and
    the main estimates' evaluation rollouts, then the rungs' diagnostics' sets in rung order
    (:func:`ladder_set_cases`)."""
    probe = heldout_probes(wc.object)[0]
    out = {theta_tag(th): eval_rollout(wc.object, probe, th) for th in target_thetas(SPLIT).values()}
    for m in CONFIG_DEPLOYABLE:
        for th in thetas_of(estimate_json(wc.object, SPLIT, m)).values():
            out.setdefault(theta_tag(th), eval_rollout(wc.object, probe, th))
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
    """The estimate files a rung's diagnostics' set is chosen from (through their checkpoints):
    every deployable method's of this rung and of the earlier rungs, and of the main route."""
    rungs = LADDER_RUNGS[: LADDER_RUNGS.index(rung) + 1]
    return ([ladder_estimate_json(obj, r, m) for r in rungs for m in CONFIG_DEPLOYABLE]
            + [estimate_json(obj, SPLIT, m) for m in CONFIG_DEPLOYABLE])
