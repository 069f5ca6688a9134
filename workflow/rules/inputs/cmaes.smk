# The input functions and helpers of cmaes.smk (included at its top).


def cmaes_target_rollouts(obj, split):
    """target name -> {"rollout", "F"}: its Probe-A evaluation rollout and deformation
    gradients (the video CMA-ES fits), in targets.csv order."""
    need_eval_F("the CMA-ES video route")
    probe = calibration_probe(obj)
    return {name: {"rollout": eval_rollout(obj, probe, th, with_F=True), "F": eval_rollout(obj, probe, th, ".F.parquet")}
            for name, th in target_thetas(split).items()}


def cmaes_estimate_file(obj, split, seed):
    """The CMA-ES estimate file of (object, split, seed), as a plain path: listing every seed's
    file as an input schedules the seeds' jobs side by side."""
    return f"{P}/cmaes/estimates/{obj}/{split}/seed{seed}.json"


def cmaes_json(obj, split, seed):
    """The same file through its checkpoint, for input functions that read its thetas (they are
    evaluated again once it exists)."""
    return checkpoints.cmaes_estimate.get(object=obj, split=split, seed=str(seed)).output.json


def cmaes_eval_paths(obj, split, seeds, path_of):
    """{"probe/theta": path_of(obj, probe, theta)} of every seed's frozen CMA-ES estimates and of
    the split's targets under every evaluation probe (path_of: eval_rollout or frames_file)."""
    thetas = list(target_thetas(split).values())
    for seed in seeds:
        thetas += _estimate_thetas(cmaes_json(obj, split, seed))
    return {f"{pr}/{theta_tag(th)}": path_of(obj, pr, th) for pr in eval_probes(obj) for th in thetas}
